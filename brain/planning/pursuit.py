"""The track the vehicle makes along a polyline: a kinematic bicycle steered by pure pursuit.

A searched path is a string of cells, shortcut and rounded over free cells, and the gate checks
that polyline. The vehicle turns no tighter than wheelbase / tan(max steering) (2.3 m), turns
its wheels at a limited rate and cannot reverse, so from a standstill in front of a ditch a
polyline that steps 8 m sideways within a metre is not what it drives: it drives straight on
along its heading while control tries. The planner therefore publishes this track instead, the
way the vehicle would drive the polyline at slow speed, and gates the track.

The model: the rear axle moves ``step_m`` at a time along its heading; the wheel angle is pure
pursuit's, atan(2 L sin(alpha) / d) for the point ``lookahead_m`` further along the polyline
(at the bearing alpha from the heading, d away), limited to the wheel-angle stop and to the
actuator's rate at the given speed. The track ends where the rear axle's projection reaches the
polyline's end. It fails (None) when it strays further than ``max_deviation_m`` from the
polyline or does not get to its end within a bounded number of steps (an orbit round an end
point too close beside it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Bicycle:
    """The vehicle as pure pursuit drives it. The vehicle's numbers come from the planner's
    config (``PlannerConfig.bicycle``), which holds them once; only the model's own steps are here."""

    wheelbase_m: float
    max_steering_rad: float
    max_steering_rate_radps: float
    speed_mps: float  # the slow mode's speed: sets how far the wheels turn per metre
    lookahead_m: float
    step_m: float = 0.2  # a cell: the gate sees the track at least this finely
    max_deviation_m: float = 2.0  # the planner re-plans a vehicle further off; here it guards against orbits

    def __post_init__(self) -> None:
        for name in ("wheelbase_m", "max_steering_rate_radps", "speed_mps", "lookahead_m", "step_m", "max_deviation_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"Bicycle.{name} must be finite and positive, got {value!r}")
        if not 0.0 < self.max_steering_rad < math.pi / 2:
            raise ValueError(f"Bicycle.max_steering_rad must be in (0, pi/2), got {self.max_steering_rad!r}")


def pursue(points: FloatArray, east_m: float, north_m: float, yaw_rad: float, bicycle: Bicycle) -> FloatArray | None:
    """The rear axle's track (M x 2, from the pose) along the polyline ``points`` (N x 2), or
    None when the vehicle cannot follow it (module docstring)."""
    polyline = _Polyline(np.asarray(points, dtype=float).reshape(-1, 2))
    if polyline.count < 2:
        return None
    b = bicycle
    steer_step = b.max_steering_rate_radps * b.step_m / b.speed_mps
    max_steps = math.ceil(3.0 * (polyline.length_m + b.lookahead_m) / b.step_m) + 10
    x, y, yaw, steering = east_m, north_m, yaw_rad, 0.0
    track = [(x, y)]
    along = 0.0
    for _ in range(max_steps):
        along, deviation = polyline.project(x, y, along)
        if deviation > b.max_deviation_m:
            return None
        if along >= polyline.length_m - 1e-6:
            return np.asarray(track)
        tx, ty = polyline.point_at(min(along + b.lookahead_m, polyline.length_m))
        distance = math.hypot(tx - x, ty - y)
        if distance < b.step_m:
            return np.asarray(track)  # at the end point, whatever its projection says
        alpha = math.atan2(ty - y, tx - x) - yaw
        wanted = math.atan2(2.0 * b.wheelbase_m * math.sin(alpha), distance)
        wanted = max(-b.max_steering_rad, min(b.max_steering_rad, wanted))
        steering += max(-steer_step, min(steer_step, wanted - steering))
        x += b.step_m * math.cos(yaw)
        y += b.step_m * math.sin(yaw)
        yaw += b.step_m * math.tan(steering) / b.wheelbase_m
        track.append((x, y))
    return None


class _Polyline:
    """Stations along a polyline, with projections searched forward only (plain floats: a few
    segments a step, where numpy's call overhead would dominate)."""

    def __init__(self, points: FloatArray) -> None:
        self.xs = points[:, 0].tolist()
        self.ys = points[:, 1].tolist()
        self.count = len(self.xs)
        self.stations = [0.0]
        for i in range(1, self.count):
            self.stations.append(
                self.stations[-1] + math.hypot(self.xs[i] - self.xs[i - 1], self.ys[i] - self.ys[i - 1])
            )
        self.length_m = self.stations[-1]
        self._segment = 0

    def project(self, x: float, y: float, since_m: float, reach_m: float = 3.0) -> tuple[float, float]:
        """Station of the nearest point on the segments from the last projection's to ``reach_m``
        past ``since_m`` (the vehicle only moves forward along the path), and its distance."""
        best_station, best_gap = since_m, math.inf
        i = self._segment
        best_segment = i
        while i < self.count - 1 and self.stations[i] <= since_m + reach_m:
            x0, y0 = self.xs[i], self.ys[i]
            dx, dy = self.xs[i + 1] - x0, self.ys[i + 1] - y0
            length2 = dx * dx + dy * dy
            t = 0.0 if length2 < 1e-12 else max(0.0, min(1.0, ((x - x0) * dx + (y - y0) * dy) / length2))
            gap = math.hypot(x0 + t * dx - x, y0 + t * dy - y)
            if gap < best_gap:
                best_gap, best_segment = gap, i
                best_station = self.stations[i] + t * (self.stations[i + 1] - self.stations[i])
            i += 1
        self._segment = best_segment
        return max(best_station, since_m), best_gap

    def point_at(self, s_m: float) -> tuple[float, float]:
        i = self._segment
        while i < self.count - 2 and self.stations[i + 1] < s_m:
            i += 1
        span = self.stations[i + 1] - self.stations[i]
        t = 0.0 if span < 1e-12 else (s_m - self.stations[i]) / span
        return self.xs[i] + t * (self.xs[i + 1] - self.xs[i]), self.ys[i] + t * (self.ys[i + 1] - self.ys[i])
