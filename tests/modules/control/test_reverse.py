"""Driving a path backwards: rear-axle tracking against the simulated vehicle, and the gear change."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from brain.pose import Pose
from modules.control.controller import Mode, Motion, Output, VehicleController
from modules.control.path_tracking import TrackedPath
from modules.control.reverse import ReversingController
from modules.sim.vehicle import VehicleParams, VehicleState, step
from protocol.messages import ActuatorCommand
from tests.modules.control.closed_loop import signed_distance

SIM_DT_S = 0.01
CONTROL_EVERY = 2  # 50 Hz
PARAMS = VehicleParams()


def back_up(
    controller: ReversingController,
    state: VehicleState,
    east: NDArray[np.float64],
    north: NDArray[np.float64],
    seconds: float,
) -> tuple[list[float], list[Output], VehicleState]:
    """Closed loop on the true state, one control step of delay; the rear axle's cross-track
    error against the polyline at every simulator step, and every control output."""
    errors: list[float] = []
    outs: list[Output] = []
    command = ActuatorCommand(0.0, 1.0, 0.0)
    hint = 0
    for k in range(round(seconds / SIM_DT_S)):
        if k % CONTROL_EVERY == 0:
            out = controller.drive(Motion.of(state), SIM_DT_S * CONTROL_EVERY)
            outs.append(out)
            next_command = ActuatorCommand(out.throttle, out.brake, out.steering_rad, out.stop_reason, out.reverse)
        step(state, command, SIM_DT_S, PARAMS)
        command = next_command
        error, hint = signed_distance(east, north, state.east_m, state.north_m, hint)
        errors.append(error)
    return errors, outs, state


def reverse_path(east: NDArray[np.float64], north: NDArray[np.float64], speed_mps: float) -> TrackedPath:
    speed = np.full_like(east, speed_mps)
    speed[-1] = 0.0
    return TrackedPath(east, north, speed)


def test_a_straight_path_is_backed_along_and_a_5_cm_offset_settles_within_a_centimetre() -> None:
    east = -np.arange(0.0, 8.01, 0.25)
    north = np.zeros_like(east)
    controller = ReversingController()
    controller.set_path(reverse_path(east, north, 1.0), reverse=True)
    state = VehicleState(north_m=0.05, yaw_rad=0.02)  # a little off the path, facing away from it
    errors, outs, state = back_up(controller, state, east, north, 15.0)
    assert all(out.reverse for out in outs)
    assert max(abs(e) for e in errors) < 0.06
    assert max(abs(e) for e in errors[400:]) < 0.01  # after 4 s (about 3.5 m)
    assert state.east_m == pytest.approx(-8.0, abs=0.8) and state.speed_mps == 0.0
    assert outs[-1].mode is Mode.END or outs[-1].mode is Mode.HOLD
    assert max(abs(out.target_speed_mps) for out in outs) <= 1.0


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_a_curved_path_is_backed_along_within_a_few_centimetres(side: float) -> None:
    radius_m = 4.0  # curvature 0.25 /m; the vehicle manages 0.44
    angle = np.linspace(0.0, math.pi / 2, 60)
    # Backwards from (0, 0) facing east: travel west, curving left (side 1) or right.
    east = -radius_m * np.sin(angle)
    north = side * radius_m * (1.0 - np.cos(angle))
    controller = ReversingController()
    controller.set_path(reverse_path(east, north, 1.0), reverse=True)
    errors, _outs, state = back_up(controller, VehicleState(), east, north, 12.0)
    assert max(abs(e) for e in errors) < 0.05
    assert state.speed_mps == 0.0
    assert math.hypot(state.east_m + radius_m, state.north_m - side * radius_m) < 0.8


def test_it_brakes_to_a_standstill_before_it_changes_gear() -> None:
    east = -np.arange(0.0, 6.01, 0.25)
    controller = ReversingController()
    controller.set_path(reverse_path(east, np.zeros_like(east), 1.0), reverse=True)
    state = VehicleState(east_m=2.0, speed_mps=2.0)  # still rolling forwards
    _errors, outs, state = back_up(controller, state, east, np.zeros_like(east), 4.0)
    first = next(k for k, out in enumerate(outs) if out.reverse)
    assert first > 10
    assert all((out.throttle, out.brake) == (0.0, 1.0) and "gear" in out.stop_reason for out in outs[:first])
    assert all(out.reverse for out in outs[first:])
    assert state.speed_mps < -0.3  # and then it reversed


def test_a_forward_path_after_backing_up_changes_back_at_a_standstill() -> None:
    controller = ReversingController()
    controller.set_path(reverse_path(-np.arange(0.0, 4.01), np.zeros(5), 1.0), reverse=True)
    assert controller.drive(Motion(Pose(0.0, 0.0, 0.0), 0.0), 0.02).reverse
    east = np.arange(0.0, 20.0)
    controller.set_path(TrackedPath(east, np.zeros_like(east), np.full_like(east, 3.0)))
    rolling = controller.drive(Motion(Pose(0.0, 0.0, 0.0), -0.5), 0.02)
    assert rolling.reverse and (rolling.throttle, rolling.brake) == (0.0, 1.0)
    standing = controller.drive(Motion(Pose(0.0, 0.0, 0.0), -0.01), 0.02)
    assert not standing.reverse and standing.throttle > 0.0
    assert controller.brake("pause", Mode.PAUSE, 0.02).reverse is False


def test_forward_paths_are_driven_exactly_as_the_forward_controller_drives_them() -> None:
    east = np.arange(0.0, 40.0)
    path = TrackedPath(east, 0.02 * east**1.5, np.full_like(east, 4.0))
    forward, reversing = VehicleController(), ReversingController()
    forward.set_path(path)
    reversing.set_path(path)
    for k in range(200):
        motion = Motion(Pose(0.1 * k, 0.3 * math.sin(k / 9), 0.1 * math.cos(k / 7)), 0.02 * k, 0.01)
        assert reversing.drive(motion, 0.02) == forward.drive(motion, 0.02)
