"""The sans-IO controller: limits applied, ends of paths, off-path braking, slow mode."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from brain.pose import Pose
from brain.vehicle import VehicleGeometry
from modules.control.controller import ControllerSettings, Mode, Motion, VehicleController
from modules.control.path_tracking import TrackedPath
from modules.sim.vehicle import VehicleState

DT = 0.02


def straight(speed_mps: float = 5.0, length_m: float = 50.0) -> TrackedPath:
    east = np.arange(0.0, length_m + 0.5, 1.0)
    return TrackedPath(east, np.zeros_like(east), np.full_like(east, speed_mps))


def controller(  # type: ignore[no-untyped-def]
    path: TrackedPath | None = None, vehicle: VehicleGeometry | None = None, **settings
) -> VehicleController:
    c = VehicleController(ControllerSettings(**settings), vehicle)
    c.set_path(path or straight())
    return c


@pytest.mark.parametrize("law", ["stanley", "pd"])
def test_a_vehicle_left_of_the_path_steers_right_and_one_right_of_it_left(law: str) -> None:
    left = controller(law=law).drive(Motion(Pose(5.0, 1.0, 0.0), 5.0), DT)
    right = controller(law=law).drive(Motion(Pose(5.0, -1.0, 0.0), 5.0), DT)
    assert left.cross_track_m > 0.0 and left.steering_rad < 0.0
    assert right.cross_track_m < 0.0 and right.steering_rad > 0.0


def test_steering_is_rate_and_angle_limited() -> None:
    c = controller(vehicle=VehicleGeometry(max_steering_rad=0.5, max_steering_rate_radps=0.8))
    outs = [c.drive(Motion(Pose(5.0, -4.0, 0.0), 2.0), DT) for _ in range(60)]
    assert outs[0].steering_rad == pytest.approx(0.8 * DT)
    assert max(abs(b.steering_rad - a.steering_rad) for a, b in itertools.pairwise(outs)) <= 0.8 * DT + 1e-12
    assert max(out.steering_rad for out in outs) == pytest.approx(0.5)


def test_below_speed_it_drives_above_it_brakes() -> None:
    slow = controller().drive(Motion(Pose(5.0, 0.0, 0.0), 2.0), DT)
    fast = controller().drive(Motion(Pose(5.0, 0.0, 0.0), 9.0), DT)
    assert slow.throttle > 0.0 and slow.brake == 0.0 and slow.mode is Mode.DRIVE and slow.stop_reason == ""
    assert fast.brake > 0.0 and fast.throttle == 0.0
    assert slow.target_speed_mps == pytest.approx(5.0) and slow.speed_error_mps == pytest.approx(3.0)


def test_a_path_starting_at_standstill_still_gets_the_vehicle_moving() -> None:
    east = np.arange(0.0, 51.0)
    path = TrackedPath(east, np.zeros_like(east), np.minimum(8.0, np.sqrt(3.0 * east)))  # 0 m/s at the start
    out = controller(path, law="pd").drive(Motion(Pose(0.0, 0.0, 0.0), 0.0), DT)
    assert out.target_speed_mps > 1.0 and out.throttle > 0.0


def test_past_the_end_of_the_path_it_brakes_and_says_so() -> None:
    out = controller(straight(length_m=20.0), law="pd").drive(Motion(Pose(21.0, 0.0, 0.0), 3.0), DT)
    assert (out.throttle, out.brake) == (0.0, 1.0)
    assert out.mode is Mode.END and out.stop_reason == "end of path"


def test_a_path_asking_for_zero_speed_holds_the_vehicle() -> None:
    out = controller(straight(speed_mps=0.0)).drive(Motion(Pose(5.0, 0.0, 0.0), 0.1), DT)
    assert (out.throttle, out.brake) == (0.0, 1.0)
    assert out.mode is Mode.HOLD


def test_far_from_the_path_it_brakes_with_the_steering_held() -> None:
    c = controller(max_cross_track_m=5.0)
    c.drive(Motion(Pose(5.0, -3.0, 0.0), 5.0), DT)
    held = c.steering_rad
    out = c.drive(Motion(Pose(5.2, -6.0, 0.0), 5.0), DT)
    assert out.mode is Mode.OFF_PATH and "off path" in out.stop_reason
    assert (out.throttle, out.brake, out.steering_rad) == (0.0, 1.0, held)
    assert out.cross_track_m == pytest.approx(-6.0)


def test_slow_mode_caps_the_target_speed() -> None:
    c = VehicleController(ControllerSettings(slow_mode_speed_mps=1.0))
    c.set_path(straight(speed_mps=10.0), slow_mode=True)
    assert c.drive(Motion(Pose(5.0, 0.0, 0.0), 3.0), DT).target_speed_mps == pytest.approx(1.0)


def test_brake_holds_the_steering_and_forgets_the_integrator() -> None:
    c = controller()
    for _ in range(20):
        c.drive(Motion(Pose(5.0, -1.0, 0.0), 2.0), DT)
    steering = c.steering_rad
    out = c.brake("PATH stale", Mode.FAILSAFE, DT)
    assert (out.throttle, out.brake, out.steering_rad, out.stop_reason) == (0.0, 1.0, steering, "PATH stale")
    assert c.speed.integral == 0.0
    assert math.isnan(out.cross_track_m)


def test_driving_without_a_path_is_a_local_error() -> None:
    with pytest.raises(RuntimeError):
        VehicleController().drive(Motion(Pose(0.0, 0.0, 0.0), 0.0), DT)


@pytest.mark.parametrize("kwargs", [{"law": "pure_pursuit"}, {"window_ahead_m": 0.0}, {"speed_preview_time_s": -1.0}])
def test_bad_settings_are_refused(kwargs: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        ControllerSettings(**kwargs)  # type: ignore[arg-type]


def test_saturated_steering_slows_to_the_tightest_turns_safe_speed() -> None:
    """3 m beside a 10 m/s path the steering law asks for more than the wheels can give: the
    target drops to the speed at which the tightest turn takes 2 m/s^2; on the path it does not."""
    vehicle = VehicleGeometry()
    tightest_speed = math.sqrt(2.0 * vehicle.wheelbase_m / math.tan(vehicle.max_steering_rad))
    off = controller(straight(10.0)).drive(Motion(Pose(5.0, -3.0, 0.0), 8.0), DT)
    on = controller(straight(10.0)).drive(Motion(Pose(5.0, 0.0, 0.0), 8.0), DT)
    assert off.target_speed_mps == pytest.approx(tightest_speed) and tightest_speed < 2.5
    assert on.target_speed_mps == pytest.approx(10.0)


def test_a_pose_is_dead_reckoned_to_the_present_along_its_arc() -> None:
    """A quarter turn of radius 2 m at 1 m/s, reckoned in one go, lands where the arc does; a
    reversing pose moves backwards; no age, no change."""
    state = VehicleState(east_m=10.0, north_m=5.0, speed_mps=1.0, yaw_rate_radps=0.5)
    quarter = Motion.of(state, math.pi)  # pi m of a 2 m radius circle
    assert quarter.pose == pytest.approx((12.0, 7.0, math.pi / 2))
    assert (quarter.speed_mps, quarter.yaw_rate_radps) == (1.0, 0.5)
    small = Motion.of(state, 0.05).pose
    assert small.east_m == pytest.approx(10.05, abs=1e-3) and small.north_m == pytest.approx(5.000625, abs=1e-6)
    backing = Motion.of(VehicleState(yaw_rad=math.pi / 2, speed_mps=-1.0), 0.1).pose
    assert (backing.east_m, backing.north_m) == pytest.approx((0.0, -0.1))
    unchanged = Motion(Pose(10.0, 5.0, 0.0), 1.0, 0.5)
    assert Motion.of(state) == unchanged and Motion.of(state, -1.0) == unchanged
