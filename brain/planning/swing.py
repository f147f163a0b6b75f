"""The front corners' swing on a turn: how far the body reaches beyond the rear axle's track.

A path is the rear axle's track, and the gate keeps half a width plus a margin clear round it.
On a straight that holds the whole body. On a turn of radius R the outer front corner runs on a
circle of radius sqrt((R + w/2)^2 + f^2) (w the width, f rear axle to front), beyond the track's
R + w/2 by

    swing(k) = f^2 k / (1 + k w/2 + sqrt((1 + k w/2)^2 + (f k)^2)),   k = 1/R,

which is 0.46 m at the ATV's full lock, 0.25 m at 5 m, 0.13 m at 10 m and nothing on a
straight. That is more than the margins (0.15 m to hazards, 0.1 m to the corridor's edge): a
tube alone let the vehicle start a full-lock swerve past a boulder its corner then hit, or
swing its nose out of the corridor.

Where the gate checks a point of the track, the corner of a pose up to f behind it may be level
with it, displaced by the swing of the turning between that pose and the point. So each sample
asks the swing of the tightest curvature among the track's vertices in the f behind it, on both
sides (the inner side gets it too: the distance field does not say which side a hazard is on).
The rear corners swing outwards by less (f is the longer overhang). Curvature at a vertex is
2 sin(turn / 2) over its mean segment: exactly 1/R for equal chords of an arc, as Hybrid A*
publishes them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class FrontSwing:
    """The swing of a vehicle's front corners: rear axle to front ``front_m``, ``half_width_m``."""

    front_m: float
    half_width_m: float

    def at(self, curvature: ArrayLike) -> FloatArray:
        """The swing (m) on a steady turn of ``curvature`` (1/m, either sign)."""
        k = np.abs(np.asarray(curvature, dtype=float))
        side = 1.0 + k * self.half_width_m
        return self.front_m**2 * k / (side + np.sqrt(side * side + (self.front_m * k) ** 2))

    def of(self, curvature: float) -> float:
        """`at` for one curvature, in float arithmetic (Hybrid A*'s inner loop: numpy's per-call
        overhead is ten times the formula's)."""
        k = abs(curvature)
        side = 1.0 + k * self.half_width_m
        return self.front_m**2 * k / (side + math.sqrt(side * side + (self.front_m * k) ** 2))

    def along(self, points: FloatArray, sample_along_m: FloatArray) -> FloatArray:
        """For samples at ``sample_along_m`` (metres along the polyline ``points``, N x 2), the
        swing of the tightest vertex within ``front_m`` behind each (module docstring)."""
        vertex_along, curvature = vertex_curvature(points)
        out = np.zeros(len(sample_along_m))
        if len(curvature) == 0 or self.front_m <= 0.0:
            return out
        swing = self.at(curvature)
        # Vertices in [s - f, s): a handful per sample at any sane spacing, so one pass per offset.
        first = np.searchsorted(vertex_along, sample_along_m - self.front_m, side="left")
        end = np.searchsorted(vertex_along, sample_along_m - 1e-9, side="left")
        for offset in range(int((end - first).max(initial=0))):
            index = first + offset
            held = index < end
            np.maximum(out, np.where(held, swing[np.minimum(index, len(swing) - 1)], 0.0), out=out)
        return out


def curvature_at(a: tuple[float, float], b: tuple[float, float], c: tuple[float, float]) -> float:
    """The curvature at vertex ``b`` of the polyline a-b-c as `vertex_curvature` computes it, in
    float arithmetic for one vertex; 0 where a segment has no length."""
    first = math.hypot(b[0] - a[0], b[1] - a[1])
    second = math.hypot(c[0] - b[0], c[1] - b[1])
    if first <= 1e-9 or second <= 1e-9:
        return 0.0
    turn = math.remainder(math.atan2(c[1] - b[1], c[0] - b[0]) - math.atan2(b[1] - a[1], b[0] - a[0]), math.tau)
    return 2.0 * math.sin(abs(turn) / 2.0) / ((first + second) / 2.0)


def vertex_curvature(points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The interior vertices of the polyline ``points`` (N x 2): how far along each lies and its
    curvature, 2 sin(turn / 2) over the mean of its two segments. Repeated points are dropped."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    step = np.diff(points, axis=0)
    length = np.hypot(step[:, 0], step[:, 1])
    along = np.concatenate([[0.0], np.cumsum(length)])
    moving = length > 1e-9
    step, length, ends = step[moving], length[moving], along[1:][moving]
    if len(length) < 2:
        return np.zeros(0), np.zeros(0)
    heading = np.arctan2(step[:, 1], step[:, 0])
    turn = np.remainder(np.diff(heading) + math.pi, math.tau) - math.pi
    curvature = 2.0 * np.sin(np.abs(turn) / 2.0) / ((length[1:] + length[:-1]) / 2.0)
    return ends[:-1], curvature
