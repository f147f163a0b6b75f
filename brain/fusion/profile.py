"""Vertical-lidar ground profiles -> stretches of hazard and of seen-level ground.

A profile is the ground height along one forward line. Ground is a hazard where it leaves the
vehicle's ground plane by more than a step (a ditch floor, a berm top) or where neighbouring
returns differ steeply (a wall) by more than noise can (the nearest returns lie 6 cm apart, so
1 cm of range noise alone can make a steep slope). Hazards are judged per stretch between neighbouring returns:
a stretch is hazardous when either end is off the plane or it is steep (so the shadow before a
ditch floor, where its near edge hides, counts as hazard: conservative); it is seen level when
both ends are on the plane, not steep, and close enough that nothing fits unseen between them.
Wider gaps stay unknown. A profile that stops well short of where flat ground would still return
has lost the ground (a drop too deep for the beams): the stretch after its last return is a hazard.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class Stretches(NamedTuple):
    """Forward intervals of a profile's line, rows of (x_from_m, x_to_m) in the vehicle frame."""

    hazard: FloatArray  # (n, 2)
    level: FloatArray  # (m, 2)


def classify_profile(
    ranges_m: FloatArray | tuple[float, ...],
    heights_m: FloatArray | tuple[float, ...],
    step_m: float,
    max_slope: float,
    max_gap_m: float,
    expected_end_m: float,
    lost_m: float = 1.0,
    point_half_m: float = 0.1,
    max_range_m: float = math.inf,
    min_rise_m: float = 0.0,
) -> Stretches:
    """Hazard and level stretches of one profile. ``expected_end_m`` is where the last return
    lies on flat ground: a profile ending more than ``lost_m`` short of it has lost the ground.
    ``point_half_m`` is the half length given a lone hazardous return. A rise steeper than
    ``max_slope`` counts only from ``min_rise_m``. Returns behind the vehicle's origin or beyond
    ``max_range_m`` are ignored, as are non-finite ones."""
    r = np.asarray(ranges_m, dtype=float)
    h = np.asarray(heights_m, dtype=float)
    if r.shape != h.shape or r.ndim != 1:
        raise ValueError(f"a profile needs as many heights as ranges, got {r.shape} and {h.shape}")
    usable = np.isfinite(h) & (r >= 0.0) & (r <= max_range_m)
    if not usable.all():
        r, h = r[usable], h[usable]
    gap = r[1:] - r[:-1]
    if (gap < 0).any():
        order = np.argsort(r, kind="stable")
        r, h = r[order], h[order]
        gap = r[1:] - r[:-1]
    if not r.size:
        return Stretches(np.zeros((0, 2)), np.zeros((0, 2)))
    off_plane = np.abs(h) > step_m
    rise = np.abs(h[1:] - h[:-1])
    steep = (rise > max_slope * np.maximum(gap, 1e-3)) & (rise >= min_rise_m)
    hazard_segment = off_plane[:-1] | off_plane[1:] | steep
    level_segment = ~hazard_segment & (gap <= max_gap_m)
    hazard = [_spans(r, hazard_segment)]
    # A hazardous return with no hazardous stretch on either side (a profile of one return).
    covered = np.zeros(r.size, dtype=bool)
    covered[:-1] |= hazard_segment
    covered[1:] |= hazard_segment
    lone = r[off_plane & ~covered]
    if lone.size:
        hazard.append(np.column_stack((lone - point_half_m, lone + point_half_m)))
    if r[-1] < expected_end_m - lost_m:
        hazard.append(np.array([[r[-1], r[-1] + max_gap_m]]))
    return Stretches(np.concatenate(hazard), _spans(r, level_segment))


def _spans(r: FloatArray, segments: NDArray[np.bool_]) -> FloatArray:
    """(from, to) of each run of flagged segments, segment i lying between returns i and i + 1."""
    flags = np.concatenate(([False], segments, [False])).view(np.int8)
    edges = np.flatnonzero(flags[1:] - flags[:-1])
    return np.column_stack((r[edges[::2]], r[edges[1::2]]))
