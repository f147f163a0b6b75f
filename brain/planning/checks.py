"""The one safety gate every path passes before it is published or kept.

A path is the polyline through its points. It is sampled at most ``check_spacing_m`` apart and
each sample must have

* a lower bound on its distance to the nearest lethal cell centre of at least
  ``clearance_m + spacing / 2`` (the distance function is 1-Lipschitz, so nowhere between two
  samples is the polyline closer than ``clearance_m``: half width plus margin), and
* a distance inside the corridor's edge of at least ``corridor_clearance_m + spacing / 2``,

each grown by the front corners' swing where the track turns (`brain.planning.swing`): on a
turn the body reaches beyond the rear axle's tube.

The vehicle's nose reaches beyond the last point (the pose is the rear axle), so for a path that
ends in a stop the straight extension of the last segment by the front overhang is checked for
hazards too: it must not stop with its nose in an obstacle. (A path that runs on to the horizon
is extended next cycle instead.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from brain.planning.bounds import LocalCorridor
from brain.planning.hazards import HazardField
from brain.planning.swing import FrontSwing

FloatArray = NDArray[np.float64]

_NOSE_DIRECTION_M = 0.5  # the nose points along at least this much of the path's end


@dataclass(frozen=True)
class Samples:
    """Points along a polyline: where they are, how far along, and which segment each lies on."""

    east_m: FloatArray
    north_m: FloatArray
    along_m: FloatArray
    segment: NDArray[np.intp]
    spacing_m: float  # the largest gap between consecutive samples
    reach_m: FloatArray  # per sample: the longer of its gaps to its neighbours

    @property
    def slack_m(self) -> FloatArray:
        """How much closer than at either end a segment between samples can pass anything."""
        return self.reach_m / 2.0


def densify(points: FloatArray, spacing_m: float) -> Samples:
    """Samples of the polyline ``points`` (N x 2) every ``spacing_m`` or less, vertices included."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(points) == 1:
        zero = np.zeros(1)
        return Samples(points[:, 0].copy(), points[:, 1].copy(), zero, np.zeros(1, dtype=np.intp), 0.0, zero)
    step = np.diff(points, axis=0)
    length = np.hypot(step[:, 0], step[:, 1])
    pieces = np.maximum(1, np.ceil(length / spacing_m - 1e-9).astype(np.intp))
    segment = np.repeat(np.arange(len(length)), pieces)
    # Each sample's index within its segment: a running count reset at every segment start.
    within = np.arange(len(segment)) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    fraction = np.empty(len(segment) + 1)
    fraction[:-1] = within / pieces[segment]
    fraction[-1] = 1.0
    segment = np.append(segment, len(length) - 1)
    east = points[segment, 0] + fraction * step[segment, 0]
    north = points[segment, 1] + fraction * step[segment, 1]
    offsets = np.cumsum(length) - length
    along = offsets[segment] + fraction * length[segment]
    gap = (length / pieces)[segment[:-1]]  # from each sample to the next
    reach = np.empty(len(segment))
    reach[:-1] = gap
    reach[-1] = 0.0
    np.maximum(reach[1:], gap, out=reach[1:])
    return Samples(east, north, along, segment, float(gap.max()), reach)


@dataclass(frozen=True)
class Verdict:
    """Whether a path passed, and if not, how far along it the first failing sample lies."""

    ok: bool
    blocked_at_m: float = math.inf  # first sample too close to a lethal cell (inf: none)
    outside_at_m: float = math.inf  # first sample too close to the corridor's edge (inf: none)

    @property
    def first_failure_m(self) -> float:
        return min(self.blocked_at_m, self.outside_at_m)


class PathGate:
    """Checks polylines against one cycle's hazards and the corridor."""

    def __init__(
        self,
        hazards: HazardField,
        corridor: LocalCorridor,
        clearance_m: float,
        corridor_clearance_m: float,
        spacing_m: float,
        swing: FrontSwing,
    ) -> None:
        self.hazards = hazards
        self.corridor = corridor
        self.clearance_m = clearance_m
        self.corridor_clearance_m = corridor_clearance_m
        self.spacing_m = spacing_m
        self.swing = swing

    @property
    def nose_m(self) -> float:
        """How far the nose reaches beyond the rear axle."""
        return self.swing.front_m

    def check(self, points: FloatArray, nose: bool = True) -> Verdict:
        """The verdict on the polyline through ``points`` (N x 2, N >= 1)."""
        samples = densify(points, self.spacing_m)
        slack = samples.slack_m + self.swing.along(points, samples.along_m)
        clear = self.hazards.clearance_bound(samples.east_m, samples.north_m)
        blocked = np.flatnonzero(clear < self.clearance_m + slack)
        inside = self.corridor.distance_to_edge(samples.east_m, samples.north_m)
        outside = np.flatnonzero(inside < self.corridor_clearance_m + slack)
        blocked_at = float(samples.along_m[blocked[0]]) if len(blocked) else math.inf
        outside_at = float(samples.along_m[outside[0]]) if len(outside) else math.inf
        if nose and math.isinf(blocked_at) and not self.nose_clear(np.asarray(points, dtype=float).reshape(-1, 2)):
            blocked_at = float(samples.along_m[-1])
        return Verdict(math.isinf(blocked_at) and math.isinf(outside_at), blocked_at, outside_at)

    def nose_clear(self, points: FloatArray) -> bool:
        """Whether the nose, stopped at the last point and pointing along the path's last half
        metre or more, is clear of lethal cells."""
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        if self.nose_m <= 0.0 or len(points) < 2:
            return True
        end = points[-1]
        back = points[-2]
        for k in range(len(points) - 2, -1, -1):  # usually the previous point already
            back = points[k]
            if math.hypot(*(end - back)) >= _NOSE_DIRECTION_M:
                break
        length = math.hypot(*(end - back))
        if length <= 0.0:
            return True
        count = max(1, math.ceil(self.nose_m / self.spacing_m))
        t = np.linspace(0.0, self.nose_m / length, count + 1)
        bound = self.hazards.clearance_bound(end[0] + t * (end[0] - back[0]), end[1] + t * (end[1] - back[1]))
        return bool(np.all(bound >= self.clearance_m + self.nose_m / count / 2.0))
