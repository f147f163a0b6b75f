"""The simulated stereo camera: one rendered pair per new true pose into the frame ring, stamped
with the pose's measurement time, with the scenario's camera faults applied; one frame per grab,
just before it, while the ESVS triggers it, and its own frame rate while nothing does."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest

from modules.esvs.frames import Frame, RingReader, _attach
from modules.sim.camera.process import FIRST_RENDER_S, MARGIN_S, StereoCamera, StereoCameraConfig
from modules.sim.world import FaultKind, SensorFault, Shape, World, WorldObstacle
from protocol import channels
from protocol.auth import Keyring
from protocol.messages import SimTruth
from protocol.transport import MemTransport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import ManualClock, MasterClock
from rascal.runtime.module import Runtime
from tests.modules.esvs.framework.rings import ring_name_fixture

ROCK = WorldObstacle("rock", Shape.CYLINDER, 20.0, 0.5, 1.2, radius_m=0.6)
WORLD = World(
    obstacles=(ROCK,),
    faults=(
        SensorFault(("esvs",), FaultKind.SILENCE, 10.0, 11.0),
        SensorFault(("esvs",), FaultKind.STUCK, 20.0, 21.0),
        SensorFault(("esvs",), FaultKind.NOISE, 30.0, 31.0, magnitude=10.0),
        SensorFault(("lidars",), FaultKind.SILENCE, 0.0, 100.0),  # another sensor's fault
    ),
)


@pytest.fixture
def ring_name() -> Iterator[str]:
    yield from ring_name_fixture()


@dataclass
class Bench:
    camera: StereoCamera
    sim: Bus
    clock: ManualClock
    reader: RingReader

    def truth(self, scenario_time_s: float, east_m: float = 0.0) -> int:
        """Publish a true pose measured now, let the camera hear it and expose; returns its time."""
        self.clock.advance(10_000_000)
        truth = SimTruth(east_m, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, scenario_time_s=scenario_time_s)
        self.sim.publish(channels.SIM_TRUTH, truth, t_meas_ns=self.clock.t_ns)
        self.camera.bus.poll()
        self.camera.expose()
        return self.clock.t_ns

    def newest(self) -> Frame | None:
        return self.reader.latest()


@pytest.fixture
def bench(ring_name: str) -> Iterator[Bench]:
    hub, keyring, clock = uuid.uuid4().hex, Keyring.generate(), ManualClock()
    runtime = Runtime(Bus(MemTransport(hub), 19, keyring, clock), clock)
    camera = StereoCamera(StereoCameraConfig(ring_name=ring_name), runtime, world=WORLD, seed=3)
    camera.on_start()
    sim = Bus(MemTransport(hub), 5, keyring, clock)
    reader = RingReader(ring_name)
    yield Bench(camera, sim, clock, reader)
    reader.close()
    camera.on_stop()
    sim.close()


def test_each_new_pose_gives_one_frame_stamped_with_its_time(bench: Bench) -> None:
    assert bench.newest() is None  # nothing before the first pose
    t1 = bench.truth(1.0)
    first = bench.newest()
    assert first is not None and (first.seq, first.t_exposure_ns) == (1, t1)
    bench.camera.expose()  # no new pose: no new measurement
    assert bench.newest().seq == 1  # type: ignore[union-attr]
    t2 = bench.truth(1.1, east_m=2.0)
    second = bench.newest()
    assert second is not None and (second.seq, second.t_exposure_ns) == (2, t2)
    assert not np.array_equal(first.left, second.left), "the vehicle moved 2 m towards the rock"
    assert "frames 2" in bench.camera.status_detail()


def test_the_frame_is_the_scene_seen_from_the_pose(bench: Bench) -> None:
    bench.truth(1.0)
    frame = bench.newest()
    assert frame is not None
    rendered = bench.camera.renderer.render((0.0, 0.0, 0.0))  # noiseless, for the scene itself
    assert np.abs(frame.left.astype(int) - rendered.left.astype(int)).mean() < 3.0  # sensor noise only
    assert rendered.visible_obstacles().get("rock", 0) > 100


def test_a_stale_pose_gives_no_frame(bench: Bench) -> None:
    bench.sim.publish(
        channels.SIM_TRUTH, SimTruth(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0), t_meas_ns=bench.clock.t_ns - 600_000_000
    )
    bench.camera.bus.poll()
    bench.camera.expose()
    assert bench.newest() is None


def test_camera_faults_silence_repeat_and_add_noise(bench: Bench) -> None:
    bench.truth(5.0)
    clean = bench.newest()
    assert clean is not None
    bench.truth(10.5)  # silence
    assert bench.newest().seq == 1  # type: ignore[union-attr]
    t_stuck = bench.truth(20.5, east_m=3.0)  # stuck: the last pair again, newly stamped
    stuck = bench.newest()
    assert stuck is not None and stuck.t_exposure_ns == t_stuck and stuck.seq == 2
    assert np.array_equal(stuck.left, clean.left)
    bench.truth(30.5)  # ten times the noise
    noisy = bench.newest()
    assert noisy is not None
    assert np.abs(noisy.left.astype(int) - clean.left.astype(int)).std() > 5.0
    assert "fault noise" in bench.camera.status_detail()


def test_stopping_unlinks_the_ring(ring_name: str) -> None:
    clock = ManualClock()
    runtime = Runtime(Bus(MemTransport(uuid.uuid4().hex), 19, Keyring.generate(), clock), clock)
    camera = StereoCamera(StereoCameraConfig(ring_name=ring_name), runtime, world=WORLD)
    camera.on_start()
    _attach(ring_name).close()
    camera.on_stop()
    with pytest.raises(FileNotFoundError):
        _attach(ring_name)


def test_a_bad_frame_rate_is_refused(ring_name: str) -> None:
    clock = ManualClock()
    runtime = Runtime(Bus(MemTransport(uuid.uuid4().hex), 19, Keyring.generate(), clock), clock)
    with pytest.raises(ValueError, match="fps"):
        StereoCamera(StereoCameraConfig(ring_name=ring_name, fps=0.0), runtime, world=WORLD).on_start()


class FakeMonotonic:
    def __init__(self) -> None:
        self.t_ns = 5_000_000_000

    def __call__(self) -> int:
        return self.t_ns


def test_the_exposures_follow_the_trigger_a_render_ahead_of_each_grab(
    ring_name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    clock, monotonic = ManualClock(), FakeMonotonic()
    runtime = Runtime(Bus(MemTransport(uuid.uuid4().hex), 19, Keyring.generate(), clock), clock)
    camera = StereoCamera(StereoCameraConfig(ring_name=ring_name), runtime, world=WORLD, monotonic_ns=monotonic)
    camera.on_start()
    retimed: list[tuple[str, float, float | None]] = []
    monkeypatch.setattr(
        runtime, "set_period", lambda name, period_s, first_in_s=None: retimed.append((name, period_s, first_in_s))
    )
    reader = RingReader(ring_name, now_ns=monotonic)
    try:
        camera.phase()
        assert not retimed and "free-running 15 fps" in camera.status_detail()
        reader.newest()
        reader.trigger(100_000_000)  # a grab now, one every 100 ms
        monotonic.t_ns += 10_000_000
        camera.phase()
        # The next grab is in 90 ms; no frame made yet, so a render is taken to last FIRST_RENDER_S.
        lead_s = FIRST_RENDER_S + MARGIN_S
        assert retimed == [("tick", 0.1, pytest.approx(0.09 - lead_s))]
        assert "triggered every 100 ms" in camera.status_detail()
        camera.phase()
        assert len(retimed) == 1  # on its grid: left alone
        monotonic.t_ns += 40_000_000
        reader.trigger(100_000_000)  # the round was moved 50 ms later
        camera.phase()
        assert retimed[-1] == ("tick", 0.1, pytest.approx(0.1 - lead_s))
        monotonic.t_ns += 310_000_000  # three periods without a grab: the trigger is gone
        camera.phase()
        assert retimed[-1] == ("tick", 1 / 15, None) and "free-running" in camera.status_detail()
    finally:
        reader.close()
        camera.on_stop()


def test_triggered_the_camera_renders_one_fresh_frame_per_grab(bus_url: str, ring_name: str) -> None:
    keyring, clock = Keyring.generate(), MasterClock()
    runtime = Runtime(Bus.open(bus_url, source_id=19, clock=clock, keyring=keyring), clock)
    camera = StereoCamera(StereoCameraConfig(ring_name=ring_name), runtime, world=WORLD, seed=3)
    sim = Bus.open(bus_url, source_id=5, clock=clock, keyring=keyring)
    reader = RingReader(ring_name)
    grabs: list[tuple[int, int, int]] = []  # (sequence, exposure age ns, frames written by then)

    def truth() -> None:
        sim.publish(channels.SIM_TRUTH, SimTruth(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0), t_meas_ns=clock.now_ns())

    def grab() -> None:
        info = reader.newest()
        reader.trigger(100_000_000)
        if info is not None:
            grabs.append((info.seq, clock.now_ns() - info.t_exposure_ns, camera.written))

    runtime.add_task("truth", truth, 0.01)
    runtime.add_task("grab", grab, 0.1, offset_s=0.035, priority=5)
    try:
        runtime.run(camera, 3.0)
    finally:
        reader.close()
        sim.close()
    steady = grabs[10:]  # a second to phase the exposures to the grabs
    fresh = [age for (seq, age, _n), (before, _a, _m) in zip(steady[1:], steady, strict=False) if seq == before + 1]
    assert len(fresh) >= 0.8 * (len(steady) - 1), grabs  # a new frame at (nearly) every grab ...
    assert steady[-1][2] - steady[0][2] <= len(steady) + 1, grabs  # ... and hardly one more
    # Made a render and a margin before the grab, from a pose at most a truth period older: far
    # fresher than a free-running 15 fps camera's (which can be a whole frame older again).
    assert sorted(fresh)[len(fresh) // 2] < 50_000_000, grabs
