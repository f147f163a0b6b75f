"""Steering limits: the wheel stop and the actuator's rate, the vehicle's (brain/vehicle.py)."""

from __future__ import annotations

import pytest

from brain.vehicle import VehicleGeometry
from modules.control.limits import DEFAULT_WHEELBASE_M, SteeringLimits


def test_defaults_are_the_vehicles() -> None:
    vehicle, limits = VehicleGeometry(), SteeringLimits()
    assert limits.max_steering_rad == vehicle.max_steering_rad
    assert limits.max_steering_rate_radps == vehicle.max_steering_rate_radps
    assert vehicle.wheelbase_m == DEFAULT_WHEELBASE_M


def test_the_command_is_clamped_to_the_wheel_stop() -> None:
    limits = SteeringLimits(max_steering_rad=0.5, max_steering_rate_radps=100.0)
    assert limits.apply(0.0, 2.0, 0.02) == pytest.approx(0.5)
    assert limits.apply(0.0, -2.0, 0.02) == pytest.approx(-0.5)
    assert limits.apply(0.0, 0.3, 0.02) == pytest.approx(0.3)


def test_the_command_moves_at_most_the_actuator_rate_per_step() -> None:
    limits = SteeringLimits(max_steering_rad=0.5, max_steering_rate_radps=0.8)
    angle, angles = 0.0, []
    for _ in range(50):
        angle = limits.apply(angle, 0.5, 0.02)
        angles.append(angle)
    assert angles[0] == pytest.approx(0.016)
    assert angles[-1] == pytest.approx(0.5)
    assert max(b - a for a, b in zip([0.0, *angles], angles, strict=False)) <= 0.016 + 1e-12
    assert limits.apply(0.5, -0.5, 0.02) == pytest.approx(0.484)


@pytest.mark.parametrize(
    "kwargs", [{"max_steering_rad": 0.0}, {"max_steering_rad": 1.6}, {"max_steering_rate_radps": 0}]
)
def test_impossible_limits_are_refused(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="max_steering"):
        SteeringLimits(**kwargs)


def test_a_non_positive_step_is_refused() -> None:
    with pytest.raises(ValueError, match="dt_s"):
        SteeringLimits().apply(0.0, 0.1, 0.0)
