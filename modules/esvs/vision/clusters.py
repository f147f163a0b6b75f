"""Obstacle points -> compact Obstacle descriptors in the VEHICLE frame.

Points are grouped on a bird's-eye occupancy grid in *column-disparity* coordinates (bearing and
inverse range) rather than metres: stereo depth noise grows with the square of range (0.06 m at
10 m, 0.7 m at 35 m for 1/8 px of disparity noise on this rig) while disparity noise is the same
everywhere, so one cell size groups a near rock and a far one equally well. Occupied cells are
joined by cv2.connectedComponents; each component is one obstacle.

What a descriptor says: stereo sees the surfaces facing the cameras, not what is behind them.
The box is fitted to the visible surface's *profile*: per column bin, the median range of its
points at the bin's outermost bearings. Depth noise lies along each ray and bearings are exact, so
the median takes the noise out of the depth (0.7 m at 35 m for one point) and keeps the surface's
outline; the outermost 2 % of bearings are left out as strays. The rectangle is the one whose
sides the profile lies on (an L-shape fit), so a box seen at an angle comes out turned with it
(``yaw_rad``). A rectangle square to the vehicle round all the points reached 0.3-0.5 m beyond a
box's sides once the vehicle had turned, enough to close a gate. ``x_m``/``y_m``/``length_m``/
``width_m`` are that rectangle: length along ``yaw_rad``, turned by at most 45 deg, so a face seen
head-on has yaw 0 and a length of its visible depth.
``height_m`` is its top above the vehicle's ground plane (98 %; a lower bound when the top is
above the matched band), ``range_m`` the distance from the vehicle origin to its nearest part: the
20th percentile of its points' ranges, low enough to favour the near face of a deep object, high
enough that depth noise (symmetric in disparity) biases a flat face short by under 1 sigma.
``confidence`` grows with the number of points and falls with their disparity spread.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from protocol.messages import Obstacle

# Orientations tried for a descriptor's rectangle, 3 deg apart, yaw 0 first.
_CANDIDATE_YAWS = np.radians(np.r_[np.arange(0.0, 46.0, 3.0), np.arange(-3.0, -45.0, -3.0)])


@dataclass(frozen=True)
class ClusterParams:
    column_bin_px: int = 4
    disparity_bin_px: float = 0.25  # 0.5 merged obstacles ~1 px apart (simulated-scene recall 94.5 -> 95.8 %)
    min_cell_points: int = 2  # a cell with fewer points is noise
    min_points: int = 25  # an obstacle needs this many points
    confidence_points: float = 150.0  # confidence = (1 - exp(-points / this)) * consistency
    consistency_px: float = 0.75  # consistency = share of points this close to the median disparity
    max_obstacles: int = 16  # nearest first: 16 descriptors fit one 1400 B datagram
    # A cluster topping out this low is the far wall of a ditch seen from above (SGBM gives the
    # wall one disparity, so it passes Algorithm 1), not an obstacle. Assumes level ground.
    min_top_m: float = 0.15
    side_tolerance_m: float = 0.05  # closer to a side than this counts as on it (rectangle fit)
    profile_min_share: float = 0.25  # a column bin with fewer points than this share of the median is left out

    def __post_init__(self) -> None:
        if self.column_bin_px < 1 or self.disparity_bin_px <= 0 or self.min_points < 1:
            raise ValueError("column_bin_px, disparity_bin_px and min_points must be positive")
        if self.side_tolerance_m <= 0 or not 0 <= self.profile_min_share <= 1:
            raise ValueError("side_tolerance_m must be positive and profile_min_share within 0-1")


def cluster_labels(
    columns: np.ndarray, disparities: np.ndarray, width_px: int, max_disparity: float, params: ClusterParams
) -> np.ndarray:
    """Component label (0 = noise) of each point, from its column and disparity."""
    cell_u = columns // params.column_bin_px
    cell_d = np.floor(disparities / params.disparity_bin_px).astype(np.int64)
    shape = (int(max_disparity / params.disparity_bin_px) + 2, width_px // params.column_bin_px + 1)
    cell_d = np.clip(cell_d, 0, shape[0] - 1)
    cell = cell_d * shape[1] + cell_u
    counts = np.bincount(cell, minlength=shape[0] * shape[1]).reshape(shape)
    occupied = (counts >= params.min_cell_points).astype(np.uint8)
    # Bridge one-cell gaps: a surface's points scatter over neighbouring disparity bins.
    occupied = cv2.morphologyEx(occupied, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    _, labels = cv2.connectedComponents(occupied, connectivity=8)
    point_labels = labels.ravel()[cell]
    point_labels[occupied.ravel()[cell] == 0] = 0
    return point_labels


def describe(
    mask: np.ndarray,
    disparity: np.ndarray,
    xyz: tuple[np.ndarray, np.ndarray, np.ndarray],
    max_disparity: float,
    params: ClusterParams | None = None,
) -> tuple[Obstacle, ...]:
    """The obstacle points of ``mask`` (with their disparity and VEHICLE x, y, z planes) as
    Obstacles, nearest first, at most ``max_obstacles``."""
    params = params or ClusterParams()
    index = np.flatnonzero(mask.ravel())
    if index.size < params.min_points:
        return ()
    width = mask.shape[1]
    d = disparity.ravel()[index]
    labels = cluster_labels(index % width, d, width, max_disparity, params)
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(1, labels.max() + 2))
    points = np.column_stack([plane.ravel()[index] for plane in xyz])
    obstacles = []
    for start, stop in itertools.pairwise(bounds):
        if stop - start >= params.min_points:
            members = order[start:stop]
            obstacle = _descriptor(points[members], index[members] % width, d[members], params)
            if obstacle.height_m >= params.min_top_m:
                obstacles.append(obstacle)
    obstacles.sort(key=lambda o: o.range_m)
    return tuple(obstacles[: params.max_obstacles])


def _descriptor(points: np.ndarray, columns: np.ndarray, disparities: np.ndarray, params: ClusterParams) -> Obstacle:
    ranges = np.hypot(points[:, 0], points[:, 1])
    x_m, y_m, length, width, yaw = _rectangle(_profile(points, ranges, columns, params), params.side_tolerance_m)
    top = float(np.percentile(points[:, 2], 98))
    median = float(np.median(disparities))
    consistency = float(np.mean(np.abs(disparities - median) <= params.consistency_px))
    count = len(points)
    return Obstacle(
        x_m=x_m,
        y_m=y_m,
        length_m=length,
        width_m=width,
        height_m=max(top, 0.0),
        yaw_rad=yaw,
        confidence=(1.0 - math.exp(-count / params.confidence_points)) * consistency,
        range_m=float(np.percentile(ranges, 20)),
    )


def _rectangle(outline: np.ndarray, tolerance_m: float) -> tuple[float, float, float, float, float]:
    """The rectangle whose sides the outline's points lie closest to (the closeness criterion of
    Zhang et al., "Efficient L-shape fitting for vehicle detection using laser scanners", 2017),
    a point within ``tolerance_m`` of a side counting as on it: centre x, y, length along its yaw,
    width, and that yaw, within +-45 deg. A face seen head-on gets yaw 0, two faces meeting at a
    corner the corner's turn."""
    yaws = _CANDIDATE_YAWS
    along = outline[:, 0, None] * np.cos(yaws) + outline[:, 1, None] * np.sin(yaws)
    across = -outline[:, 0, None] * np.sin(yaws) + outline[:, 1, None] * np.cos(yaws)
    to_side = np.minimum(_to_nearer_end(along), _to_nearer_end(across))
    closeness = (1.0 / np.maximum(to_side, tolerance_m)).sum(axis=0)
    best = int(np.argmax(closeness))
    a, b, yaw = along[:, best], across[:, best], float(yaws[best])
    centre_a, centre_b = (a.min() + a.max()) / 2, (b.min() + b.max()) / 2
    c, s = math.cos(yaw), math.sin(yaw)
    x_m, y_m = centre_a * c - centre_b * s, centre_a * s + centre_b * c
    return float(x_m), float(y_m), float(np.ptp(a)), float(np.ptp(b)), yaw


def _to_nearer_end(coordinates: np.ndarray) -> np.ndarray:
    return np.minimum(coordinates - coordinates.min(axis=0), coordinates.max(axis=0) - coordinates)


def _profile(points: np.ndarray, ranges: np.ndarray, columns: np.ndarray, params: ClusterParams) -> np.ndarray:
    """(2k, 2) outline of the visible surface (points with their ``ranges`` from the vehicle origin):
    for each of its k column bins, the points at the median range of the bin's points and the bin's
    outermost bearings (within 2-98 %)."""
    bearings = np.arctan2(points[:, 1], points[:, 0])
    low, high = np.percentile(bearings, [2, 98])
    bins = columns // params.column_bin_px
    order = np.lexsort((ranges, bins))  # by bin, then by range within it
    starts = np.flatnonzero(np.r_[True, np.diff(bins[order]) != 0])
    counts = np.diff(np.r_[starts, len(order)])
    sorted_ranges, sorted_bearings = ranges[order], bearings[order]
    distance = (sorted_ranges[starts + (counts - 1) // 2] + sorted_ranges[starts + counts // 2]) / 2
    ends = np.column_stack((np.minimum.reduceat(sorted_bearings, starts), np.maximum.reduceat(sorted_bearings, starts)))
    # A bin with few points (an edge the matcher half found) has no range to trust.
    kept = counts >= min(counts.max(), max(params.min_cell_points, params.profile_min_share * np.median(counts)))
    distance, ends = distance[kept], ends[kept]
    # Columns run right to left in bearing; the outermost kept bins reach the cluster's limits.
    ends[-1, 0], ends[0, 1] = low, high
    ends = np.clip(ends, low, high)
    return np.stack((distance[:, None] * np.cos(ends), distance[:, None] * np.sin(ends)), axis=-1).reshape(-1, 2)
