"""Offline replays for navigation: drive a simulated vehicle, measure it with the sensor models,
feed a navigation filter the measurements in arrival order, and compare it with the truth.

Each 100 Hz truth sample goes through the nav sensor models at the nav module's rates (IMU
100 Hz, GPS 10 Hz, speedometer 50 Hz, each magnetometer 20 Hz). Everything is offline and
seeded: the same seed, driver and faults give the same measurements. Two drivers: a scripted one
(10 m/s on a repeating script of straights and left and right curves, for filter tests) and one
that follows a scenario's route with pure pursuit on the true pose (for the accuracy tool).
Lives beside the sensor models because, like them, it reads the simulator's truth.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import numpy as np

from brain.corridor import CoursePath, GeodeticOrigin
from modules.sim.nav.models import (
    MAGNETOMETER_1,
    MAGNETOMETER_2,
    GpsModel,
    GpsParams,
    ImuModel,
    ImuParams,
    MagnetometerModel,
    SpeedometerModel,
    SpeedometerParams,
)
from modules.sim.vehicle import VehicleParams, VehicleState, step
from modules.sim.world import FaultKind, SensorFault
from protocol.messages import ActuatorCommand, GpsFix, ImuSample, MagHeading, WheelSpeed
from protocol.messages import VehicleState as NavState
from rascal.runtime.angles import wrap_angles

ORIGIN = GeodeticOrigin(35.0, -117.0, 700.0)
STEP_NS = 10_000_000  # the simulator's 100 Hz
T0_NS = 1_000_000_000_000  # shared time of the first sample: arbitrary, not zero
SPEED_MPS = 10.0
# (seconds, steering rad): about 62 m radius curves at 0.03 rad, repeated for as long as the drive lasts.
SCRIPT: tuple[tuple[float, float], ...] = (
    (15.0, 0.0),
    (8.0, 0.03),
    (10.0, 0.0),
    (12.0, -0.03),
    (6.0, 0.0),
    (5.0, 0.05),
)


class Truth(NamedTuple):
    """One true state sample, in the shape the sensor models read."""

    east_m: float
    north_m: float
    yaw_rad: float
    speed_mps: float
    yaw_rate_radps: float
    scenario_time_s: float
    progress_m: float = 0.0  # replays schedule their faults by time only


class Event(NamedTuple):
    """A measurement as the filter receives it: arrival order is list order."""

    t_ns: int
    kind: str  # imu, gps, speed, mag
    msg: Any


@dataclass(frozen=True)
class Drive:
    truth: list[Truth]  # sample k is at T0_NS + k * STEP_NS
    events: list[Event]


def gps_outage(start_s: float, end_s: float) -> SensorFault:
    return SensorFault(("gps",), FaultKind.OUTAGE, start_s, end_s)


def gps_jump(start_s: float, end_s: float, metres: float) -> SensorFault:
    return SensorFault(("gps",), FaultKind.JUMP, start_s, end_s, metres)


def t_ns_at(t_s: float) -> int:
    return T0_NS + round(t_s * 100) * STEP_NS


def steering_at(t_s: float) -> float:
    """The scripted steering angle at ``t_s``, repeating the script."""
    t = t_s % sum(d for d, _ in SCRIPT)
    for duration, steering in SCRIPT:
        if t < duration:
            return steering
        t -= duration
    return 0.0


Driver = Callable[[VehicleState, float], ActuatorCommand]


class Navigator(Protocol):
    """What a replay feeds and reads (modules.ins.navigator.InsFilter)."""

    t_ns: int | None

    @property
    def x(self) -> np.ndarray: ...

    @property
    def P(self) -> np.ndarray: ...

    def on_imu(self, msg: ImuSample, t_ns: int) -> None: ...

    def on_gps(self, msg: GpsFix, t_ns: int) -> None: ...

    def on_speed(self, msg: WheelSpeed, t_ns: int) -> None: ...

    def on_mag(self, msg: MagHeading, t_ns: int) -> None: ...

    def state(self, t_ns: int) -> NavState: ...


def scripted_driver(vehicle: VehicleState, t_s: float) -> ActuatorCommand:
    """Hold SPEED_MPS (cruise throttle plus a proportional hold) on the repeating SCRIPT."""
    return ActuatorCommand(0.3 + 0.5 * (SPEED_MPS - vehicle.speed_mps), 0.0, steering_at(t_s))


def route_driver(route: CoursePath, max_speed_mps: float, params: VehicleParams | None = None) -> Driver:
    """Follow ``route`` by pure pursuit on the true pose at its speeds, capped at ``max_speed_mps``,
    stopping at its end. Only offline tools may drive on truth like this."""
    params = params or VehicleParams()
    points = np.column_stack([route.east_m, route.north_m])
    index = [0]

    def driver(vehicle: VehicleState, _t_s: float) -> ActuatorCommand:
        low = index[0]
        near = points[low : low + 60]
        index[0] = low + int(np.argmin(np.hypot(near[:, 0] - vehicle.east_m, near[:, 1] - vehicle.north_m)))
        lookahead_m = 4.0 + 0.5 * vehicle.speed_mps
        target = min(len(points) - 1, index[0] + round(lookahead_m / route.spacing_m))
        dx, dy = points[target, 0] - vehicle.east_m, points[target, 1] - vehicle.north_m
        alpha = math.atan2(dy, dx) - vehicle.yaw_rad
        steering = math.atan2(2.0 * params.wheelbase_m * math.sin(alpha), max(math.hypot(dx, dy), 1e-3))
        at_end = index[0] >= len(points) - 3
        # The route's speed ahead (it starts from rest), but never below a crawl until the end.
        speed = 0.0 if at_end else min(max_speed_mps, max(1.0, float(route.speed_mps[target])))
        error = speed - vehicle.speed_mps
        if error >= 0:
            return ActuatorCommand(min(1.0, 0.3 + 0.5 * error), 0.0, steering)
        return ActuatorCommand(0.0, min(1.0, -0.3 * error), steering)

    return driver


def drive(
    duration_s: float,
    seed: int,
    faults: Sequence[SensorFault] = (),
    driver: Driver = scripted_driver,
    start: VehicleState | None = None,
    origin: GeodeticOrigin = ORIGIN,
) -> Drive:
    """Drive for ``duration_s`` and measure every step; ``seed`` fixes every sensor's noise. By
    default the scripted drive, starting at speed heading north-east (so the first minute is not
    spent accelerating)."""
    params = VehicleParams()
    rngs = [np.random.default_rng([seed, i]) for i in range(5)]
    imu = ImuModel(ImuParams(), rngs[0], faults)
    gps = GpsModel(GpsParams(), origin, rngs[1], faults)
    speedometer = SpeedometerModel(SpeedometerParams(), rngs[2], faults)
    mags = (
        MagnetometerModel(1, MAGNETOMETER_1, rngs[3], faults),
        MagnetometerModel(2, MAGNETOMETER_2, rngs[4], faults),
    )
    vehicle = start or VehicleState(yaw_rad=math.radians(40.0), speed_mps=SPEED_MPS)
    truth: list[Truth] = []
    events: list[Event] = []
    for k in range(round(duration_s * 100) + 1):
        t_s = k * 0.01
        if k:
            step(vehicle, driver(vehicle, t_s), 0.01, params)
        sample = Truth(vehicle.east_m, vehicle.north_m, vehicle.yaw_rad, vehicle.speed_mps, vehicle.yaw_rate_radps, t_s)
        truth.append(sample)
        t_ns = T0_NS + k * STEP_NS
        due: list[tuple[str, Any]] = [("imu", imu.measure(sample, t_ns, t_s))]
        if k % 10 == 0:
            due.append(("gps", gps.measure(sample, t_ns, t_s)))
        if k % 2 == 0:
            due.append(("speed", speedometer.measure(sample, t_ns, t_s)))
        if k % 5 == 0:
            due += [("mag", mag.measure(sample, t_ns, t_s)) for mag in mags]
        events += [Event(t_ns, kind, msg) for kind, msg in due if msg is not None]
    return Drive(truth, events)


def delay(events: Iterable[Event], delays_ns: Mapping[str, int]) -> list[Event]:
    """The events in arrival order when each kind arrives ``delays_ns[kind]`` after its
    measurement time (stamps unchanged): late, out of order with the others."""
    keyed = [(e.t_ns + delays_ns.get(e.kind, 0), i, e) for i, e in enumerate(events)]
    return [e for _, _, e in sorted(keyed)]


class Run(NamedTuple):
    """Per truth sample: the filter's estimate at that time, and what the checks need."""

    east_m: np.ndarray
    north_m: np.ndarray
    yaw_rad: np.ndarray
    speed_mps: np.ndarray
    quality: np.ndarray
    position_var_m2: np.ndarray  # east + north variance
    yaw_var_rad2: np.ndarray
    mag_bias_rad: np.ndarray  # (samples, 2)
    worst_asymmetry: float  # max |P - P'| seen
    min_eigenvalue: float  # smallest eigenvalue of P seen


def run(nav: Navigator, events: Sequence[Event], samples: int, on_event: Callable[[Event], None] | None = None) -> Run:
    """Feed ``events`` to ``nav`` and read its estimate after every IMU sample.
    ``on_event`` sees each event after the filter did."""
    est = np.full((samples, 8), np.nan)
    quality = np.zeros(samples, dtype=int)
    asymmetry, min_eig = 0.0, math.inf
    handlers = {"imu": nav.on_imu, "gps": nav.on_gps, "speed": nav.on_speed, "mag": nav.on_mag}
    for event in events:
        handlers[event.kind](event.msg, event.t_ns)
        if on_event is not None:
            on_event(event)
        newest = nav.t_ns
        if event.kind != "imu" or newest is None or event.t_ns < newest:
            continue  # no estimate yet, or an IMU sample from before the filter started
        k = (event.t_ns - T0_NS) // STEP_NS
        state = nav.state(event.t_ns)
        P = nav.P
        asymmetry = max(asymmetry, float(np.max(np.abs(P - P.T))))
        if k % 10 == 0:  # eigenvalues cost more than the rest of the loop: every 0.1 s is enough
            min_eig = min(min_eig, float(np.linalg.eigvalsh(P)[0]))
        cov = state.covariance
        x = nav.x
        est[k] = (state.east_m, state.north_m, state.yaw_rad, state.speed_mps, cov[0] + cov[6], cov[12], x[6], x[7])
        quality[k] = state.quality
    east, north, yaw, speed, position_var, yaw_var = est[:, :6].T
    return Run(east, north, yaw, speed, quality, position_var, yaw_var, est[:, 6:8], asymmetry, min_eig)


class Errors(NamedTuple):
    position_m: np.ndarray
    yaw_rad: np.ndarray
    speed_mps: np.ndarray


def errors(result: Run, truth: Sequence[Truth]) -> Errors:
    """Estimate minus truth per sample (NaN where the filter had no estimate)."""
    east = np.array([t.east_m for t in truth])
    north = np.array([t.north_m for t in truth])
    yaw = np.array([t.yaw_rad for t in truth])
    speed = np.array([t.speed_mps for t in truth])
    yaw_error = wrap_angles(result.yaw_rad - yaw)
    return Errors(np.hypot(result.east_m - east, result.north_m - north), yaw_error, result.speed_mps - speed)


def window(t0_s: float, t1_s: float) -> slice:
    """Sample indices of [t0_s, t1_s)."""
    return slice(round(t0_s * 100), round(t1_s * 100))


def rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))
