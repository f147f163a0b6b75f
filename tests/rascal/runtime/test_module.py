"""The module lifecycle: periodic tasks, heartbeats, inputs with max age."""

from __future__ import annotations

import itertools
import threading
import time
import uuid
from dataclasses import dataclass

import pytest

from protocol import channels
from protocol.auth import Keyring
from protocol.messages import ModuleState, ModuleStatus, ObstacleList
from protocol.transport import MemTransport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from rascal.runtime.config import setting
from rascal.runtime.module import Module, Runtime


@dataclass(frozen=True)
class CounterConfig:
    period_s: float = setting(0.05, "task period")


class Counter(Module):
    name = "counter"
    default_source_id = 40
    Config = CounterConfig

    def on_start(self) -> None:
        self.order: list[str] = []
        self.stopped = False
        self.input(channels.OBSTACLES_BEACON, 0.2)
        self.every(self.config.period_s, self.low, priority=0)
        self.every(self.config.period_s, self.high, priority=5)

    def low(self) -> None:
        self.order.append("low")

    def high(self) -> None:
        self.order.append("high")

    def on_stop(self) -> None:
        self.stopped = True


def make_runtime(hub: str, source_id: int, keyring: Keyring) -> Runtime:
    return Runtime(Bus(MemTransport(hub), source_id, keyring, MasterClock()), MasterClock())


def test_tasks_run_at_their_period_higher_priority_first() -> None:
    keyring = Keyring.generate()
    runtime = make_runtime(uuid.uuid4().hex, 40, keyring)
    module = Counter(CounterConfig(), runtime)
    runtime.run(module, duration_s=0.52)
    assert 9 <= module.order.count("high") <= 12
    assert module.order[:2] == ["high", "low"]
    assert module.stopped


def test_heartbeat_reports_state_and_stale_inputs() -> None:
    keyring = Keyring.generate()
    hub = uuid.uuid4().hex
    listener = Bus(MemTransport(hub), 41, keyring, MasterClock())
    statuses: list[ModuleStatus] = []
    listener.subscribe(channels.MODULE_STATUS, lambda msg, env: statuses.append(msg))
    runtime = make_runtime(hub, 40, keyring)
    runtime.run(Counter(CounterConfig(), runtime), duration_s=0.3)
    listener.poll()
    assert [s.module for s in statuses] == ["counter", "counter"]  # at start and on stopping
    first, last = statuses
    assert first.state == ModuleState.DEGRADED  # its input has never arrived
    assert first.stale_inputs == (channels.OBSTACLES_BEACON,)
    assert last.state == ModuleState.STOPPING
    assert first.cpu_pct == -1.0 and last.cpu_pct >= 0.0  # too soon to judge, then measured


def test_set_period_retimes_running_tasks_staggered() -> None:
    runtime = make_runtime(uuid.uuid4().hex, 41, Keyring.generate())
    calls: list[str] = []
    for k in range(3):
        runtime.add_task("watch", lambda: calls.append("w"), 0.1, offset_s=0.025 * (k + 1))
    runtime.add_task("other", lambda: calls.append("o"), 0.1)
    assert runtime.set_period("watch", 0.04, first_in_s=0.05, stagger_s=0.01) == 3
    watches = sorted(task for task in runtime._tasks if task.name == "watch")
    assert [task.period_ns for task in watches] == [40_000_000] * 3
    assert [b.due_ns - a.due_ns for a, b in itertools.pairwise(watches)] == [10_000_000] * 2
    assert next(task for task in runtime._tasks if task.name == "other").period_ns == 100_000_000
    assert runtime.set_period("missing", 1.0) == 0
    with pytest.raises(ValueError):
        runtime.set_period("watch", 0.0)


class Slow(Module):
    """A module whose handler is slower than its input arrives."""

    name = "slow"
    default_source_id = 42
    Config = CounterConfig

    def on_start(self) -> None:
        self.handled = 0
        self.bus.subscribe(channels.OBSTACLES_BEACON, self.on_beacon)

    def on_beacon(self, _msg: object, _envelope: object) -> None:
        self.handled += 1
        time.sleep(0.002)


def test_a_module_slower_than_its_input_still_runs_its_tasks_and_heartbeats() -> None:
    """1,000 messages/s into a handler that takes 2 ms: the backlog never drains, and the
    heartbeat must still go out every second (the supervisor kills a module silent for 3 s)."""
    keyring = Keyring.generate()
    hub = uuid.uuid4().hex
    listener = Bus(MemTransport(hub), 41, keyring, MasterClock())
    statuses: list[ModuleStatus] = []
    listener.subscribe(channels.MODULE_STATUS, lambda msg, env: statuses.append(msg))
    feeder = Bus(MemTransport(hub), 43, keyring, MasterClock())
    beacon = ObstacleList(0, 0, ())
    stop = threading.Event()

    def feed() -> None:
        deadline = time.monotonic() + 3.0
        while not stop.is_set() and time.monotonic() < deadline:
            for _ in range(10):
                feeder.publish(channels.OBSTACLES_BEACON, beacon)
            time.sleep(0.01)

    runtime = make_runtime(hub, 42, keyring)
    module = Slow(CounterConfig(), runtime)
    thread = threading.Thread(target=feed, daemon=True)
    thread.start()
    started = time.monotonic()
    try:
        runtime.run(module, duration_s=2.5)
    finally:
        stop.set()
        thread.join(5.0)
    elapsed_s = time.monotonic() - started
    listener.poll(0.0, 100_000)
    beats = [s for s in statuses if s.module == "slow"]
    assert elapsed_s < 3.0  # the run ended on time, too
    assert len(beats) >= 3, f"{len(beats)} heartbeats in {elapsed_s:.1f} s, {module.handled} messages handled"
