"""The corridor guard: control slows, then stops, rather than cut out of the RDDF corridor.

The planner keeps its paths inside the corridor; the guard checks what the wheels are about to
do. Each step it predicts the footprint's four corners along the arc of the present steering
(rear axle, constant curvature tan(delta) / L) and measures them against the corridor's edge the
way the simulator counts exits (`brain.corridor.Corridor.distance_to_edge` of the corners: the
union of the RDDF's capsules), on the few segments near the vehicle (`LocalCorridor`).

* **Brake** when, within ``horizon_s`` of travel at the present speed (at least ``min_reach_m``,
  so a standing vehicle checks its first half metre), the footprint would cross the edge or,
  already across it, get further out.
* **Speed cap** when, at the speed the controller is about to ask for, the footprint would come
  within the margin of the edge sooner than ``horizon_s``: the speed that puts that point
  ``horizon_s`` away, never below ``creep_mps``. The margin is ``margin_m`` or half the present
  clearance, whichever is less, so a footprint running along the edge is not slowed, one closing
  on it is. The cap starts at the speed asked for and falls continuously to ``creep_mps`` as the
  footprint nears the edge: no step in the target speed.

A steering angle held constant is a fair guess for as long as the actuator needs to change it
(0.8 rad/s) and a poor one well beyond that (at the end of a tight curve it curls the prediction
across the edge the vehicle is about to straighten along): hence the short horizon. Each reach
is sampled at ``SAMPLES`` even steps. A footprint that no segment's band comes near (over
``BOX_PAD_M`` outside: the corridor is not where the vehicle is) has nothing to be guarded from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from brain.corridor import Corridor
from brain.planning.bounds import Box, LocalCorridor
from brain.vehicle import VehicleGeometry
from rascal.runtime.config import setting

FloatArray = NDArray[np.float64]

SAMPLES = 4  # steps along each reach
BOX_PAD_M = 10.0  # the segments near the vehicle are looked up again once it has moved about this far
_FRACTIONS = np.linspace(0.0, 1.0, SAMPLES + 1)


@dataclass(frozen=True)
class GuardSettings:
    horizon_s: float = setting(
        0.6, "the footprint is predicted this many seconds of travel ahead on the present steering"
    )
    min_reach_m: float = setting(0.5, "... and at least this far (a standing vehicle checks its first half metre)")
    margin_m: float = setting(
        0.3, "the speed is capped when the footprint would come this near the edge (or half as near as now)"
    )
    creep_mps: float = setting(0.5, "the lowest cap, short of braking: still moving, so the steering can turn it away")

    def __post_init__(self) -> None:
        for name in ("horizon_s", "min_reach_m", "margin_m", "creep_mps"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0.0):
                raise ValueError(f"corridor guard {name} must be finite and positive, got {getattr(self, name)!r}")


class EdgeVerdict(NamedTuple):
    clearance_m: float  # the predicted footprint's least clearance to the edge (negative: outside)
    cap_mps: float  # highest speed to ask for (inf: no cap)
    crossing_m: float  # arc length of travel within which the footprint would cross the edge (inf: none)

    @property
    def brake(self) -> bool:
        return math.isfinite(self.crossing_m)

    @property
    def clear(self) -> bool:
        """Neither braking nor capping: the footprint keeps its margin."""
        return not self.brake and math.isinf(self.cap_mps)


class CorridorGuard:
    """Speed cap and brake verdict from the footprint predicted along the present steering."""

    def __init__(
        self, corridor: Corridor, vehicle: VehicleGeometry | None = None, settings: GuardSettings | None = None
    ) -> None:
        self.settings = settings or GuardSettings()
        self.vehicle = vehicle or VehicleGeometry()
        self.corridors = LocalCorridor(corridor)
        back, front, half = -self.vehicle.rear_overhang_m, self.vehicle.front_m, self.vehicle.half_width_m
        self._corners = np.array([back, back, front, front]) + 1j * np.array([-half, half, -half, half])
        self._box: Box = (math.inf, math.inf, -math.inf, -math.inf)  # contains nothing: look up at once
        self._near: Corridor | None = None

    def assess(
        self,
        east_m: float,
        north_m: float,
        yaw_rad: float,
        speed_mps: float,
        steering_rad: float,
        target_speed_mps: float,
    ) -> EdgeVerdict:
        """The verdict for a vehicle at this rear-axle pose, driving forwards at ``speed_mps`` on
        ``steering_rad`` and about to ask for ``target_speed_mps``."""
        s = self.settings
        stop_reach = max(s.min_reach_m, speed_mps * s.horizon_s)
        look_reach = max(stop_reach, target_speed_mps * s.horizon_s)
        arc = np.concatenate((stop_reach * _FRACTIONS, look_reach * _FRACTIONS))
        clearance = self._clearance(east_m, north_m, yaw_rad, math.tan(steering_rad) / self.vehicle.wheelbase_m, arc)
        now = float(clearance[0])
        stop = slice(0, SAMPLES + 1)
        look = slice(SAMPLES + 1, None)
        crossing = _first_below(arc[stop], clearance[stop], min(0.0, now))
        closing = _first_below(arc[look], clearance[look], min(s.margin_m, now / 2.0))
        cap = max(s.creep_mps, closing / s.horizon_s) if math.isfinite(closing) else math.inf
        return EdgeVerdict(float(clearance.min()), cap, crossing)

    def _clearance(self, east: float, north: float, yaw: float, curvature: float, arc: FloatArray) -> FloatArray:
        """The footprint's least clearance to the edge at each arc length along the circle."""
        half_turn = 0.5 * curvature * arc
        chord = arc * np.sinc(half_turn / math.pi)  # 2 sin(turn / 2) / curvature; the arc itself when straight
        # Complex numbers as points (east + i north) and rotations: a few array operations in all.
        axle = complex(east, north) + chord * np.exp(1j * (yaw + half_turn))
        corners = axle[:, None] + np.exp(1j * (yaw + 2.0 * half_turn))[:, None] * self._corners
        near = self._corridor_near(corners)
        if near is None:
            return np.full(len(arc), -math.inf)
        return np.asarray(near.distance_to_edge(corners.real, corners.imag)).min(axis=1)

    def _corridor_near(self, points: NDArray[np.complex128]) -> Corridor | None:
        """The corridor's segments that can reach the points (exact inside it), looked up again
        only once the points leave the padded box of the last look-up."""
        east, north = points.real, points.imag
        low_e, low_n, high_e, high_n = float(east.min()), float(north.min()), float(east.max()), float(north.max())
        box = self._box
        if not (box[0] <= low_e and box[1] <= low_n and high_e <= box[2] and high_n <= box[3]):
            self._box = (low_e - BOX_PAD_M, low_n - BOX_PAD_M, high_e + BOX_PAD_M, high_n + BOX_PAD_M)
            self._near = self.corridors.near(self._box)
        return self._near


def _first_below(arc: FloatArray, clearance: FloatArray, limit: float) -> float:
    """The arc length at which ``clearance`` first drops below ``limit`` (interpolated between
    samples; 0 if it starts below), inf if it never does."""
    below = clearance < limit
    if not below.any():
        return math.inf
    k = int(np.argmax(below))
    if k == 0:
        return 0.0
    before, after = float(clearance[k - 1]), float(clearance[k])
    return float(arc[k - 1] + (arc[k] - arc[k - 1]) * (before - limit) / (before - after))
