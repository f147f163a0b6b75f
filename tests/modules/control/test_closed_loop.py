"""The controller closes the loop on the simulated vehicle (true state in, no bus)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from modules.control.controller import ControllerSettings, Mode
from modules.sim.scenario import DEFAULT_SCENARIO, load_scenario
from tests.modules.control.closed_loop import drive, s_curve, sign_changes

RASCAL_TOP_TESTED_MPS = 17.8  # RASCAL II.C: the controller was tested up to 17.8 m/s


def straight(length_m: float, speed_mps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    east = np.arange(0.0, length_m + 0.5, 1.0)
    return east, np.zeros_like(east), np.full_like(east, speed_mps)


@pytest.mark.parametrize("law", ["stanley", "pd"])
@pytest.mark.parametrize(("offset_m", "yaw_rad"), [(1.0, 0.0), (-2.0, 0.1)])
def test_a_straight_at_17_8_mps_settles_without_oscillating(law: str, offset_m: float, yaw_rad: float) -> None:
    speed = RASCAL_TOP_TESTED_MPS
    run = drive(ControllerSettings(law=law), *straight(900.0, speed), (0.0, offset_m, yaw_rad, speed), 30.0)
    settled = run.after(10.0)
    assert np.max(np.abs(run.cross_track_m[settled])) < 0.1
    assert np.max(np.abs(run.yaw_rad[settled])) < 0.005  # heading error on an eastward path
    assert np.max(np.abs(run.speed_mps[settled] - speed)) < 0.3
    # Back onto the line with at most a small overshoot: the steering reverses a few times, not for ever.
    assert sign_changes(run.steering_rad) <= 4
    assert np.max(np.abs(run.steering_rad)) <= 0.5
    assert all(mode is Mode.DRIVE for mode in run.modes)


@pytest.mark.parametrize("law", ["stanley", "pd"])
def test_at_17_8_mps_60_ms_of_state_latency_still_settles(law: str) -> None:
    # Without the heading-bandwidth cap, Stanley's heading loop (v / L = 14 rad/s here) turns
    # unstable with this much delay between measuring and steering.
    speed = RASCAL_TOP_TESTED_MPS
    run = drive(ControllerSettings(law=law), *straight(900.0, speed), (0.0, 1.0, 0.0, speed), 30.0, delay_steps=3)
    assert np.max(np.abs(run.cross_track_m[run.after(10.0)])) < 0.1
    assert sign_changes(run.steering_rad) <= 6


def test_without_the_bandwidth_cap_that_latency_is_unstable() -> None:
    speed = RASCAL_TOP_TESTED_MPS
    settings = ControllerSettings(law="stanley", heading_bandwidth_radps=1e6)
    run = drive(settings, *straight(900.0, speed), (0.0, 1.0, 0.0, speed), 30.0, delay_steps=3)
    assert np.max(np.abs(run.cross_track_m)) > 1.0 or Mode.OFF_PATH in run.modes


@pytest.mark.parametrize(("law", "bound_m"), [("stanley", 0.1), ("pd", 0.1)])
def test_an_s_curve_is_tracked(law: str, bound_m: float) -> None:
    east, north, speed = s_curve(radius_m=25.0, speed_mps=7.0)
    run = drive(ControllerSettings(law=law), east, north, speed, (0.0, 0.0, 0.0, 7.0), 40.0)
    assert run.progress_m > 160.0  # through both bends and stopped near the end
    assert run.speed_mps[-1] == 0.0
    assert run.rms_cross_track_m <= bound_m
    # Left bend first: its inside is on the left, the right bend's on the right; the rear axle
    # cuts the inside of both, so the error changes sign between them.
    assert np.max(run.cross_track_m) > 0.0 > np.min(run.cross_track_m)


@pytest.fixture(scope="module")
def route():  # type: ignore[no-untyped-def]
    return load_scenario(DEFAULT_SCENARIO).route


@pytest.mark.parametrize(("law", "bound_m"), [("stanley", 0.3), ("pd", 0.5)])
def test_the_default_route_at_rddf_speeds(route, law: str, bound_m: float) -> None:  # type: ignore[no-untyped-def]
    yaw = math.atan2(route.north_m[1] - route.north_m[0], route.east_m[1] - route.east_m[0])
    start = (float(route.east_m[0]), float(route.north_m[0]), yaw, 0.0)
    run = drive(ControllerSettings(law=law), route.east_m, route.north_m, route.speed_mps, start, 400.0)
    assert run.progress_m > route.length_m - 5.0  # drove the whole course ...
    assert run.modes[-1] is Mode.END or run.modes[-1] is Mode.HOLD  # ... and stopped at its end
    assert run.speed_mps[-1] == 0.0
    assert run.rms_cross_track_m <= bound_m
    assert np.max(np.abs(run.cross_track_m)) < 1.0  # even in the sharp turn
    # Speeds follow the RDDF profile: never more than 0.5 m/s over the fastest point of it.
    assert np.max(run.speed_mps) <= float(np.max(route.speed_mps)) + 0.5
