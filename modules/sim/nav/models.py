"""Navigation sensor models: the true vehicle state in, one noisy measurement out.

Pure and seeded: every model draws from the ``numpy.random.Generator`` it is handed, reads no
clock and does no I/O, so a seed and a truth sequence fix every output. Each model's
``measure(truth, t_ns, t_s)`` takes one true state sample, its time ``t_ns`` (shared-time
nanoseconds; only differences are used) and ``t_s``, seconds since the scenario started, at
which (with the sample's course progress) the fault schedule is evaluated. It returns the bus
message, or None when the sensor is silent. Models draw the same random numbers whatever the
faults, so a fault never shifts the noise that follows it.

Faults (``modules.sim.world.SensorFault``), combined as every simulated sensor combines them (modules/sim/sensing.py):

- SILENCE and OUTAGE: no output. For the GPS an outage is no fix at all rather than a fix
  marked INVALID, so no consumer can mistake a stand-in for a position; a filter detects it
  as a GPS input that goes stale (fixes are due every 0.1 s).
- STUCK: the last output repeats (nothing until there was one).
- NOISE: the white noise is multiplied by ``magnitude`` (the reported std is not: the sensor
  does not know).
- JUMP (GPS only): the position is offset by ``magnitude`` metres in a horizontal direction
  drawn per fault from the seed, constant while the fault is active; quality stays DGPS, as a
  receiver with a wrong fix does not know it is wrong.

Frames: truth is planar, in the course's ENU frame, and the ground is flat (SimTruth has no
height, roll or pitch). The IMU body frame is x forward, y left, z up.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

import numpy as np
import pymap3d

from brain.corridor import WGS84, GeodeticOrigin
from brain.pose import PoseLike
from modules.sim.sensing import NO_FAULT, FaultEffect, StuckGate, fault_effect
from modules.sim.world import FaultKind, SensorFault, World
from protocol.messages import GpsFix, ImuSample, MagHeading, NavQuality, WheelSpeed
from rascal.runtime.angles import wrap_angle

STANDARD_GRAVITY_MPS2 = 9.80665  # defines the milli-g of accelerometer specifications
# The simulated world's gravity: the vehicle model (modules/sim/vehicle.py) uses the same.
WORLD_GRAVITY_MPS2 = 9.81
DEG_PER_H_TO_RADPS = math.radians(1.0) / 3600.0
# A random-walk coefficient per sqrt(hour) is the noise density per sqrt(Hz) divided by 60.
PER_SQRT_H_TO_PER_SQRT_S = 1.0 / 60.0
MILLI_G_TO_MPS2 = STANDARD_GRAVITY_MPS2 / 1000.0

M = TypeVar("M")


class TruthState(PoseLike, Protocol):
    """What the sensors see of a true state sample (``protocol.messages.SimTruth`` is one)."""

    @property
    def speed_mps(self) -> float: ...

    @property
    def yaw_rate_radps(self) -> float: ...

    @property
    def scenario_time_s(self) -> float: ...

    @property
    def progress_m(self) -> float: ...


class GaussMarkov:
    """First-order Gauss-Markov process per axis (dx/dt = -x/tau + w), stationary std ``sigma``.

    It models bias drift and slow position error: bounded like a real bias instability, unlike
    a random walk. It starts at zero, so a configured turn-on bias is the bias at power-on.
    """

    def __init__(self, sigma: float, correlation_s: float, rng: np.random.Generator, axes: int) -> None:
        if sigma < 0 or correlation_s <= 0:
            raise ValueError("Gauss-Markov process: sigma must be >= 0 and correlation time > 0")
        self.sigma = sigma
        self.correlation_s = correlation_s
        self.values = [0.0] * axes  # plain floats: three-element numpy arithmetic costs more than it does
        self._rng = rng

    @property
    def value(self) -> np.ndarray:
        return np.array(self.values)

    def step(self, dt_s: float) -> list[float]:
        """Advance by ``dt_s`` seconds (exact discretisation, any step size) and return the value."""
        phi = math.exp(-dt_s / self.correlation_s)
        drive = self.sigma * math.sqrt(1.0 - phi * phi)
        normals = self._rng.standard_normal(len(self.values)).tolist()
        self.values = [phi * value + drive * normal for value, normal in zip(self.values, normals, strict=True)]
        return self.values


class _Sensor(Generic[M]):
    """Fault schedule lookup and the output gate (silence, stuck) shared by every model."""

    def __init__(self, name: str, faults: Sequence[SensorFault]) -> None:
        self.name = name
        # Only this sensor's faults: most sensors have none, and then every sample is clear.
        self._schedule = World(faults=tuple(fault for fault in faults if name in fault.sensors))
        self._gate: StuckGate[M] = StuckGate()
        self._prev_t_ns: int | None = None

    def _effect(self, truth: TruthState, t_s: float) -> FaultEffect:
        if not self._schedule.faults:
            return NO_FAULT
        return fault_effect(self._schedule, self.name, t_s, truth.progress_m)

    def _elapsed_s(self, t_ns: int) -> float | None:
        """Seconds since the previous call (None on the first), remembering ``t_ns``."""
        prev = self._prev_t_ns
        if prev is not None and t_ns <= prev:
            raise ValueError(f"{self.name}: measurement times must increase ({t_ns} after {prev})")
        self._prev_t_ns = t_ns
        return None if prev is None else (t_ns - prev) / 1e9

    def _emit(self, effect: FaultEffect, measurement: M) -> M | None:
        """The measurement, made whatever the faults (its noise processes run on), as they allow."""
        return self._gate.emit(effect, lambda: measurement)


@dataclass(frozen=True)
class ImuParams:
    """A tactical-grade IMU (the class of RASCAL's GIC-100; its datasheet values were not at
    hand, so these are mid-range values of that class: gyro bias 1-10 deg/h, angle random walk
    0.1-0.2 deg/sqrt(h), accelerometer bias ~1 mg, velocity random walk ~0.05 m/s/sqrt(h)).

    Bias = a fixed turn-on bias per axis (x, y, z) plus a Gauss-Markov in-run drift with the
    given instability (stationary std) and correlation time.
    """

    gyro_bias_deg_per_h: tuple[float, float, float] = (4.0, -3.0, 5.0)
    gyro_bias_instability_deg_per_h: float = 1.0  # typical tactical in-run bias stability
    gyro_bias_correlation_s: float = 300.0  # minutes-scale thermal drift
    gyro_arw_deg_per_sqrt_h: float = 0.15
    accel_bias_mg: tuple[float, float, float] = (1.0, -0.8, 0.6)
    accel_bias_instability_mg: float = 0.1  # assumed: a tenth of the turn-on bias
    accel_bias_correlation_s: float = 300.0
    accel_vrw_mps_per_sqrt_h: float = 0.05
    gravity_mps2: float = WORLD_GRAVITY_MPS2


class ImuModel(_Sensor[ImuSample]):
    """Body-frame specific force and angular rate of a vehicle on flat ground.

    True specific force: longitudinal = d(speed)/dt over the interval since the previous call
    (zero on the first), lateral = speed * yaw_rate (centripetal, left positive in a left turn),
    vertical = +gravity (the ground pushes up). True rate: yaw rate on z only.
    """

    def __init__(
        self,
        params: ImuParams,
        rng: np.random.Generator,
        faults: Sequence[SensorFault] = (),
        rate_hz: float = 100.0,
    ) -> None:
        super().__init__("imu", faults)
        if rate_hz <= 0:
            raise ValueError("imu: rate_hz must be positive")
        self.params = params
        self._rng = rng
        self._gyro_bias0 = np.asarray(params.gyro_bias_deg_per_h) * DEG_PER_H_TO_RADPS
        self._accel_bias0 = np.asarray(params.accel_bias_mg) * MILLI_G_TO_MPS2
        self._gyro_drift = GaussMarkov(
            params.gyro_bias_instability_deg_per_h * DEG_PER_H_TO_RADPS, params.gyro_bias_correlation_s, rng, 3
        )
        self._accel_drift = GaussMarkov(
            params.accel_bias_instability_mg * MILLI_G_TO_MPS2, params.accel_bias_correlation_s, rng, 3
        )
        # A random walk with density N per sqrt(Hz), sampled at fs, is white noise of std
        # N * sqrt(fs) per sample: the sample rate sets the noise bandwidth.
        sqrt_rate = math.sqrt(rate_hz)
        self.gyro_noise_radps = math.radians(params.gyro_arw_deg_per_sqrt_h) * PER_SQRT_H_TO_PER_SQRT_S * sqrt_rate
        self.accel_noise_mps2 = params.accel_vrw_mps_per_sqrt_h * PER_SQRT_H_TO_PER_SQRT_S * sqrt_rate
        self._prev_speed_mps: float | None = None

    @property
    def gyro_bias_radps(self) -> np.ndarray:
        """The gyro bias now (turn-on plus drift), per axis."""
        return self._gyro_bias0 + self._gyro_drift.value

    @property
    def accel_bias_mps2(self) -> np.ndarray:
        """The accelerometer bias now (turn-on plus drift), per axis."""
        return self._accel_bias0 + self._accel_drift.value

    def measure(self, truth: TruthState, t_ns: int, t_s: float) -> ImuSample | None:
        """One IMU sample at ``t_ns``; ``t_s`` (scenario seconds) selects the active faults."""
        dt_s = self._elapsed_s(t_ns)
        long_accel = 0.0
        if dt_s is not None:
            self._gyro_drift.step(dt_s)
            self._accel_drift.step(dt_s)
            assert self._prev_speed_mps is not None
            long_accel = (truth.speed_mps - self._prev_speed_mps) / dt_s
        self._prev_speed_mps = truth.speed_mps
        effect = self._effect(truth, t_s)
        noise = (self._rng.standard_normal(6) * effect.noise_scale).tolist()
        true_accel = (long_accel, truth.speed_mps * truth.yaw_rate_radps, self.params.gravity_mps2)
        true_rate = (0.0, 0.0, truth.yaw_rate_radps)
        accel = _biased(
            true_accel, self._accel_bias0.tolist(), self._accel_drift.values, noise[:3], self.accel_noise_mps2
        )
        gyro = _biased(true_rate, self._gyro_bias0.tolist(), self._gyro_drift.values, noise[3:], self.gyro_noise_radps)
        return self._emit(effect, ImuSample(*accel, *gyro))


def _biased(
    true: Sequence[float], bias0: Sequence[float], drift: Sequence[float], noise: Sequence[float], noise_std: float
) -> list[float]:
    """Per axis: truth + (turn-on bias + drift) + noise * its std."""
    return [t + (b + d) + n * noise_std for t, b, d, n in zip(true, bias0, drift, noise, strict=True)]


def enu_to_geodetic(origin: GeodeticOrigin, east_m: float, north_m: float, up_m: float) -> tuple[float, float, float]:
    """(lat_deg, lon_deg, alt_m) of a point given in the ENU frame of ``origin`` (WGS84): what
    pymap3d.enu2geodetic computes, in scalar ``math`` (pymap3d's array code costs ~100 us a fix)."""
    x0, y0, z0, sin_lat, cos_lat, sin_lon, cos_lon = _enu_frame(origin)
    t = cos_lat * up_m - sin_lat * north_m
    w = sin_lat * up_m + cos_lat * north_m
    u = cos_lon * t - sin_lon * east_m
    v = sin_lon * t + cos_lon * east_m
    return _ecef_to_geodetic(x0 + u, y0 + v, z0 + w)


@functools.lru_cache(maxsize=8)
def _enu_frame(origin: GeodeticOrigin) -> tuple[float, float, float, float, float, float, float]:
    """The origin in ECEF and the sines and cosines of its latitude and longitude."""
    x0, y0, z0 = pymap3d.geodetic2ecef(origin.lat_deg, origin.lon_deg, origin.alt_m)
    lat, lon = math.radians(origin.lat_deg), math.radians(origin.lon_deg)
    return float(x0), float(y0), float(z0), math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)


def _ecef_to_geodetic(x: float, y: float, z: float) -> tuple[float, float, float]:
    """WGS84 latitude and longitude (degrees) and height of an ECEF point, by You (2000), the
    closed form pymap3d.ecef2geodetic uses."""
    a, b = WGS84.semimajor_axis, WGS84.semiminor_axis
    e2 = a * a - b * b
    r2 = x * x + y * y + z * z
    u = math.sqrt(0.5 * (r2 - e2) + 0.5 * math.hypot(r2 - e2, 2 * math.sqrt(e2) * z))
    hxy = math.hypot(x, y)
    hue = math.hypot(u, math.sqrt(e2))
    if u == 0.0 or hxy == 0.0:  # the centre or a pole
        beta = 0.0 if z == 0.0 else math.copysign(math.pi / 2, z)
    else:
        beta = math.atan(hue / u * z / hxy)
        beta += ((b * u - a * hue + e2) * math.sin(beta)) / (a * hue / math.cos(beta) - e2 * math.cos(beta))
    lat = math.atan(a / b * math.tan(beta))
    alt = math.hypot(z - b * math.sin(beta), hxy - a * math.cos(beta))
    if (x * x + y * y) / (a * a) + z * z / (b * b) < 1:
        alt = -alt
    return math.degrees(lat), math.degrees(math.atan2(y, x)), alt


@dataclass(frozen=True)
class GpsParams:
    """A differential GPS receiver (decimetre class, like a carrier-phase differential service).

    Error per axis (east, north, up) = white noise + a slow Gauss-Markov wander (multipath and
    correction latency change over minutes, not samples). Vertical errors are about twice the
    horizontal, as the satellite geometry is weaker vertically. The antenna is taken to be at
    the vehicle's reference point (no lever arm), at the origin's altitude (flat course).
    """

    noise_std_m: tuple[float, float, float] = (0.1, 0.1, 0.2)
    wander_std_m: tuple[float, float, float] = (0.05, 0.05, 0.1)
    wander_correlation_s: float = 120.0
    satellites: int = 9  # a typical open-sky count; reported, not modelled


class GpsModel(_Sensor[GpsFix]):
    """DGPS fixes in WGS84 from the true ENU position; reported std = white noise and wander
    combined."""

    def __init__(
        self, params: GpsParams, origin: GeodeticOrigin, rng: np.random.Generator, faults: Sequence[SensorFault] = ()
    ) -> None:
        super().__init__("gps", faults)
        self.params = params
        self.origin = origin
        self._rng = rng
        self._noise_m = np.asarray(params.noise_std_m)
        # One unit-variance process scaled per axis, as the axes' wander stds differ.
        self._wander = GaussMarkov(1.0, params.wander_correlation_s, rng, 3)
        self._wander_std_m = np.asarray(params.wander_std_m)
        self._std_m = tuple(float(s) for s in np.hypot(self._noise_m, self._wander_std_m))
        # Directions are drawn up front, in schedule order, so they depend on the seed alone.
        self._jump_direction_rad = {
            fault: float(rng.uniform(-math.pi, math.pi))
            for fault in faults
            if fault.kind is FaultKind.JUMP and self.name in fault.sensors
        }

    def measure(self, truth: TruthState, t_ns: int, t_s: float) -> GpsFix | None:
        """One fix at ``t_ns``; ``t_s`` (scenario seconds) selects the active faults."""
        dt_s = self._elapsed_s(t_ns)
        if dt_s is not None:
            self._wander.step(dt_s)
        effect = self._effect(truth, t_s)
        normals = (self._rng.standard_normal(3) * self._noise_m * effect.noise_scale).tolist()
        wander = (self._wander.value * self._wander_std_m).tolist()
        east, north, up = (
            position + (drift + noise) + jump
            for position, drift, noise, jump in zip(
                (truth.east_m, truth.north_m, 0.0), wander, normals, self._jump_offset(effect), strict=True
            )
        )
        lat, lon, alt = enu_to_geodetic(self.origin, east, north, up)
        fix = GpsFix(lat, lon, alt, *self._std_m, int(NavQuality.DGPS), self.params.satellites)
        return self._emit(effect, fix)

    def _jump_offset(self, effect: FaultEffect) -> tuple[float, float, float]:
        east, north = 0.0, 0.0
        for fault in effect.jumps:
            direction = self._jump_direction_rad[fault]
            east += fault.magnitude * math.cos(direction)
            north += fault.magnitude * math.sin(direction)
        return east, north, 0.0


@dataclass(frozen=True)
class SpeedometerParams:
    """A wheel-speed sensor. The scale error is the tyre's effective rolling radius being off
    by 1-2 % (load, pressure, wear); the noise is tick quantisation over a short window."""

    scale_error: float = 0.015  # measured = (1 + scale_error) * true
    noise_std_mps: float = 0.05


class SpeedometerModel(_Sensor[WheelSpeed]):
    """Speed and odometer. The odometer counts wheel rotation, so it carries the scale error
    but not the speed noise; it is signed like the speed (reversing winds it back), so its
    differences are displacements along the body x axis."""

    def __init__(self, params: SpeedometerParams, rng: np.random.Generator, faults: Sequence[SensorFault] = ()) -> None:
        super().__init__("speedometer", faults)
        self.params = params
        self._rng = rng
        self._scale = 1.0 + params.scale_error
        self.odometer_m = 0.0
        self._prev_speed_mps: float | None = None

    def measure(self, truth: TruthState, t_ns: int, t_s: float) -> WheelSpeed | None:
        """Speed and odometer at ``t_ns``; ``t_s`` (scenario seconds) selects the active faults."""
        dt_s = self._elapsed_s(t_ns)
        if dt_s is not None:
            assert self._prev_speed_mps is not None
            # Trapezoid: exact for the piecewise-linear speed a stepped simulator produces.
            self.odometer_m += self._scale * 0.5 * (self._prev_speed_mps + truth.speed_mps) * dt_s
        self._prev_speed_mps = truth.speed_mps
        effect = self._effect(truth, t_s)
        noise = float(self._rng.standard_normal()) * self.params.noise_std_mps * effect.noise_scale
        return self._emit(effect, WheelSpeed(self._scale * truth.speed_mps + noise, self.odometer_m))


@dataclass(frozen=True)
class MagnetometerParams:
    """A heading magnetometer (fluxgate compass). The bias is what calibration leaves: hard and
    soft iron of the vehicle and the declination model's error, a few degrees, constant over a
    run. Reported std is the noise only: the bias is unknown to the sensor, and the two units'
    different biases are what lets a filter notice and estimate it."""

    bias_deg: float
    noise_std_deg: float = 0.5


MAGNETOMETER_1 = MagnetometerParams(bias_deg=2.0)
MAGNETOMETER_2 = MagnetometerParams(bias_deg=-3.0)


class MagnetometerModel(_Sensor[MagHeading]):
    """Heading clockwise from north (``pi/2 - yaw``) with bias and noise, wrapped to [-pi, pi].
    Unit ``index`` (1 or 2) is sensor ``magnetometer_<index>`` in the fault schedule."""

    def __init__(
        self, index: int, params: MagnetometerParams, rng: np.random.Generator, faults: Sequence[SensorFault] = ()
    ) -> None:
        super().__init__(f"magnetometer_{index}", faults)
        self.index = index
        self.params = params
        self._rng = rng
        self._bias_rad = math.radians(params.bias_deg)
        self._noise_rad = math.radians(params.noise_std_deg)

    def measure(self, truth: TruthState, t_ns: int, t_s: float) -> MagHeading | None:
        """One heading at ``t_ns``; ``t_s`` (scenario seconds) selects the active faults."""
        self._elapsed_s(t_ns)  # no dynamics here; called to hold it to increasing times like the others
        effect = self._effect(truth, t_s)
        noise = float(self._rng.standard_normal()) * self._noise_rad * effect.noise_scale
        heading = wrap_angle(math.pi / 2 - truth.yaw_rad + self._bias_rad + noise)
        return self._emit(effect, MagHeading(self.index, heading, self._noise_rad))
