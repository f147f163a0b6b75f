"""Steering limits of the vehicle: the wheel-angle stop and the steering actuator's rate.

The defaults are the vehicle's (brain/vehicle.py, declared there once). The controller limits
its own command the same way the actuator will, so it always knows the steering it actually
asked for and its derivative terms never fight a saturated wheel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from brain.vehicle import VehicleGeometry

_VEHICLE = VehicleGeometry()
DEFAULT_WHEELBASE_M = _VEHICLE.wheelbase_m
DEFAULT_MAX_STEERING_RAD = _VEHICLE.max_steering_rad
DEFAULT_MAX_STEERING_RATE_RADPS = _VEHICLE.max_steering_rate_radps


def clamp(value: float, low: float, high: float) -> float:
    return low if value < low else high if value > high else value


@dataclass(frozen=True)
class SteeringLimits:
    """Front-wheel angle limit (either side) and how fast the wheels can turn."""

    max_steering_rad: float = DEFAULT_MAX_STEERING_RAD
    max_steering_rate_radps: float = DEFAULT_MAX_STEERING_RATE_RADPS

    def __post_init__(self) -> None:
        if not 0.0 < self.max_steering_rad < math.pi / 2:
            raise ValueError(f"max_steering_rad must be in (0, pi/2), got {self.max_steering_rad!r}")
        if not (math.isfinite(self.max_steering_rate_radps) and self.max_steering_rate_radps > 0.0):
            rate = self.max_steering_rate_radps
            raise ValueError(f"max_steering_rate_radps must be finite and positive, got {rate!r}")

    def apply(self, previous_rad: float, target_rad: float, dt_s: float) -> float:
        """``target_rad`` clamped to the wheel stop, then moved from ``previous_rad`` by at most
        the actuator's rate over ``dt_s``."""
        if not dt_s > 0.0:
            raise ValueError(f"dt_s must be positive, got {dt_s!r}")
        target = clamp(target_rad, -self.max_steering_rad, self.max_steering_rad)
        step = self.max_steering_rate_radps * dt_s
        return previous_rad + clamp(target - previous_rad, -step, step)
