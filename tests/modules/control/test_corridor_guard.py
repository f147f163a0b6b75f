"""The corridor guard: the footprint predicted along the present steering, against the corridor's edge;
and the controller with it, closing the loop on the simulated vehicle."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from brain.corridor import Corridor
from brain.vehicle import VehicleGeometry
from modules.control.controller import ControllerSettings, Mode, Motion, VehicleController
from modules.control.corridor_guard import CorridorGuard, GuardSettings
from modules.control.limits import DEFAULT_MAX_STEERING_RAD, DEFAULT_WHEELBASE_M
from modules.control.path_tracking import TrackedPath
from modules.sim.collision import footprint
from modules.sim.vehicle import VehicleParams, VehicleState, step
from protocol.messages import ActuatorCommand
from tests.modules.control.closed_loop import SIM_DT_S, drive, s_curve

HALF_WIDTH_M = 1.85  # the narrowest real race corridors, 3.7 m: 1.25 m to spare each side of the vehicle
VEHICLE = VehicleGeometry()
SIDE_M = VEHICLE.width_m / 2.0
NOSE_M = VEHICLE.front_m  # rear axle to the front end
STRAIGHT = Corridor([[-50.0, 0.0]], [[250.0, 0.0]], [HALF_WIDTH_M])  # due east
ALONG_EDGE_Y = HALF_WIDTH_M - SIDE_M - 0.1  # a rear axle whose left side runs 0.1 m inside the edge
PARAMS = VehicleParams()


def guard(corridor: Corridor = STRAIGHT) -> CorridorGuard:
    return CorridorGuard(corridor, VEHICLE)


def ring(centre_radius_m: float, segments: int = 72) -> Corridor:
    """A 3.7 m corridor round a circle: an RDDF polyline of short segments."""
    angle = np.linspace(0.0, math.tau, segments + 1)
    points = np.column_stack([centre_radius_m * np.cos(angle), centre_radius_m * np.sin(angle)])
    return Corridor(points[:-1], points[1:], np.full(segments, HALF_WIDTH_M))


@pytest.mark.parametrize("speed_mps", [0.0, 3.0, 13.4])
def test_a_centred_vehicle_on_a_straight_is_left_alone(speed_mps: float) -> None:
    verdict = guard().assess(50.0, 0.0, 0.0, speed_mps, 0.0, speed_mps)
    assert verdict.clear and not verdict.brake and math.isinf(verdict.cap_mps)
    assert verdict.clearance_m == pytest.approx(HALF_WIDTH_M - SIDE_M)


def test_heading_out_at_the_edge_it_brakes() -> None:
    # The left front corner is 0.12 m inside the edge, closing on it at 0.2 rad.
    y, yaw = 0.8, 0.2
    corner = y + NOSE_M * math.sin(yaw) + SIDE_M * math.cos(yaw)
    assert 0.0 < HALF_WIDTH_M - corner < 0.15
    verdict = guard().assess(50.0, y, yaw, 3.0, 0.0, 3.0)
    assert verdict.brake
    # It would cross the edge after (0.12 m / sin 0.2) of travel: within the 1.8 m of 0.6 s at 3 m/s.
    assert verdict.crossing_m == pytest.approx((HALF_WIDTH_M - corner) / math.sin(yaw), abs=0.1)
    assert verdict.clearance_m < 0.0 and verdict.cap_mps < 3.0


def test_standing_with_its_nose_at_the_edge_it_may_turn_away_but_not_drive_on() -> None:
    y, yaw = 0.85, 0.2  # left front corner 0.07 m inside, pointing out
    assert guard().assess(50.0, y, yaw, 0.0, 0.0, 2.0).brake  # the first half metre would cross
    away = guard().assess(50.0, y, yaw, 0.0, -DEFAULT_MAX_STEERING_RAD, 2.0)
    assert not away.brake and away.clearance_m > 0.0


@pytest.mark.parametrize(
    ("y", "steering_rad", "speed_mps"),
    [
        *((ALONG_EDGE_Y, 0.0, v) for v in (1.0, 5.0, 13.4)),  # along the left edge, straight
        (-ALONG_EDGE_Y, DEFAULT_MAX_STEERING_RAD, 1.0),  # along the right edge, turning away: the tail swings out
        *((-ALONG_EDGE_Y, 0.02, v) for v in (5.0, 13.4)),  # drifting away from it
    ],
)
def test_near_the_edge_heading_along_it_is_left_alone(y: float, steering_rad: float, speed_mps: float) -> None:
    verdict = guard().assess(50.0, y, 0.0, speed_mps, steering_rad, speed_mps)
    assert verdict.clear and 0.05 < verdict.clearance_m <= 0.1 + 1e-9


@pytest.mark.parametrize("radius_m", [DEFAULT_WHEELBASE_M / math.tan(DEFAULT_MAX_STEERING_RAD), 4.0, 10.0])
def test_a_tight_legal_turn_in_a_narrow_corridor_is_left_alone(radius_m: float) -> None:
    """Round a 3.7 m wide bend on a circle of ``radius_m`` (down to the tightest the vehicle can
    turn, 2.29 m), at the 2 m/s^2 lateral acceleration the planner allows, with the path asking for
    twice that speed: no brake, no cap. The rear axle's circle sits where the swept footprint
    (inner side to outer front corner) is centred in the corridor."""
    swept_out = math.hypot(radius_m + SIDE_M, NOSE_M)
    corridor = ring((radius_m - SIDE_M + swept_out) / 2.0)
    steering = math.atan(DEFAULT_WHEELBASE_M / radius_m)
    speed = math.sqrt(2.0 * radius_m)
    for angle in np.linspace(0.0, math.tau, 9):  # anywhere round the bend, anticlockwise
        verdict = CorridorGuard(corridor, VEHICLE).assess(
            radius_m * math.cos(angle), radius_m * math.sin(angle), angle + math.pi / 2, speed, steering, 2 * speed
        )
        assert verdict.clear and verdict.clearance_m > 0.8


def test_the_cap_falls_smoothly_and_monotonically_as_the_edge_nears() -> None:
    """Closing on the left edge at 0.05 rad, 5 m/s, the path asking for 8 m/s: no cap while the
    edge is far; then a cap that starts at the speed asked for and falls with every step nearer,
    down to the creep speed, with the brake before the footprint is out."""
    g = guard()
    rows = [(y, g.assess(50.0, y, 0.05, 5.0, 0.0, 8.0)) for y in np.arange(-0.5, 1.2, 0.01)]
    caps = [v.cap_mps for _y, v in rows]
    assert math.isinf(caps[0])
    capped = [cap for cap in caps if math.isfinite(cap)]
    assert 7.5 < capped[0] <= 8.0  # no step in the target speed
    assert all(b <= a for a, b in itertools.pairwise(capped))
    assert capped[-1] == GuardSettings().creep_mps
    first_brake = next(y for y, v in rows if v.brake)
    assert first_brake + NOSE_M * math.sin(0.05) + SIDE_M * math.cos(0.05) < HALF_WIDTH_M  # still inside


def test_already_across_the_edge_it_brakes_only_to_go_further_out() -> None:
    y = HALF_WIDTH_M - SIDE_M + 0.1  # the left side 0.1 m out (say, after a jump of the position fix)
    back = guard().assess(50.0, y, -0.1, 2.0, 0.0, 2.0)
    out = guard().assess(50.0, y, 0.1, 2.0, 0.0, 2.0)
    assert not back.brake and back.cap_mps == GuardSettings().creep_mps
    assert out.brake


def test_far_from_every_segment_there_is_nothing_to_guard() -> None:
    assert guard().assess(50.0, 100.0, 0.0, 5.0, 0.0, 5.0).clear


def test_the_guard_checks_the_vehicle_it_is_given() -> None:
    """Facing the left edge, a vehicle 0.5 m longer has its nose 0.5 m nearer it."""
    longer = dataclasses.replace(VEHICLE, length_m=VEHICLE.length_m + 0.5)
    verdicts = [CorridorGuard(STRAIGHT, v).assess(50.0, -0.8, math.pi / 2, 0.0, 0.0, 1.0) for v in (VEHICLE, longer)]
    assert verdicts[1].clearance_m == pytest.approx(verdicts[0].clearance_m - 0.5, abs=0.02)


@pytest.mark.parametrize("kwargs", [{"horizon_s": 0.0}, {"min_reach_m": -1.0}, {"margin_m": math.nan}])
def test_bad_settings_are_refused(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="corridor guard"):
        GuardSettings(**kwargs)


# -- the controller with the guard, against the simulated vehicle -------------------------------


def drive_out(angle_rad: float, speed_mps: float, guarded: bool) -> tuple[float, float, str]:
    """Follow a straight path that leaves STRAIGHT at ``angle_rad`` until the vehicle stands: the
    least clearance of the true footprint's corners to the edge (as the simulator counts exits),
    the speed at the guard's first brake and the last stop reason."""
    s = np.arange(0.0, 150.0)
    path = TrackedPath(s * math.cos(angle_rad), s * math.sin(angle_rad), np.full_like(s, speed_mps))
    controller = VehicleController(ControllerSettings())
    controller.set_path(path)
    controller.guard = guard() if guarded else None
    state = VehicleState(yaw_rad=angle_rad, speed_mps=speed_mps)
    command = ActuatorCommand(0.0, 0.0, 0.0)
    least, braked_at_mps, reason = math.inf, math.nan, ""
    for k in range(round(40.0 / SIM_DT_S)):
        if k % 2 == 0:
            out = controller.drive(Motion.of(state), 2 * SIM_DT_S)
            command = ActuatorCommand(out.throttle, out.brake, out.steering_rad)
            reason = out.stop_reason
            if out.mode is Mode.CORRIDOR and math.isnan(braked_at_mps):
                braked_at_mps = state.speed_mps
            if out.brake == 1.0 and state.speed_mps == 0.0:
                break
        step(state, command, SIM_DT_S, PARAMS)
        corners = np.array(footprint(state, PARAMS).corners())
        least = min(least, float(np.min(STRAIGHT.distance_to_edge(corners[:, 0], corners[:, 1]))))
    return least, braked_at_mps, reason


@pytest.mark.parametrize(("angle_deg", "speed_mps"), [(2.0, 10.0), (5.0, 6.0), (10.0, 3.0)])
def test_a_path_out_of_the_corridor_is_driven_to_a_stop_inside_it(angle_deg: float, speed_mps: float) -> None:
    assert drive_out(math.radians(angle_deg), speed_mps, guarded=False)[0] < -0.5  # without: out it goes
    least, braked_at_mps, reason = drive_out(math.radians(angle_deg), speed_mps, guarded=True)
    assert least > 0.0
    assert reason.startswith("corridor edge ") and reason.endswith(" m ahead")
    assert braked_at_mps < 1.0  # the cap had slowed it almost to the creep speed before the brake


@pytest.mark.parametrize("radius_m", [2.4, 12.0, 50.0])
def test_s_curves_in_a_narrow_corridor_are_driven_exactly_as_without_the_guard(radius_m: float) -> None:
    """Left then right bends of ``radius_m`` at the planner's 2 m/s^2 in a 3.7 m corridor round the path."""
    east, north, speed = s_curve(radius_m, math.sqrt(2.0 * radius_m))
    points = np.column_stack([east, north])
    points = np.vstack([points, points[-1] + [30.0, 0.0]])  # the course goes on past the path's end
    corridor = Corridor(points[:-1], points[1:], np.full(len(points) - 1, HALF_WIDTH_M))
    start = (0.0, 0.0, 0.0, float(speed[0]))
    free = drive(ControllerSettings(), east, north, speed, start, 80.0)
    guarded = drive(ControllerSettings(), east, north, speed, start, 80.0, guard=guard(corridor))
    assert np.array_equal(guarded.speed_mps, free.speed_mps) and np.array_equal(guarded.yaw_rad, free.yaw_rad)
    assert Mode.CORRIDOR not in guarded.modes
