"""Speed profiles: caps, curvature, acceleration and braking limits over uneven spacing."""

from __future__ import annotations

import numpy as np
import pytest

from brain.planning.speed import arc_length, clearance_cap, curvature, reachable, steering_rate_cap


def test_reachable_speeds_respect_caps_and_both_limits() -> None:
    rng = np.random.default_rng(4)
    along = np.concatenate([[0.0], np.cumsum(rng.uniform(0.2, 1.5, 120))])
    cap = rng.uniform(1.0, 15.0, len(along))
    speeds = reachable(along, cap, start_speed_mps=3.0, final_speed_mps=0.0, max_accel_mps2=1.5, max_decel_mps2=2.0)
    assert np.all(speeds <= cap + 1e-9)
    assert speeds[0] <= 3.0 + 1e-9 and speeds[-1] == 0.0
    change = np.diff(speeds**2) / (2 * np.diff(along))
    assert change.max() <= 1.5 + 1e-9 and change.min() >= -2.0 - 1e-9
    # And it is the highest such profile: each point is at a cap or at a limit from a neighbour.
    tight = np.isclose(speeds, np.minimum(cap, [3.0, *cap[1:-1], 0.0]))
    tight[1:] |= np.isclose(change, 1.5)
    tight[:-1] |= np.isclose(change, -2.0)
    assert tight.all()


def test_stopping_at_the_end_starts_braking_in_time() -> None:
    along = np.arange(0.0, 81.0)
    speeds = reachable(along, np.full(81, 10.0), 10.0, 0.0, 1.5, 2.0)
    assert speeds[0] == pytest.approx(10.0)
    assert speeds[-26] == pytest.approx(10.0)  # 25 m from the end: v^2 / (2 a) = 25 m to stop from 10 m/s
    assert speeds[-10] == pytest.approx(np.sqrt(2 * 2.0 * 9.0))


def test_curvature_of_a_circle_and_of_a_line() -> None:
    angle = np.linspace(0.0, np.pi, 200)
    circle = np.column_stack([20.0 * np.cos(angle), 20.0 * np.sin(angle)])
    kappa = curvature(circle, window_m=3.0)
    assert kappa[20:-20] == pytest.approx(1 / 20.0, rel=0.05)
    line = np.column_stack([np.arange(10.0), np.zeros(10)])
    assert np.all(curvature(line, 3.0) == 0.0)
    assert arc_length(line)[-1] == pytest.approx(9.0)


def test_clearance_cap_grows_with_clearance() -> None:
    caps = clearance_cap(np.array([0.5, 1.0, 3.0, np.inf]), least_m=1.0, speed_at_least_mps=2.0, gain=2.0)
    np.testing.assert_allclose(caps, [2.0, 2.0, 6.0, np.inf])


def s_bend(radius_m: float, step_m: float = 0.1) -> np.ndarray:
    """A left quarter circle then a right one: the wheels swing from lock to lock at the joint."""
    angles = np.arange(0.0, np.pi / 2, step_m / radius_m)
    left = np.column_stack((radius_m * np.sin(angles), radius_m * (1 - np.cos(angles))))
    end = left[-1] + (radius_m, radius_m)
    right = np.column_stack((end[0] - radius_m * np.cos(angles[1:]), end[1] - radius_m + radius_m * np.sin(angles[1:])))
    return np.vstack((left, right))


def test_the_steering_rate_caps_the_speed_where_the_path_swings_from_lock_to_lock() -> None:
    wheelbase, rate = 1.25, 0.8
    points = s_bend(3.0)
    cap = steering_rate_cap(points, 1.0, wheelbase, rate)
    joint = int(np.argmin(cap))
    # The wheels swing 2 atan(1.25 / 3) = 0.79 rad over about the 1 m window: under 1.1 m/s there.
    assert np.hypot(*(points[joint] - (3.0, 3.0))) < 0.5
    assert 0.8 < cap[joint] < 1.1
    # On the arcs themselves the wheel angle holds still: no cap.
    assert np.all(cap[: joint - 15] > 10.0)
    assert np.all(np.isinf(steering_rate_cap(np.column_stack((np.arange(10.0), np.zeros(10))), 1.0, wheelbase, rate)))
