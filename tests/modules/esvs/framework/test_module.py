"""The ESVS module in-process on a private loopback bus, fed by a frame ring the test writes: the round's
reports, ModuleStatus, ConfigUpdate handling, vehicle state, and a worker killed mid-run."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

from modules.esvs.frames import RingWriter
from modules.esvs.module import Esvs
from modules.esvs.settings import EsvsConfig
from modules.esvs.worker import Report
from protocol import channels
from protocol.auth import Keyring
from protocol.messages import (
    ConfigUpdate,
    ModuleState,
    ModuleStatus,
    NavQuality,
    ObstacleList,
    Severity,
    VehicleState,
)
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from rascal.runtime.module import Runtime
from tests.modules.esvs.framework.rings import HEIGHT, WIDTH, ring_name_fixture
from tests.modules.esvs.framework.workers import SCENE, scene_pair

STATE = VehicleState(1.0, 2.0, 0.0, 0.1, 3.0, 3.0, 0.3, 0.0, tuple([0.0] * 25), int(NavQuality.DGPS))


@pytest.fixture
def ring_name() -> Iterator[str]:
    yield from ring_name_fixture()


@dataclass
class Run:
    """What the test's own bus heard during one ESVS run."""

    module: Esvs
    heard: dict[str, list[tuple[Any, Any]]] = field(default_factory=lambda: defaultdict(list))
    exposures: list[int] = field(default_factory=list)

    def messages(self, channel: str) -> list[Any]:
        return [message for message, _envelope in self.heard[channel]]

    def events(self, code: str) -> list[str]:
        return [event.text for event in self.messages(channels.HEALTH) if event.code == code]

    def statuses(self) -> list[ModuleStatus]:
        return [status for status in self.messages(channels.MODULE_STATUS) if status.module == "esvs"]


def run_esvs(
    bus_url: str,
    ring_name: str,
    config: EsvsConfig,
    duration_s: float,
    script: list[tuple[float, Callable[[Run, Bus], None]]],
    shape: tuple[int, int] = (HEIGHT, WIDTH),
) -> Run:
    """Run the ESVS for ``duration_s`` while a thread writes scene frames at 20 Hz; each script
    step runs once, in the ESVS's own loop, ``at`` seconds after the start. The bus is a private
    loopback one (a mem:// bus never blocks in poll, so the round's loop would spin)."""
    keyring = Keyring.generate()
    runtime = Runtime(Bus.open(bus_url, source_id=20, clock=MasterClock(), keyring=keyring), MasterClock())
    run = Run(Esvs(config, runtime))
    listener = Bus.open(bus_url, source_id=99, clock=MasterClock(), keyring=keyring)
    for channel in (channels.OBSTACLES_ESVS, channels.LANE_BORDERS, channels.MODULE_STATUS, channels.HEALTH):
        listener.subscribe(channel, lambda message, envelope, c=channel: run.heard[c].append((message, envelope)))
    writer = RingWriter(ring_name, *shape)
    stop = threading.Event()
    left, right = (image[: shape[0], : shape[1]].copy() for image in scene_pair())

    def camera() -> None:
        while not stop.wait(0.05):
            run.exposures.append(time.time_ns())
            writer.write(left, right, run.exposures[-1])

    pending = sorted(script, key=lambda step: step[0])
    started: list[float] = []  # the script's clock starts with the ESVS's first round

    def play() -> None:
        started[:] = started or [time.monotonic()]
        while pending and time.monotonic() - started[0] >= pending[0][0]:
            pending.pop(0)[1](run, listener)
        listener.poll()

    runtime.add_task("script", play, 0.1)  # not below the round: ModuleStatus reports the shortest period
    thread = threading.Thread(target=camera, daemon=True)
    thread.start()
    try:
        runtime.run(run.module, duration_s)
    finally:
        stop.set()
        thread.join()
        writer.close()
    listener.poll(0.2)
    listener.close()
    return run


def config_update(key: str, value: str, module: str = "esvs") -> Callable[[Run, Bus], None]:
    return lambda _run, bus: bus.publish(channels.CONFIG, ConfigUpdate(module, key, value)) and None


def kill_worker(run: Run, _bus: Bus) -> None:
    assert run.module.watchdog is not None
    os.kill(run.module.watchdog.workers["vision"].pid, signal.SIGKILL)


@pytest.mark.slow
def test_monolithic_round_reports_obeys_config_and_survives_a_killed_worker(bus_url: str, ring_name: str) -> None:
    config = EsvsConfig(ring_name=ring_name, sched="none", vehicle_state_max_age_s=2.0)
    script = [
        (0.75, lambda _run, bus: bus.publish(channels.VEHICLE_STATE, STATE) and None),
        (1.0, config_update("round_period_s", "0.05")),
        (1.1, config_update("mode", "cambada")),
        (1.2, config_update("round_period_s", "0.01")),
        (1.3, config_update("inject_fault", "hang")),
        (1.4, config_update("round_period_s", "0.2", module="lidar")),
        (1.5, kill_worker),
    ]
    run = run_esvs(bus_url, ring_name, config, 3.2, script)

    obstacles = run.heard[channels.OBSTACLES_ESVS]
    assert obstacles, run.statuses()
    assert all(len(message.obstacles) == len(SCENE.boxes) for message, _envelope in obstacles)
    stamps = [envelope.t_meas_ns for _message, envelope in obstacles]
    assert set(stamps) <= set(run.exposures), "reports are stamped with their frame's exposure time"
    assert len(set(stamps)) == len(stamps), "each completed report is sent once"
    lanes = run.messages(channels.LANE_BORDERS)
    assert lanes and all(len(message.borders) == len(SCENE.stripes) for message in lanes)

    assert run.events("config") == ["round_period_s changed from 0.1 to 0.05"]
    rejected = run.events("config_rejected")
    assert len(rejected) == 3
    assert "restart" in rejected[0] and "round_period_s" in rejected[1] and "disabled" in rejected[2]

    restarts = run.events("worker_restart")
    assert len(restarts) == 1, restarts
    restart = restarts[0]
    assert "vision worker" in restart and "crashed" in restart
    kill_time = run.module.activations["vision"]
    assert any(report.seq for report in kill_time), "the vision worker reported"
    statuses = run.statuses()
    assert statuses[0].loop_period_ns == 100_000_000
    assert statuses[-1].loop_period_ns == 50_000_000
    assert statuses[-1].restarts == 1
    assert "no vehicle state" in statuses[0].detail
    assert "vehicle state age" in statuses[1].detail, "the heartbeat at 1 s reports the state sent at 0.8 s"
    assert "frames grabbed" in statuses[-1].detail
    # Reports resumed after the restart: the last one is newer than any before the restart event.
    restart_envelope = next(env for event, env in run.heard[channels.HEALTH] if event.code == "worker_restart")
    assert max(stamps) > restart_envelope.t_pub_ns
    severities = {event.code: event.severity for event in run.messages(channels.HEALTH)}
    assert severities["worker_restart"] == Severity.WARNING and severities["config"] == Severity.INFO


@pytest.mark.slow
def test_cambada_mode_runs_obstacles_every_round_and_lanes_every_second(bus_url: str, ring_name: str) -> None:
    config = EsvsConfig(ring_name=ring_name, sched="none", mode="cambada")
    run = run_esvs(bus_url, ring_name, config, 2.5, [(1.0, config_update("min_obstacle_points", "100000"))])
    obstacles = run.messages(channels.OBSTACLES_ESVS)
    lanes = run.messages(channels.LANE_BORDERS)
    assert obstacles and lanes
    assert len(lanes) < len(obstacles)
    assert len(obstacles[0].obstacles) == len(SCENE.boxes)
    assert obstacles[-1].obstacles == (), "the new parameter reached the obstacle worker"
    assert all(len(message.borders) == len(SCENE.stripes) for message in lanes)
    detail = run.statuses()[-1].detail
    assert detail.startswith("cambada") and "obstacles pid" in detail and "lanes pid" in detail
    activations = run.module.activations
    assert {report.role for report in activations["obstacles"]} == {"obstacles"}
    assert run.module.watchdog is not None and run.module.watchdog.restarts == 0, run.messages(channels.HEALTH)


@pytest.mark.slow
def test_frames_of_another_size_are_reported_not_processed(bus_url: str, ring_name: str) -> None:
    config = EsvsConfig(ring_name=ring_name, sched="none")
    run = run_esvs(bus_url, ring_name, config, 1.5, [], shape=(480, 640))
    assert run.events("frame_size") == [f"frame ring {ring_name!r} holds 640x480 frames; the rig is 656x490"]
    assert run.heard[channels.OBSTACLES_ESVS] == []
    assert run.module.watchdog is not None and run.module.watchdog.restarts == 0
    assert run.statuses()[-2].state == ModuleState.DEGRADED


def test_a_frame_reported_twice_is_sent_once(bus_url: str, ring_name: str) -> None:
    # A worker killed as its report comes in: the report is collected, and its replacement is
    # handed the same frame and reports it again. Seen in CI as 49 distinct stamps in 50 messages.
    writer = RingWriter(ring_name, HEIGHT, WIDTH)
    keyring = Keyring.generate()
    runtime = Runtime(Bus.open(bus_url, source_id=20, clock=MasterClock(), keyring=keyring), MasterClock())
    esvs = Esvs(EsvsConfig(ring_name=ring_name, sched="none"), runtime)
    listener = Bus.open(bus_url, source_id=99, clock=MasterClock(), keyring=keyring)
    stamps: list[int] = []
    listener.subscribe(channels.OBSTACLES_ESVS, lambda _message, envelope: stamps.append(envelope.t_meas_ns))
    esvs.on_start()
    try:
        exposed = time.time_ns()
        for seq, t_exposure_ns in ((1, exposed), (1, exposed), (2, exposed + 50_000_000)):
            esvs._collect(Report("vision", 0, 1, 1, seq, t_exposure_ns, 0, ObstacleList(seq, 0, ()), None, 0.01))
            esvs._send()
        listener.poll(0.2)
    finally:
        esvs.on_stop()
        runtime.bus.close()
        listener.close()
        writer.close()
    assert stamps == [exposed, exposed + 50_000_000]
