"""The nav_sensors module: truth over an in-process bus in, sensor channels out."""

from __future__ import annotations

import math
import uuid
from collections import Counter
from typing import Any

import numpy as np

from brain.corridor import GeodeticOrigin
from modules.sim.nav.process import NavSensors, NavSensorsConfig, RateGate, ScenarioInputs, SensorSuite
from modules.sim.world import FaultKind, SensorFault
from protocol import channels
from protocol.auth import Keyring
from protocol.codec import Envelope
from protocol.messages import SimTruth
from protocol.transport import MemTransport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import ManualClock
from rascal.runtime.module import Runtime

ORIGIN = GeodeticOrigin(35.0, -116.5, 700.0)
TRUTH_PERIOD_NS = 10_000_000  # the simulator's 100 Hz
OUTPUTS = (channels.IMU, channels.GPS, channels.WHEEL_SPEED, channels.MAG_HEADING)


def driving(t_s: float) -> SimTruth:
    """A vehicle accelerating through a gentle left turn."""
    speed = 5.0 + 0.5 * t_s
    yaw = 0.3 + 0.1 * t_s
    return SimTruth(2.0 * t_s, 3.0 * t_s, yaw, speed, 0.1, 0.05, speed * t_s, 0, scenario_time_s=t_s)


class Rig:
    """A simulator stand-in publishing SIM_TRUTH, the module under test and a listener, all on
    one mem:// hub and one manual clock that advances with the truth."""

    def __init__(self, inputs: ScenarioInputs, start_ns: int = 1_700_000_000_000_000_000) -> None:
        hub, keyring = uuid.uuid4().hex, Keyring.generate()
        self.clock = ManualClock(start_ns)
        self.sim = Bus(MemTransport(hub), 90, keyring, self.clock)
        runtime = Runtime(Bus(MemTransport(hub), NavSensors.default_source_id, keyring, self.clock), self.clock)
        self.module = NavSensors(NavSensorsConfig(), runtime, inputs=inputs)
        self.module.on_start()
        self.listener = Bus(MemTransport(hub), 91, keyring, self.clock)
        self.received: list[tuple[str, Any, Envelope]] = []
        for channel in OUTPUTS:
            self.listener.subscribe(channel, lambda msg, env: self.received.append((env.channel, msg, env)))
        self.truth_times: list[int] = []

    def run(self, samples: int) -> None:
        for k in range(samples):
            t_meas_ns = self.clock.t_ns
            self.sim.publish(channels.SIM_TRUTH, driving(k * TRUTH_PERIOD_NS / 1e9), t_meas_ns=t_meas_ns)
            self.truth_times.append(t_meas_ns)
            self.module.bus.poll()
            self.listener.poll()
            self.clock.advance(TRUTH_PERIOD_NS)

    def times(self, channel: str) -> list[int]:
        return [env.t_meas_ns for ch, _, env in self.received if ch == channel]


def test_two_seconds_of_truth_give_the_configured_rates_stamped_with_truth_times() -> None:
    rig = Rig(ScenarioInputs(ORIGIN, seed=3, faults=()))
    rig.run(200)
    counts = Counter(channel for channel, _, _ in rig.received)
    magnetometers = Counter(msg.magnetometer for channel, msg, _ in rig.received if channel == channels.MAG_HEADING)
    assert counts[channels.IMU] == 2 * 100
    assert counts[channels.GPS] == 2 * 10
    assert counts[channels.WHEEL_SPEED] == 2 * 50
    assert magnetometers == {1: 2 * 20, 2: 2 * 20}
    assert rig.times(channels.IMU) == rig.truth_times
    assert rig.times(channels.GPS) == rig.truth_times[::10]
    assert rig.times(channels.WHEEL_SPEED) == rig.truth_times[::2]
    assert rig.times(channels.MAG_HEADING) == [t for t in rig.truth_times[::5] for _ in (1, 2)]
    assert all(env.source_id == NavSensors.default_source_id for _, _, env in rig.received)


def test_fault_schedule_runs_on_the_simulators_scenario_time() -> None:
    outage = SensorFault(("gps",), FaultKind.OUTAGE, start_s=0.5, end_s=1.0)
    rig = Rig(ScenarioInputs(ORIGIN, seed=3, faults=(outage,)))
    rig.run(200)
    start = rig.truth_times[0]
    gps_scenario_s = [(t - start) / 1e9 for t in rig.times(channels.GPS)]
    expected = [k / 10 for k in range(20) if not 0.5 <= k / 10 < 1.0]
    assert all(math.isclose(a, b, abs_tol=1e-9) for a, b in zip(gps_scenario_s, expected, strict=True))
    assert len(rig.times(channels.IMU)) == 200  # other sensors unaffected


def test_same_seed_gives_identical_outputs_and_another_seed_does_not() -> None:
    faults = (SensorFault(("gps",), FaultKind.JUMP, 0.5, 1.5, magnitude=4.0),)

    def outputs(seed: int) -> list[tuple[str, Any]]:
        suite = SensorSuite(NavSensorsConfig(), ScenarioInputs(ORIGIN, seed, faults))
        out: list[tuple[str, Any]] = []
        for k in range(300):
            out.extend(suite.step(driving(k / 100), 5_000_000_000 + k * TRUTH_PERIOD_NS))
        return out

    first = outputs(42)
    assert first == outputs(42)
    assert first != outputs(43)
    assert {channel for channel, _ in first} == set(OUTPUTS)


def test_a_reordered_truth_sample_is_dropped() -> None:
    suite = SensorSuite(NavSensorsConfig(), ScenarioInputs(ORIGIN, 1, ()))
    assert suite.step(driving(0.0), 2 * TRUTH_PERIOD_NS)
    assert suite.step(driving(0.0), TRUTH_PERIOD_NS) == []
    assert suite.dropped == 1


def test_a_jittered_stream_fills_every_slot_of_a_grid_as_fast_as_itself() -> None:
    """Scenario time jitters with the simulator's ticks (it is the time that really passed):
    100 Hz truth with +-3 ms jitter still gives 100 IMU samples a second and 10 GPS fixes."""
    rng = np.random.default_rng(1)
    stamps = [0] + [round((k * 0.01 + rng.uniform(-0.003, 0.003)) * 1e9) for k in range(1, 1000)]
    imu, gps = RateGate(100.0), RateGate(10.0)
    assert sum(imu.due(t) for t in stamps) == 1000
    assert sum(gps.due(t) for t in stamps) == 100
