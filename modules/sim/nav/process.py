"""Simulated navigation sensors: the simulator's true state in, IMU, DGPS, speedometer and two
magnetometers out, each on its own channel stamped with the truth sample's measurement time.

Publication is driven by the truth stream, not by a timer: every new SimTruth sample is a
moment the sensors can measure, and each sensor publishes on the samples that fall on its own
rate grid (anchored at the first sample). A sensor can therefore publish at most at the truth
rate (100 Hz from the simulator).

Scenario time, at which the fault schedule is evaluated, is counted from the first truth sample
this process receives: SimTruth carries no scenario clock, so start this module before the
simulator starts stepping, or the schedule shifts by the difference.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from modules.sim.nav.models import (
    MAGNETOMETER_1,
    MAGNETOMETER_2,
    GeodeticOrigin,
    GpsModel,
    GpsParams,
    ImuModel,
    ImuParams,
    MagnetometerModel,
    SpeedometerModel,
    SpeedometerParams,
    TruthState,
)
from modules.sim.scenario import DEFAULT_SCENARIO, load_scenario
from modules.sim.world import SensorFault
from protocol import channels
from protocol.codec import Envelope
from protocol.messages import SimTruth
from rascal.runtime.config import setting
from rascal.runtime.module import Module, Runtime
from rascal.runtime.ports import Port

# Names in the fault schedule, also the order in which per-sensor random streams are spawned.
SENSOR_STREAMS = ("imu", "gps", "speedometer", "magnetometer_1", "magnetometer_2")
# Ten missed samples of the simulator's 100 Hz: the heartbeat then reports SIM_TRUTH as stale.
TRUTH_MAX_AGE_S = 0.1


@dataclass(frozen=True)
class NavSensorsConfig:
    scenario: str = setting(str(DEFAULT_SCENARIO), "scenario TOML: ENU origin, seed and fault schedule")
    seed_offset: int = setting(0, "non-negative, combined with the scenario seed: change it for other noise")
    imu_hz: float = setting(100.0, "IMU rate (at most the truth rate)")
    gps_hz: float = setting(10.0, "DGPS fix rate")
    speedometer_hz: float = setting(50.0, "speedometer rate")
    magnetometer_hz: float = setting(20.0, "rate of each of the two magnetometers")


class ScenarioInputs(NamedTuple):
    """What the sensors need from a scenario."""

    origin: GeodeticOrigin
    seed: int
    faults: tuple[SensorFault, ...]


def scenario_inputs(path: str) -> ScenarioInputs:
    """Origin, seed and fault schedule of the scenario file at ``path``."""
    scenario = load_scenario(path)
    origin = scenario.origin
    return ScenarioInputs(origin, scenario.seed, tuple(scenario.world.faults))


def sensor_generators(seed: int, seed_offset: int) -> dict[str, np.random.Generator]:
    """One independent random stream per sensor, so a change to one sensor (a fault, a rate)
    leaves the others' noise unchanged for the same seed."""
    if seed < 0 or seed_offset < 0:
        raise ValueError(f"nav_sensors: seed ({seed}) and seed_offset ({seed_offset}) must be non-negative")
    children = np.random.SeedSequence([seed, seed_offset]).spawn(len(SENSOR_STREAMS))
    return {name: np.random.default_rng(child) for name, child in zip(SENSOR_STREAMS, children, strict=True)}


SPACING_SMOOTHING = 0.05  # weight of each new sample spacing in the gate's running mean


class RateGate:
    """Picks the samples of an irregular or faster stream that fall on a ``rate_hz`` grid."""

    def __init__(self, rate_hz: float) -> None:
        if rate_hz <= 0:
            raise ValueError(f"rate must be positive, not {rate_hz}")
        self.period_ns = round(1e9 / rate_hz)
        # A sample within half the stream's mean spacing before a grid point counts as on it:
        # scenario time advances by the time that really passed between simulator ticks, so
        # samples jitter around the grid, and a stream as fast as the grid must fill every slot.
        self._last_slot = -1
        self._last_elapsed_ns: int | None = None
        self._mean_spacing_ns: float | None = None  # known from the second sample on

    def due(self, elapsed_ns: int) -> bool:
        """Whether the sample ``elapsed_ns`` after the grid's start opens a new slot."""
        if self._last_elapsed_ns is not None:
            spacing = max(0, elapsed_ns - self._last_elapsed_ns)
            mean = self._mean_spacing_ns
            self._mean_spacing_ns = spacing if mean is None else mean + SPACING_SMOOTHING * (spacing - mean)
        self._last_elapsed_ns = elapsed_ns
        mean = self._mean_spacing_ns if self._mean_spacing_ns is not None else 0.0
        slack = int(min(self.period_ns, mean) // 2)
        slot = (elapsed_ns + slack) // self.period_ns
        if slot <= self._last_slot:
            return False
        self._last_slot = slot
        return True


class SensorSuite:
    """The module's logic without the bus: truth samples in, (channel, message) pairs out."""

    def __init__(self, config: NavSensorsConfig, inputs: ScenarioInputs) -> None:
        rngs = sensor_generators(inputs.seed, config.seed_offset)
        faults = inputs.faults
        self.imu = ImuModel(ImuParams(), rngs["imu"], faults, config.imu_hz)
        self.gps = GpsModel(GpsParams(), inputs.origin, rngs["gps"], faults)
        self.speedometer = SpeedometerModel(SpeedometerParams(), rngs["speedometer"], faults)
        self.magnetometers = (
            MagnetometerModel(1, MAGNETOMETER_1, rngs["magnetometer_1"], faults),
            MagnetometerModel(2, MAGNETOMETER_2, rngs["magnetometer_2"], faults),
        )
        self._gates = {
            channels.IMU: RateGate(config.imu_hz),
            channels.GPS: RateGate(config.gps_hz),
            channels.WHEEL_SPEED: RateGate(config.speedometer_hz),
            channels.MAG_HEADING: RateGate(config.magnetometer_hz),
        }
        self.last_ns: int | None = None
        self.samples = 0
        self.dropped = 0

    def step(self, truth: TruthState, t_meas_ns: int) -> list[tuple[str, Any]]:
        """The measurements due at truth sample ``t_meas_ns``. A sample not newer than the last
        one (reordered on the network) is dropped: a sensor cannot measure the past."""
        if self.last_ns is not None and t_meas_ns <= self.last_ns:
            self.dropped += 1
            return []
        self.last_ns = t_meas_ns
        self.samples += 1
        # Sample rates and faults both run on the simulator's scenario clock, so every sensor
        # process sees the same schedule however late it started.
        t_s = truth.scenario_time_s
        scenario_ns = round(t_s * 1e9)
        due = {channel for channel, gate in self._gates.items() if gate.due(scenario_ns)}
        out: list[tuple[str, Any]] = []
        if channels.IMU in due:
            out.append((channels.IMU, self.imu.measure(truth, t_meas_ns, t_s)))
        if channels.GPS in due:
            out.append((channels.GPS, self.gps.measure(truth, t_meas_ns, t_s)))
        if channels.WHEEL_SPEED in due:
            out.append((channels.WHEEL_SPEED, self.speedometer.measure(truth, t_meas_ns, t_s)))
        if channels.MAG_HEADING in due:
            out.extend((channels.MAG_HEADING, mag.measure(truth, t_meas_ns, t_s)) for mag in self.magnetometers)
        return [(channel, msg) for channel, msg in out if msg is not None]


class NavSensors(Module):
    """Simulated navigation sensors: IMU, DGPS, speedometer and two magnetometers from SIM_TRUTH."""

    name = "nav_sensors"
    default_source_id = 10
    Config = NavSensorsConfig
    interface = (
        Port("in", "`SIM_TRUTH`", "SimTruth", "100 Hz (the simulator's step)", "0.1 s (heartbeat reports it stale)"),
        Port(
            "out",
            "`IMU`",
            "ImuSample (body frame x forward, y left, z up; specific force includes gravity)",
            "`imu_hz` (100)",
        ),
        Port("out", "`GPS`", "GpsFix (WGS84, quality DGPS; nothing during an outage)", "`gps_hz` (10)"),
        Port("out", "`WHEEL_SPEED`", "WheelSpeed (speed and odometer, with scale error)", "`speedometer_hz` (50)"),
        Port(
            "out",
            "`MAG_HEADING`",
            "MagHeading, `magnetometer` 1 and 2 (heading clockwise from north)",
            "`magnetometer_hz` (20) each",
        ),
        Port("out", "`MODULE_STATUS`", "ModuleStatus", "1 Hz"),
    )

    def __init__(self, config: NavSensorsConfig, runtime: Runtime, inputs: ScenarioInputs | None = None) -> None:
        """``inputs`` replaces reading the scenario file (tests, or a caller that has it loaded)."""
        super().__init__(config, runtime)
        self._inputs = inputs
        self.published = 0

    def on_start(self) -> None:
        inputs = self._inputs if self._inputs is not None else scenario_inputs(self.config.scenario)
        self.suite = SensorSuite(self.config, inputs)
        self.truth = self.input(channels.SIM_TRUTH, TRUTH_MAX_AGE_S)
        self.bus.subscribe(channels.SIM_TRUTH, self.on_truth)

    def on_truth(self, truth: SimTruth, envelope: Envelope) -> None:
        for channel, msg in self.suite.step(truth, envelope.t_meas_ns):
            self.bus.publish(channel, msg, t_meas_ns=envelope.t_meas_ns)
            self.published += 1

    def status_detail(self) -> str:
        return f"truth {self.suite.samples} (dropped {self.suite.dropped}), published {self.published}"
