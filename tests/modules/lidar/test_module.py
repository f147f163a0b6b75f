"""The lidar process over an in-process bus: fed a SimTruth stream, with an injected world."""

from __future__ import annotations

import math
import types
import uuid
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from modules.sim.lidar import process as lidar_module
from modules.sim.lidar.process import CHANNELS, SOURCE_IDS, Lidar, LidarConfig
from modules.sim.world import FaultKind, HazardKind, SensorFault, Shape, TerrainHazard, World, WorldObstacle
from protocol import channels
from protocol.auth import Keyring
from protocol.codec import Envelope
from protocol.messages import Frame, GroundSweep, ObstacleList, Sensor, SimTruth, SurfaceProfile
from protocol.transport import MemTransport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import ManualClock
from rascal.runtime.module import Runtime

TRUTH_PERIOD_NS = 40_000_000  # 25 Hz, one truth sample per lidar tick
SIM_SOURCE = 90

# Driving east along y = 0 at 5 m/s past a post and over a ditch.
WORLD = World(
    obstacles=(WorldObstacle("post", Shape.CYLINDER, 30.0, 3.0, 2.0, radius_m=0.5),),
    hazards=(TerrainHazard("ditch", HazardKind.DITCH, 9.5, 0.0, 0.0, 3.0, 8.0, 0.6),),
)


@dataclass
class Harness:
    """A lidar, a simulator stand-in publishing truth, and a listener, all on one mem:// hub."""

    lidar: Lidar
    clock: ManualClock
    sim: Bus
    listener: Bus
    received: list[tuple[Any, Envelope]] = field(default_factory=list)
    t0_ns: int = 0

    def step(self, k: int, speed_mps: float = 5.0) -> list[tuple[Any, Envelope]]:
        """Truth sample k (scenario time k * 40 ms), then one lidar tick; what the lidar published."""
        t_ns = self.t0_ns + k * TRUTH_PERIOD_NS
        self.clock.t_ns = t_ns + 1_000_000
        t_s = k * TRUTH_PERIOD_NS / 1e9
        truth = SimTruth(speed_mps * t_s, 0.0, 0.0, speed_mps, 0.0, 0.0, speed_mps * t_s, 0, scenario_time_s=t_s)
        self.sim.publish(channels.SIM_TRUTH, truth, t_meas_ns=t_ns)
        self.lidar.bus.poll()
        self.lidar.sweep()
        before = len(self.received)
        self.listener.poll()
        return self.received[before:]


def make(sensor: str, world: World = WORLD, seed: int = 5, **config: Any) -> Harness:
    hub, keyring, clock = uuid.uuid4().hex, Keyring.generate(), ManualClock()
    runtime = Runtime(Bus(MemTransport(hub), SOURCE_IDS[sensor], keyring, clock), clock)
    lidar = Lidar(LidarConfig(sensor=sensor, **config), runtime, world=world, seed=seed)
    lidar.on_start()
    harness = Harness(
        lidar, clock, Bus(MemTransport(hub), SIM_SOURCE, keyring, clock), Bus(MemTransport(hub), 99, keyring, clock)
    )
    harness.t0_ns = clock.t_ns
    harness.listener.subscribe(CHANNELS[sensor], lambda msg, env: harness.received.append((msg, env)))
    return harness


def test_a_horizontal_lidar_publishes_obstacles_in_the_vehicle_frame_at_the_truth_time() -> None:
    harness = make("lidar_h_left")
    outputs = [out for k in range(10) for out in harness.step(k)]
    assert len(outputs) == 10
    for k, (message, envelope) in enumerate(outputs):
        assert isinstance(message, ObstacleList)
        assert message.sensor == Sensor.LIDAR_H_LEFT and message.frame == Frame.VEHICLE
        assert envelope.t_meas_ns == harness.t0_ns + k * TRUTH_PERIOD_NS
        assert envelope.source_id == 21
        (post,) = message.obstacles
        assert math.hypot(post.x_m - (30.0 - 0.2 * k), post.y_m - 3.0) <= 0.2


def test_a_vertical_lidar_publishes_the_ground_profile() -> None:
    harness = make("lidar_v_right")
    (message, envelope), *_ = harness.step(0)
    assert isinstance(message, SurfaceProfile)
    assert message.sensor == Sensor.LIDAR_V_RIGHT and message.lateral_m == -0.5
    assert envelope.source_id == 24
    assert -0.61 < min(message.heights_m) < -0.3  # the ditch, its bottom partly in shadow
    assert "ditch" in harness.lidar.status_detail()


def test_the_sweeping_lidar_publishes_the_ground_line_across_the_road() -> None:
    # A wash under the scan line (37 m ahead of the rear axle) and the post in front of it.
    wash = TerrainHazard("wash", HazardKind.DITCH, 38.0, 0.0, 0.0, 2.5, 14.0, 0.7)
    harness = make("lidar_sweep", World(obstacles=WORLD.obstacles, hazards=(wash,)))
    (message, envelope), *_ = harness.step(0)
    assert isinstance(message, GroundSweep)
    assert message.sensor == Sensor.LIDAR_SWEEP and envelope.source_id == 25
    low = [stretch for stretch in message.stretches if stretch.height_m < 0]
    assert min(s.y_right_m for s in low) == pytest.approx(-7.0, abs=0.2)
    assert max(s.y_left_m for s in low) == pytest.approx(7.0, abs=0.2)
    (post,) = [stretch for stretch in message.stretches if stretch.height_m > 0]
    assert post.y_right_m < 3.0 < post.y_left_m and post.x_near_m == pytest.approx(29.5, abs=0.2)
    assert "low" in harness.lidar.status_detail()


def test_nothing_is_published_without_a_fresh_pose() -> None:
    harness = make("lidar_h_right")
    harness.lidar.sweep()
    assert harness.lidar.published == 0
    harness.step(0)
    harness.clock.advance(10 * TRUTH_PERIOD_NS)  # no new truth: no new measurement...
    harness.lidar.sweep()
    harness.clock.advance(1_000_000_000)  # ...and a stale one places nothing
    harness.lidar.sweep()
    assert harness.lidar.published == 1


def faults(*faults: SensorFault) -> World:
    return World(obstacles=WORLD.obstacles, hazards=WORLD.hazards, faults=faults)


def test_silence_publishes_nothing_exactly_within_its_window() -> None:
    # The overheated USB hub: every lidar at once, from 1.0 s to 2.0 s of scenario time.
    world = faults(SensorFault(("lidars",), FaultKind.SILENCE, 1.0, 2.0))
    for sensor in SOURCE_IDS:
        harness = make(sensor, world)
        silent = [k for k in range(75) if not harness.step(k)]
        assert silent == list(range(25, 50)), sensor


def test_noise_scales_the_range_noise_exactly_within_its_window() -> None:
    world = faults(SensorFault(("lidar_v_left",), FaultKind.NOISE, 1.0, 2.0, magnitude=30.0))
    harness = make("lidar_v_left", world=World(faults=world.faults))  # flat ground: heights are noise
    spread = []
    for k in range(75):
        ((message, _),) = harness.step(k)
        spread.append(max(abs(z) for z in message.heights_m))
    # 1 cm noise along beams 3.7..28 deg below horizontal: heights within a few cm; x30: far more.
    assert [k for k, worst in enumerate(spread) if worst > 0.1] == list(range(25, 50))


def test_stuck_repeats_the_last_measurement_exactly_within_its_window() -> None:
    world = faults(SensorFault(("lidar_h_left",), FaultKind.STUCK, 1.0, 2.0))
    harness = make("lidar_h_left", world)
    outputs = [harness.step(k)[0] for k in range(75)]
    last_good = outputs[24][0]
    repeated = [k for k, (message, _) in enumerate(outputs) if message == last_good]
    assert repeated == list(range(24, 50))
    # Stamped as new, as a stuck driver's output is: only the content gives it away.
    for k, (_message, envelope) in enumerate(outputs):
        assert envelope.t_meas_ns == harness.t0_ns + k * TRUTH_PERIOD_NS


def test_faults_run_on_the_scenario_clock_however_late_the_lidar_starts() -> None:
    world = faults(SensorFault(("lidars",), FaultKind.SILENCE, 1.0, 2.0))
    harness = make("lidar_h_right", world)
    # The first truth this process hears is 0.8 s into the scenario.
    silent = [k for k in range(20, 75) if not harness.step(k)]
    assert silent == list(range(25, 50))


def test_faults_of_other_sensors_leave_this_one_alone() -> None:
    world = faults(SensorFault(("lidar_h_right", "gps"), FaultKind.SILENCE, 0.0, 10.0))
    harness = make("lidar_h_left", world)
    assert all(harness.step(k) for k in range(10))


def test_output_is_determined_by_the_seed_and_the_truth_stream() -> None:
    def run(seed: int, seed_offset: int = 0) -> list[Any]:
        harness = make("lidar_h_left", seed=seed, seed_offset=seed_offset)
        return [message for k in range(5) for message, _ in harness.step(k)]

    assert run(5) == run(5)
    assert run(5) != run(6)
    assert run(5) != run(5, seed_offset=1)


def test_the_scenario_is_loaded_only_when_no_world_is_given(monkeypatch: pytest.MonkeyPatch) -> None:
    loaded: list[str] = []

    def load_scenario(path: str) -> types.SimpleNamespace:
        loaded.append(path)
        return types.SimpleNamespace(world=WORLD, seed=9)

    monkeypatch.setattr(lidar_module, "load_scenario", load_scenario)
    clock = ManualClock()
    runtime = Runtime(Bus(MemTransport(uuid.uuid4().hex), 21, Keyring.generate(), clock), clock)
    lidar = Lidar(LidarConfig(scenario="somewhere.toml"), runtime)
    lidar.on_start()
    assert loaded == ["somewhere.toml"] and lidar.world is WORLD and lidar.seed == 9
    injected = Lidar(LidarConfig(scenario="elsewhere.toml"), runtime, world=WORLD, seed=1)
    injected.on_start()
    assert loaded == ["somewhere.toml"]


@pytest.mark.parametrize(("key", "value"), [("sensor", "lidar_h_middle"), ("rate_hz", 0.0), ("rate_hz", 100.0)])
def test_bad_configuration_is_refused(key: str, value: Any) -> None:
    clock = ManualClock()
    runtime = Runtime(Bus(MemTransport(uuid.uuid4().hex), 21, Keyring.generate(), clock), clock)
    with pytest.raises(ValueError, match="lidar"):
        Lidar(LidarConfig(**{key: value}), runtime, world=WORLD).on_start()


@pytest.mark.parametrize("t_meas_ns", [0, 1, 2**32 - 1, 2**32, 1_733_280_000_123_456_789, 2**64 - 1])
def test_the_noise_generator_is_seeded_with_the_documented_entropy(t_meas_ns: int) -> None:
    lidar = make("lidar_v_left", seed=2**40 + 5, seed_offset=3).lidar
    documented = np.random.SeedSequence([2**40 + 5, 3, SOURCE_IDS["lidar_v_left"], t_meas_ns])
    expected = np.random.default_rng(documented).normal(size=8)
    np.testing.assert_array_equal(np.random.default_rng(lidar._entropy(t_meas_ns)).normal(size=8), expected)
