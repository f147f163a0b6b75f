"""The navigation filter (both estimators) on simulated drives: accuracy with GPS, through outages
and jumps, late and out-of-order measurements, covariance health."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import pytest

from modules.ins.cores import FILTERS
from modules.ins.navigator import InsFilter
from modules.sim.nav import replay as sim
from modules.sim.nav.replay import Drive, Errors, Run
from modules.sim.vehicle import VehicleState
from modules.sim.world import SensorFault
from protocol.messages import ActuatorCommand, NavQuality

OUTAGE_START_S, OUTAGE_END_S, OUTAGE_RUN_S = 120.0, 300.0, 330.0


class Result(NamedTuple):
    drive: Drive
    filter: InsFilter
    run: Run
    errors: Errors


def simulate(duration_s: float, seed: int, faults: Sequence[SensorFault] = (), kind: str = "ekf") -> Result:
    drive = sim.drive(duration_s, seed, faults)
    nav = InsFilter(sim.ORIGIN, kind=kind)
    run = sim.run(nav, drive.events, len(drive.truth))
    return Result(drive, nav, run, sim.errors(run, drive.truth))


@pytest.fixture(scope="module", params=FILTERS)
def outage(request: pytest.FixtureRequest) -> Result:
    """Two minutes with GPS, three without at 10 m/s, then GPS again."""
    return simulate(OUTAGE_RUN_S, seed=1, faults=[sim.gps_outage(OUTAGE_START_S, OUTAGE_END_S)], kind=request.param)


def assert_covariance_healthy(run: Run) -> None:
    assert run.worst_asymmetry == 0.0
    assert run.min_eigenvalue > 0.0


def test_accuracy_with_gps(outage: Result) -> None:
    errors = outage.errors
    for span in (sim.window(30.0, OUTAGE_START_S), sim.window(OUTAGE_END_S + 10.0, OUTAGE_RUN_S)):
        assert sim.rms(errors.position_m[span]) <= 0.3
        assert math.degrees(sim.rms(errors.yaw_rad[span])) <= 1.0
        assert sim.rms(errors.speed_mps[span]) <= 0.1
    assert np.all(outage.run.quality[sim.window(1.0, OUTAGE_START_S)] == NavQuality.DGPS)


def test_outage_60_and_180_seconds(outage: Result) -> None:
    position = outage.errors.position_m
    assert np.max(position[sim.window(OUTAGE_START_S, OUTAGE_START_S + 60.0)]) <= 1.0
    assert np.max(position[sim.window(OUTAGE_START_S, OUTAGE_END_S)]) <= 3.0


def test_outage_is_flagged_and_covariance_grows_honestly(outage: Result) -> None:
    run = outage.run
    # The last fix is at 119.9 s; one second later the solution is dead reckoning.
    assert np.all(run.quality[sim.window(OUTAGE_START_S + 1.0, OUTAGE_END_S)] == NavQuality.DEAD_RECKONING)
    assert np.all(run.quality[sim.window(OUTAGE_END_S + 1.0, OUTAGE_RUN_S)] == NavQuality.DGPS)
    span = sim.window(OUTAGE_START_S, OUTAGE_END_S)
    variance = run.position_var_m2[span]
    # It grows with time out of GPS (not strictly: a compass update in a curve can trim it a little).
    at_60_s, at_180_s = variance[6000 - 1], variance[-1]
    assert variance[0] < at_60_s < at_180_s
    assert at_180_s > 10 * variance[0]
    # Honest: the 2D error stays within a few of its claimed standard deviations.
    assert np.max(outage.errors.position_m[span] / np.sqrt(variance)) < 4.0
    assert_covariance_healthy(run)


def test_magnetometer_bias_learned_with_gps_is_kept_through_outage(outage: Result) -> None:
    bias_deg = np.degrees(outage.run.mag_bias_rad)
    before = bias_deg[sim.window(OUTAGE_START_S - 1.0, OUTAGE_START_S)].mean(axis=0)
    end = bias_deg[sim.window(OUTAGE_END_S - 1.0, OUTAGE_END_S)].mean(axis=0)
    assert np.allclose(before, [2.0, -3.0], atol=0.1)  # the models' biases (MAGNETOMETER_1 and _2)
    assert np.allclose(end, before, atol=0.05)


@pytest.mark.parametrize("kind", FILTERS)
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_heading_is_honest_from_the_first_solution(kind: str, seed: int) -> None:
    """At rest the compasses are all there is of the heading, and each is a few degrees off: the
    claimed yaw uncertainty says so until driving reveals it. A yaw 2 deg off with a claimed
    0.35 deg put a hazard 37 m ahead 1.3 m to one side of where the map believed it could be."""
    result = simulate(30.0, seed=seed, kind=kind)
    error, sigma = result.errors.yaw_rad, np.sqrt(result.run.yaw_var_rad2)
    solved = np.isfinite(error)
    first = int(np.flatnonzero(solved)[0])
    assert math.degrees(sigma[first]) >= 2.0  # the compass biases' spread (InsParams: 5 deg)
    assert np.max(np.abs(error[solved]) / sigma[solved]) < 3.0
    assert math.degrees(np.max(np.abs(error[sim.window(10.0, 30.0)]))) <= 0.3


@pytest.mark.parametrize("kind", FILTERS)
def test_a_20_m_jump_is_rejected_counted_and_ignored(kind: str) -> None:
    result = simulate(70.0, seed=2, faults=[sim.gps_jump(40.0, 44.0, 20.0)], kind=kind)
    ekf, run = result.filter, result.run
    assert ekf.gps_rejected == 40  # every fix of the 4 s jump, and no other
    assert ekf.reacquisitions == 0
    assert np.max(result.errors.position_m[sim.window(30.0, 70.0)]) <= 0.3
    assert np.all(run.quality[sim.window(41.1, 44.0)] == NavQuality.DEAD_RECKONING)
    assert np.all(run.quality[sim.window(44.1, 70.0)] == NavQuality.DGPS)
    assert_covariance_healthy(run)


@pytest.mark.parametrize(("kind", "late_gps_ns"), [("ekf", 0), ("ekf", 250_000_000), ("ukf", 250_000_000)])
def test_a_persistent_offset_is_reacquired(kind: str, late_gps_ns: int) -> None:
    """Also with every fix 250 ms late: then each is gated, and the re-acquisition made, in the
    state rewound to its time."""
    drive = sim.drive(90.0, seed=3, faults=[sim.gps_jump(40.0, 100.0, 20.0)])
    ekf = InsFilter(sim.ORIGIN, kind=kind)
    run = sim.run(ekf, sim.delay(drive.events, {"gps": late_gps_ns}), len(drive.truth))
    result = Result(drive, ekf, run, sim.errors(run, drive.truth))
    assert ekf.reacquisitions == 1
    # Rejected for the 10 s the re-acquisition waits, then accepted again.
    assert ekf.gps_rejected == 101  # 40.0 s to 50.0 s
    # After it, the estimate sits on the offset GPS (the only position source there is).
    offset = result.errors.position_m[sim.window(55.0, 90.0)]
    assert np.all(np.abs(offset - 20.0) < 0.5)
    assert np.all(run.quality[sim.window(55.0, 90.0)] == NavQuality.DGPS)
    assert_covariance_healthy(run)


@pytest.fixture(scope="module")
def short_drive() -> Drive:
    return sim.drive(40.0, seed=4)


def final_x(events: list[sim.Event], samples: int) -> tuple[InsFilter, np.ndarray]:
    ekf = InsFilter(sim.ORIGIN)
    sim.run(ekf, events, samples)
    return ekf, ekf.x


def after_first_second(events: list[sim.Event], delays_ns: dict[str, int]) -> list[sim.Event]:
    start = sim.t_ns_at(1.0)
    return [e for e in events if e.t_ns < start] + sim.delay([e for e in events if e.t_ns >= start], delays_ns)


def test_late_measurements_are_replayed_to_the_same_answer(short_drive: Drive) -> None:
    samples = len(short_drive.truth)
    _, in_order = final_x(short_drive.events, samples)
    # After the first second, GPS 250 ms and magnetometers 30 ms late: each rewinds and replays
    # the IMU since. (The first second stays in order so both runs initialise alike.)
    late = after_first_second(short_drive.events, {"gps": 250_000_000, "mag": 30_000_000})
    ekf, replayed = final_x(late, samples)
    assert ekf.replayed > 1000
    assert ekf.late_rejected == 0
    # Not bit-identical: simultaneous measurements are applied in another order, and the
    # speedometer's model (scale * speed) is nonlinear.
    assert np.allclose(replayed, in_order, rtol=0.0, atol=1e-5)


def test_measurements_ahead_of_the_imu_wait_for_it(short_drive: Drive) -> None:
    samples = len(short_drive.truth)
    _, in_order = final_x(short_drive.events, samples)
    # The IMU 45 ms late: the other measurements arrive before the state reaches their time.
    ekf, waited = final_x(after_first_second(short_drive.events, {"imu": 45_000_000}), samples)
    assert ekf.late_rejected == 0
    assert np.allclose(waited, in_order, rtol=0.0, atol=1e-9)


def test_measurements_too_old_or_too_far_ahead_are_rejected(short_drive: Drive) -> None:
    ekf = InsFilter(sim.ORIGIN)
    sim.run(ekf, short_drive.events, len(short_drive.truth))
    before = ekf.x
    old_fix = next(e for e in reversed(short_drive.events) if e.kind == "gps" and e.t_ns <= sim.t_ns_at(39.0))
    ekf.on_gps(old_fix.msg, old_fix.t_ns)
    old_imu = next(e for e in reversed(short_drive.events) if e.kind == "imu" and e.t_ns < sim.t_ns_at(40.0))
    ekf.on_imu(old_imu.msg, old_imu.t_ns)
    compass = next(e for e in reversed(short_drive.events) if e.kind == "mag")
    ekf.on_mag(compass.msg, compass.t_ns + 1_000_000_000)  # a second ahead of the IMU: not kept
    assert (ekf.late_rejected, ekf.imu_dropped, ekf.ahead_rejected) == (1, 1, 1)
    assert np.array_equal(ekf.x, before)


def test_invalid_until_initialised_then_a_positive_definite_published_covariance(short_drive: Drive) -> None:
    ekf = InsFilter(sim.ORIGIN)
    assert ekf.state(sim.T0_NS).quality == NavQuality.INVALID
    imu = next(e for e in short_drive.events if e.kind == "imu")
    ekf.on_imu(imu.msg, imu.t_ns)
    assert ekf.state(imu.t_ns).quality == NavQuality.INVALID
    handlers = {"imu": ekf.on_imu, "gps": ekf.on_gps, "speed": ekf.on_speed, "mag": ekf.on_mag}
    for event in short_drive.events:
        handlers[event.kind](event.msg, event.t_ns)
        if event.kind == "gps" and ekf.initialised:
            state = ekf.state(event.t_ns + 5_000_000)  # a little ahead: extrapolated
            assert state.quality == NavQuality.DGPS
            cov = np.array(state.covariance).reshape(5, 5)
            assert np.array_equal(cov, cov.T)
            assert np.linalg.eigvalsh(cov)[0] > 0.0


@pytest.mark.slow
@pytest.mark.parametrize("kind", FILTERS)
@pytest.mark.parametrize("seed", range(20))
def test_never_diverges(seed: int, kind: str) -> None:
    """A 45 s drive per seed with a jump of seeded size and length and a 15 s outage."""
    rng = np.random.default_rng([seed, 99])
    jump_s = float(rng.uniform(8.0, 12.0))
    faults = [sim.gps_jump(jump_s, jump_s + float(rng.uniform(1.0, 5.0)), float(rng.uniform(5.0, 20.0)))]
    result = simulate(45.0, seed=100 + seed, faults=[*faults, sim.gps_outage(20.0, 35.0)], kind=kind)
    position = result.errors.position_m
    assert np.max(position[sim.window(5.0, 45.0)]) <= 0.5
    assert sim.rms(position[sim.window(38.0, 45.0)]) <= 0.3
    assert math.degrees(np.max(np.abs(result.errors.yaw_rad[sim.window(5.0, 45.0)]))) <= 1.0
    assert result.filter.reacquisitions == 0
    assert_covariance_healthy(result.run)


def shuttle_driver(vehicle: VehicleState, t_s: float) -> ActuatorCommand:
    """Forwards at 4 m/s, a stop at 30 s, 10 s of backing up at up to 2 m/s with the wheels turned,
    then forwards again (the gear changes at a standstill: the vehicle brakes until then)."""
    backing = 30.0 <= t_s < 40.0
    target = -2.0 if backing else 4.0
    steering = 0.25 if backing else 0.4 * math.sin(t_s / 6.0)
    error = abs(target) - abs(vehicle.speed_mps)
    if error >= 0:
        return ActuatorCommand(min(1.0, 0.3 + 0.5 * error), 0.0, steering, reverse=backing)
    return ActuatorCommand(0.0, min(1.0, -0.3 * error), steering, reverse=backing)


@pytest.mark.parametrize("kind", FILTERS)
def test_backing_up_is_navigated_with_and_without_gps(kind: str) -> None:
    """The speedometer and odometer are signed, the yaw comes from the compass: backing up is
    dead-reckoned backwards, through a GPS outage over the whole reversal too."""
    for faults, position_limit_m in (((), 0.3), ((sim.gps_outage(28.0, 48.0),), 1.0)):
        start = VehicleState(yaw_rad=math.radians(40.0))
        drive = sim.drive(60.0, seed=3, faults=faults, driver=shuttle_driver, start=start)
        nav = InsFilter(sim.ORIGIN, kind=kind)
        run = sim.run(nav, drive.events, len(drive.truth))
        errors = sim.errors(run, drive.truth)
        truth_speed = np.array([t.speed_mps for t in drive.truth])
        assert truth_speed.min() < -1.5  # it really backed up
        span = sim.window(10.0, 60.0)
        assert np.max(errors.position_m[span]) <= position_limit_m
        assert math.degrees(np.max(np.abs(errors.yaw_rad[span]))) <= 2.0
        assert sim.rms(errors.speed_mps[span]) <= 0.1
        backing = truth_speed < -0.5
        assert np.all(run.speed_mps[backing] < 0.0)
        assert_covariance_healthy(run)
