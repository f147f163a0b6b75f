"""Obstacle points from 3D stereo points: Kratos' Algorithm 1 (a simplified Manduchi et al. 2005).

Two points P and Q are *compatible*, and both are obstacle points, when Q is nearly above P:

    |depth(Q) - depth(P)|   < max_depth_diff   (0.3 m)
    min_height_diff < |height(Q) - height(P)| < max_height_diff   (0.3 m, 0.5 m)
    |height(Q) - height(P)| / |lateral(Q) - lateral(P)| > tan(min_angle)   (80 deg)

in the VEHICLE frame: depth is x (forward), lateral is y, height is z. Unlike Manduchi's test it
needs no ground plane, so flat, sloped and rough ground all pass as long as it does not rise
0.3 m within 0.3 m of depth.

Where to look for Q. Kratos searches the inverted triangle of pixels above P. A vertical surface
at camera depth Z climbs f/Z rows per metre, and f/Z = disparity/baseline, so the Q that are
0.3-0.5 m above P lie ``disparity * [0.3, 0.5] / baseline`` rows up (for RASCAL's 0.3 m baseline:
1 to 1.67 disparities). Instead of every pixel of that window, ``samples`` rows spread evenly
over it are tried (Kratos likewise examines every other point of its triangle), in P's own
column: a window of 9-60 rows shrinks to 4 gathers per pixel, vectorised over the whole image.

Pixels on depth edges (``depth_edges``) are not tried as P: the matcher smears an edge into a
strip of in-between disparities, upright like both sides, which would bridge a near obstacle and
one behind it into one cluster.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ObstaclePointParams:
    max_depth_diff_m: float = 0.3
    min_height_diff_m: float = 0.3
    max_height_diff_m: float = 0.5
    min_angle_deg: float = 80.0
    samples: int = 4  # rows tried in each pixel's window
    edge_span_px: int = 3  # a pixel whose disparity differs by more than edge_step_px between
    edge_step_px: float = 1.0  # edge_span_px left and right of it sits on a depth edge: not used

    def __post_init__(self) -> None:
        if not 0 <= self.min_height_diff_m < self.max_height_diff_m:
            raise ValueError("need 0 <= min_height_diff_m < max_height_diff_m")
        if not 0 <= self.min_angle_deg < 90 or self.samples < 1 or self.max_depth_diff_m <= 0:
            raise ValueError("need 0 <= min_angle_deg < 90, samples >= 1 and max_depth_diff_m > 0")
        if self.edge_span_px < 0 or self.edge_step_px <= 0:
            raise ValueError("need edge_span_px >= 0 (0: no edge test) and edge_step_px > 0")


def depth_edges(disparity: np.ndarray, span_px: int, step_px: float) -> np.ndarray:
    """Pixels on a depth edge: their disparity ``span_px`` columns to the left and to the right
    differ by more than ``step_px``. The matcher's blocks smear a depth edge over several
    columns of in-between disparities, which stand as upright as either side and would join the
    near and the far obstacle into one; the face of an upright obstacle changes disparity by
    under 0.05 px per column even 60 deg to the line of sight."""
    edges = np.zeros(disparity.shape, dtype=bool)
    if span_px > 0:
        step = np.abs(disparity[:, 2 * span_px :] - disparity[:, : -2 * span_px])
        edges[:, span_px:-span_px] = step > step_px
    return edges


def compatible(
    p: tuple[np.ndarray, np.ndarray, np.ndarray],
    q: tuple[np.ndarray, np.ndarray, np.ndarray],
    params: ObstaclePointParams,
) -> np.ndarray:
    """Algorithm 1's test on (x, y, z) arrays of points P and Q; False where either is NaN."""
    height = np.abs(q[2] - p[2])
    return (
        (np.abs(q[0] - p[0]) < params.max_depth_diff_m)
        & (height > params.min_height_diff_m)
        & (height < params.max_height_diff_m)
        & (height > math.tan(math.radians(params.min_angle_deg)) * np.abs(q[1] - p[1]))
    )


def window_rows(disparity: np.ndarray, baseline_m: float, params: ObstaclePointParams) -> np.ndarray:
    """(samples, ...) int32 row offsets upwards from P where Q is tried: evenly inside the window."""
    heights = params.min_height_diff_m + (np.arange(params.samples) + 0.5) / params.samples * (
        params.max_height_diff_m - params.min_height_diff_m
    )
    rows_per_px = (heights / baseline_m).astype(np.float32)  # float32: the planes' type, half the traffic
    return np.stack([np.rint(disparity * k).astype(np.int32) for k in rows_per_px])


def obstacle_points(
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    disparity: np.ndarray,
    baseline_m: float,
    params: ObstaclePointParams | None = None,
    min_disparity_px: float = 0.0,
) -> np.ndarray:
    """Boolean mask of the obstacle points among (rows, columns) planes of VEHICLE coordinates,
    NaN where there is no point; ``disparity`` of the same pixels sizes each pixel's window.
    Pixels below ``min_disparity_px`` are not tried as P: far away, where disparity noise
    swamps the depth test, a matcher's flat patch of one disparity reads as a wall."""
    params = params or ObstaclePointParams()
    if not x.shape == y.shape == z.shape == disparity.shape or x.ndim != 2:
        raise ValueError("x, y, z and disparity must be 2-D arrays of one shape")
    width = np.int32(x.shape[1])
    flat_x, flat_y, flat_z = x.ravel(), y.ravel(), z.ravel()
    usable = (
        (disparity >= min_disparity_px)
        & np.isfinite(z)
        & ~depth_edges(disparity, params.edge_span_px, params.edge_step_px)
    )
    # int32 indices: half the memory traffic of the default int64 in every step below.
    p_index = np.flatnonzero(usable).astype(np.int32)
    p_x, p_disparity = flat_x.take(p_index), disparity.ravel().take(p_index)
    mask = np.zeros(x.size, dtype=bool)
    for up in window_rows(p_disparity, baseline_m, params):
        q_index = p_index - up * width  # negative: above the image ("clip" keeps it addressable)
        # The depth test alone rejects nearly all the ground: the whole test only on what passes it.
        depth_ok = np.abs(flat_x.take(q_index, mode="clip") - p_x) < params.max_depth_diff_m
        near = np.flatnonzero(depth_ok & (up >= 1) & (q_index >= 0))
        p_near, q_near = p_index[near], q_index[near]
        p = (p_x[near], flat_y[p_near], flat_z[p_near])
        hit = compatible(p, (flat_x[q_near], flat_y[q_near], flat_z[q_near]), params)
        mask[p_near[hit]] = True
        mask[q_near[hit]] = True
    return mask.reshape(x.shape)
