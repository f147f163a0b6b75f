"""The navigation sensor models, driven directly with synthetic truth."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pymap3d
from hypothesis import given
from hypothesis import strategies as st

from modules.sim.nav.models import (
    DEG_PER_H_TO_RADPS,
    MAGNETOMETER_1,
    MAGNETOMETER_2,
    MILLI_G_TO_MPS2,
    GeodeticOrigin,
    GpsModel,
    GpsParams,
    ImuModel,
    ImuParams,
    MagnetometerModel,
    SpeedometerModel,
    SpeedometerParams,
    enu_to_geodetic,
    wrap_angle,
)
from modules.sim.world import FaultKind, SensorFault
from protocol.messages import GpsFix, SimTruth

ORIGIN = GeodeticOrigin(35.0, -116.5, 700.0)  # the Mojave desert
IDEAL_IMU = ImuParams(
    gyro_bias_deg_per_h=(0.0, 0.0, 0.0),
    gyro_bias_instability_deg_per_h=0.0,
    gyro_arw_deg_per_sqrt_h=0.0,
    accel_bias_mg=(0.0, 0.0, 0.0),
    accel_bias_instability_mg=0.0,
    accel_vrw_mps_per_sqrt_h=0.0,
)
IDEAL_GPS = GpsParams(noise_std_m=(0.0, 0.0, 0.0), wander_std_m=(0.0, 0.0, 0.0))
WHITE_GPS = GpsParams(wander_std_m=(0.0, 0.0, 0.0))


def rng(seed: int = 7) -> np.random.Generator:
    return np.random.default_rng(seed)


def truth(
    east_m: float = 0.0, north_m: float = 0.0, yaw_rad: float = 0.0, speed_mps: float = 0.0, yaw_rate_radps: float = 0.0
) -> SimTruth:
    return SimTruth(east_m, north_m, yaw_rad, speed_mps, yaw_rate_radps, 0.0, 0.0, 0)


def timeline(rate_hz: float, duration_s: float) -> Iterator[tuple[int, float]]:
    """(t_ns, t_s) of samples at ``rate_hz`` from t = 0 for ``duration_s``."""
    period_ns = round(1e9 / rate_hz)
    for k in range(round(duration_s * rate_hz)):
        yield k * period_ns, k * period_ns / 1e9


def record(
    measure: Callable[..., Any], state: Callable[[float], SimTruth], rate_hz: float, duration_s: float
) -> list[tuple[float, Any]]:
    """[(t_s, output)] of ``measure`` over a truth trajectory ``state(t_s)``."""
    return [(t_s, measure(state(t_s), t_ns, t_s)) for t_ns, t_s in timeline(rate_hz, duration_s)]


def to_enu(fix: GpsFix) -> np.ndarray:
    return np.array(
        pymap3d.geodetic2enu(fix.lat_deg, fix.lon_deg, fix.alt_m, ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.alt_m)
    )


# -- IMU ---------------------------------------------------------------------------------------


def test_imu_at_rest_reads_gravity_up_and_only_bias_and_noise_on_the_gyros() -> None:
    params = ImuParams()
    imu = ImuModel(params, rng())
    samples = [s for _, s in record(imu.measure, lambda t: truth(), 100.0, 10.0)]
    accel = np.array([s[:3] for s in samples])
    gyro = np.array([s[3:] for s in samples])
    # Every sample within turn-on bias + 5 sigma of drift + 5 sigma of white noise of the truth.
    accel_bound = max(map(abs, params.accel_bias_mg)) * MILLI_G_TO_MPS2 + 5 * (
        params.accel_bias_instability_mg * MILLI_G_TO_MPS2 + imu.accel_noise_mps2
    )
    gyro_bound = max(map(abs, params.gyro_bias_deg_per_h)) * DEG_PER_H_TO_RADPS + 5 * (
        params.gyro_bias_instability_deg_per_h * DEG_PER_H_TO_RADPS + imu.gyro_noise_radps
    )
    assert np.all(np.abs(accel - [0.0, 0.0, params.gravity_mps2]) < accel_bound)
    assert np.all(np.abs(gyro) < gyro_bound)
    assert abs(accel[:, 2].mean() - 9.81) < 0.01


def test_gyro_bias_estimated_from_a_long_static_record_is_the_configured_bias() -> None:
    params = ImuParams()
    duration_s, rate_hz = 3600.0, 10.0
    imu = ImuModel(params, rng(), rate_hz=rate_hz)
    gyro = np.array([s[3:] for _, s in record(imu.measure, lambda t: truth(), rate_hz, duration_s)])
    estimate_deg_per_h = gyro.mean(axis=0) / DEG_PER_H_TO_RADPS
    # The mean's error: angle random walk over the record, and the Gauss-Markov drift, whose
    # time average has variance sigma^2 * 2 tau / T for T >> tau.
    arw_deg_per_h = params.gyro_arw_deg_per_sqrt_h / math.sqrt(duration_s / 3600.0)
    drift_deg_per_h = (
        math.sqrt(2 * params.gyro_bias_correlation_s / duration_s) * params.gyro_bias_instability_deg_per_h
    )
    tolerance = 4 * math.hypot(arw_deg_per_h, drift_deg_per_h)
    assert np.all(np.abs(estimate_deg_per_h - params.gyro_bias_deg_per_h) < tolerance)


def test_imu_lateral_accel_in_a_steady_turn_is_speed_times_yaw_rate() -> None:
    speed, yaw_rate = 12.0, 0.25
    imu = ImuModel(IDEAL_IMU, rng())
    samples = [s for _, s in record(imu.measure, lambda t: truth(speed_mps=speed, yaw_rate_radps=yaw_rate), 100, 3)]
    for s in samples:
        assert math.isclose(s.accel_y_mps2, speed * yaw_rate, rel_tol=1e-12)
        assert math.isclose(s.gyro_z_radps, yaw_rate, rel_tol=1e-12)
        assert abs(s.accel_x_mps2) < 1e-12


def test_imu_longitudinal_accel_is_the_rate_of_change_of_speed() -> None:
    imu = ImuModel(IDEAL_IMU, rng())
    samples = [s for _, s in record(imu.measure, lambda t: truth(speed_mps=2.0 + 1.5 * t), 100, 2)]
    assert samples[0].accel_x_mps2 == 0.0  # no previous speed to differentiate
    assert all(math.isclose(s.accel_x_mps2, 1.5, rel_tol=1e-9) for s in samples[1:])


# -- GPS ---------------------------------------------------------------------------------------


def test_gps_white_noise_has_the_configured_decimetre_std() -> None:
    gps = GpsModel(WHITE_GPS, ORIGIN, rng())
    fixes = [f for _, f in record(gps.measure, lambda t: truth(east_m=120.0, north_m=-45.0), 10, 500)]
    errors = np.array([to_enu(f) for f in fixes]) - [120.0, -45.0, 0.0]
    # With 5000 samples the std estimate's relative error is 1/sqrt(2N) = 1 %.
    np.testing.assert_allclose(errors.std(axis=0), WHITE_GPS.noise_std_m, rtol=0.05)
    assert np.all(np.abs(errors.mean(axis=0)) < 0.01)
    assert (fixes[0].std_east_m, fixes[0].std_north_m, fixes[0].std_up_m) == WHITE_GPS.noise_std_m


@given(
    lat=st.floats(-80, 80),
    lon=st.floats(-180, 180),
    alt=st.floats(-400, 4000),
    east=st.floats(-50_000, 50_000),
    north=st.floats(-50_000, 50_000),
    up=st.floats(-200, 200),
)
def test_enu_to_geodetic_and_back_round_trips_within_a_millimetre(
    lat: float, lon: float, alt: float, east: float, north: float, up: float
) -> None:
    origin = GeodeticOrigin(lat, lon, alt)
    back = pymap3d.geodetic2enu(*enu_to_geodetic(origin, east, north, up), origin.lat_deg, origin.lon_deg, origin.alt_m)
    assert np.all(np.abs(np.array(back) - [east, north, up]) < 1e-3)


@given(
    lat=st.floats(-89.9, 89.9),
    lon=st.floats(-180, 180),
    east=st.floats(-50_000, 50_000),
    north=st.floats(-50_000, 50_000),
    up=st.floats(-200, 200),
)
def test_enu_to_geodetic_is_pymap3ds_conversion(lat: float, lon: float, east: float, north: float, up: float) -> None:
    origin = GeodeticOrigin(lat, lon, 100.0)
    expected = pymap3d.enu2geodetic(east, north, up, origin.lat_deg, origin.lon_deg, origin.alt_m)
    lat_deg, lon_deg, alt_m = enu_to_geodetic(origin, east, north, up)
    assert abs(lat_deg - expected[0]) < 1e-11 and abs(alt_m - expected[2]) < 1e-6
    assert abs(math.remainder(lon_deg - expected[1], 360.0)) < 1e-11


def test_gps_outage_publishes_nothing_in_its_window_and_resumes_after() -> None:
    outage = SensorFault(("gps",), FaultKind.OUTAGE, start_s=2.0, end_s=4.0)
    gps = GpsModel(GpsParams(), ORIGIN, rng(), faults=(outage,))
    for t_s, fix in record(gps.measure, lambda t: truth(east_m=3.0 * t), 10, 6):
        assert (fix is None) == (2.0 <= t_s < 4.0), t_s


def test_gps_outage_placed_on_the_course_follows_the_progress_not_the_clock() -> None:
    outage = SensorFault(("gps",), FaultKind.OUTAGE, start_s=0.0, end_s=1e12, from_m=10.0, to_m=20.0)
    gps = GpsModel(GpsParams(), ORIGIN, rng(), faults=(outage,))
    for t_s in np.arange(0.0, 6.0, 0.1):
        progress = 5.0 * t_s
        fix = gps.measure(SimTruth(progress, 0.0, 0.0, 5.0, 0.0, 0.0, progress, 0), round(t_s * 1e9), t_s)
        assert (fix is None) == (10.0 <= progress < 20.0), progress


def test_gps_jump_offsets_the_fix_by_its_magnitude_only_while_active() -> None:
    jump = SensorFault(("gps",), FaultKind.JUMP, start_s=1.0, end_s=2.0, magnitude=7.5)
    gps = GpsModel(IDEAL_GPS, ORIGIN, rng(), faults=(jump,))
    fixes = record(gps.measure, lambda t: truth(east_m=5.0 * t, north_m=10.0), 10, 3)
    offsets = {t_s: to_enu(fix) - [5.0 * t_s, 10.0, 0.0] for t_s, fix in fixes}
    inside = [offset for t_s, offset in offsets.items() if 1.0 <= t_s < 2.0]
    outside = [offset for t_s, offset in offsets.items() if not 1.0 <= t_s < 2.0]
    assert all(abs(np.hypot(o[0], o[1]) - 7.5) < 1e-3 and abs(o[2]) < 1e-3 for o in inside)
    assert np.ptp(np.array(inside), axis=0).max() < 1e-3  # one direction for the whole jump
    assert all(np.abs(o).max() < 1e-3 for o in outside)


# -- speedometer and magnetometers -------------------------------------------------------------


def test_speedometer_scale_error_shows_as_the_ratio_of_measured_to_true() -> None:
    params = SpeedometerParams()
    speedometer = SpeedometerModel(params, rng())
    readings = [w for _, w in record(speedometer.measure, lambda t: truth(speed_mps=8.0), 50, 20)]
    ratio = np.mean([w.speed_mps for w in readings]) / 8.0
    # Noise on the mean: 0.05 / sqrt(1000) / 8 ~ 2e-4 of the speed.
    assert abs(ratio - (1 + params.scale_error)) < 1e-3
    true_distance = 8.0 * (len(readings) - 1) / 50
    assert math.isclose(readings[-1].odometer_m / true_distance, 1 + params.scale_error, rel_tol=1e-9)


def test_magnetometer_biases_differ_and_headings_wrap_across_plus_minus_pi() -> None:
    # Sweep yaw around the whole circle: true headings pass through +-pi many times.
    def state(t_s: float) -> SimTruth:
        return truth(yaw_rad=wrap_angle(0.37 * t_s))

    for index, params in ((1, MAGNETOMETER_1), (2, MAGNETOMETER_2)):
        mag = MagnetometerModel(index, params, rng(index))
        readings = record(mag.measure, state, 20, 200)
        assert all(-math.pi <= m.heading_from_north_rad <= math.pi and m.magnetometer == index for _, m in readings)
        true_heading = [math.pi / 2 - state(t).yaw_rad for t, _ in readings]
        errors = np.array(
            [wrap_angle(m.heading_from_north_rad - h) for (_, m), h in zip(readings, true_heading, strict=True)]
        )
        assert np.abs(errors).max() < math.radians(abs(params.bias_deg) + 5 * params.noise_std_deg)
        assert abs(math.degrees(errors.mean()) - params.bias_deg) < 0.1
    assert MAGNETOMETER_1.bias_deg != MAGNETOMETER_2.bias_deg


def test_stuck_sensor_repeats_its_last_output_then_recovers() -> None:
    stuck = SensorFault(("magnetometer_1",), FaultKind.STUCK, start_s=1.0, end_s=2.0)
    mag = MagnetometerModel(1, MAGNETOMETER_1, rng(), faults=(stuck,))
    readings = dict(record(mag.measure, lambda t: truth(yaw_rad=0.5 * t), 20, 3))
    frozen = readings[0.95]
    assert all(m == frozen for t, m in readings.items() if 1.0 <= t < 2.0)
    assert readings[2.0] != frozen
