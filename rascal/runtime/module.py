"""One lifecycle for every module process (after MOOS Iterate/OnNewMail and CAMBADA's periodic
processes with period, offset and priority).

A module subclasses :class:`Module`, declares its typed ``Config`` and reacts in ``on_start``
(subscribe, declare inputs, add periodic tasks), in handlers, and in periodic tasks. The
:class:`Runtime` owns the bus, the shared clock and the loop: it waits on the bus until the next
task is due, runs due tasks by priority, measures activation jitter and overruns, answers or
asks the time service, and publishes a ModuleStatus heartbeat every second (with the CPU the
process and its children used since the last). Under systemd it
also tells the service manager it is ready and, with each heartbeat, that it is alive
(rascal/runtime/sdnotify.py).
"""

from __future__ import annotations

import heapq
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from protocol import channels
from protocol.messages import HealthEvent, ModuleState, ModuleStatus, Severity
from rascal.runtime.bus import Bus
from rascal.runtime.clock import Clock, MasterClock, SharedClock, SkewedLocal
from rascal.runtime.cpu import UNKNOWN_PCT, CpuMeter
from rascal.runtime.ports import Port
from rascal.runtime.rtdb import Latest
from rascal.runtime.sdnotify import Notifier
from rascal.runtime.timeclient import TimeClient, TimeMaster
from rascal.runtime.timesync import SyncState

HEARTBEAT_PERIOD_S = 1.0
# Datagrams handled per wait before due tasks run. A module slower than its inputs (starved of
# CPU, or planning in a handler) otherwise keeps finding more waiting and never returns to its
# tasks: the brain on a loaded host published paths for 3 s without a heartbeat and was killed.
POLL_BUDGET = 64
TIME_REQUEST_PERIOD_S = 0.1

RUN_DIR_ENV = "RASCAL_RUN_DIR"  # set by the supervisor: where a module may leave run artefacts


def run_artefact(name: str) -> Path | None:
    """``name`` in the supervisor's run directory, or None for a module started outside a run."""
    run_dir = os.environ.get(RUN_DIR_ENV)
    return Path(run_dir) / name if run_dir else None


@dataclass
class TaskTiming:
    """Inter-activation statistics of one periodic task since the last heartbeat (CAMBADA
    Tables 1-3 report the same: how far each activation strays from its period)."""

    activations: int = 0
    max_lateness_ns: int = 0
    overruns: int = 0


class _Task:
    __slots__ = ("due_ns", "fn", "name", "period_ns", "priority", "timing")

    def __init__(self, name: str, fn: Callable[[], None], period_ns: int, first_due_ns: int, priority: int) -> None:
        self.name = name
        self.fn = fn
        self.period_ns = period_ns
        self.due_ns = first_due_ns
        self.priority = priority
        self.timing = TaskTiming()

    def __lt__(self, other: _Task) -> bool:
        # Earlier deadline first; at equal deadlines the higher priority runs first.
        return (self.due_ns, -self.priority) < (other.due_ns, -other.priority)


class Module:
    """Base class of a module process. Subclasses set ``name``, ``default_source_id``, ``Config``
    and ``interface`` (what they read and write: rascal/runtime/ports.py)."""

    name: ClassVar[str] = "module"
    default_source_id: ClassVar[int] = 0
    Config: ClassVar[type] = object
    interface: ClassVar[tuple[Port, ...]] = ()
    cpu_counts_children: ClassVar[bool] = True  # the heartbeat's CPU includes child processes

    def __init__(self, config: Any, runtime: Runtime) -> None:
        self.config = config
        self.runtime = runtime
        self.bus = runtime.bus
        self.clock = runtime.clock

    def on_start(self) -> None:
        """Subscribe, declare inputs and add periodic tasks here."""

    def on_stop(self) -> None:
        """Leave outputs safe before the process exits."""

    def status_detail(self) -> str:
        """One line for the heartbeat, e.g. what the module is doing."""
        return ""

    def instance(self) -> str:
        """The name this process reports itself by; modules run several times (one process per
        lidar) make it unique."""
        return self.name

    # Conveniences for subclasses.
    def every(self, period_s: float, fn: Callable[[], None], *, offset_s: float = 0.0, priority: int = 0) -> None:
        self.runtime.add_task(fn.__name__, fn, period_s, offset_s, priority)

    def input(self, channel: str, max_age_s: float, msg_type: type | None = None) -> Latest[Any]:
        return self.runtime.add_input(channel, max_age_s, msg_type)

    def now_ns(self) -> int:
        return self.clock.now_ns()

    def report(self, severity: Severity, code: str, text: str) -> None:
        self.bus.publish(channels.HEALTH, HealthEvent(self.instance(), int(severity), code, text))


class Runtime:
    """Runs one module: bus, shared time, scheduling, heartbeat, clean shutdown."""

    def __init__(self, bus: Bus, clock: Clock, *, time_master: bool = False, restarts: int = 0) -> None:
        self.bus = bus
        self.clock = clock
        self.restarts = restarts
        self.inputs: list[Latest[Any]] = []
        self._tasks: list[_Task] = []
        self._stop = False
        self._started_ns = time.monotonic_ns()
        self.state = ModuleState.STARTING
        self.module: Module | None = None
        self.time_master = TimeMaster(bus) if time_master else None
        self.time_client = TimeClient(bus, clock) if isinstance(clock, SharedClock) else None
        self._epoch_ns: int | None = None
        self.notifier = Notifier()
        self._cpu: CpuMeter | None = None  # made when the loop starts: start-up imports are not the loop's load

    def add_task(
        self, name: str, fn: Callable[[], None], period_s: float, offset_s: float = 0.0, priority: int = 0
    ) -> None:
        if period_s <= 0:
            raise ValueError(f"task {name}: period must be positive")
        # Tasks share one time grid from the start of the run (CAMBADA: period + offset), so
        # tasks of equal period and offset fall due together and priority decides their order.
        epoch = self._epoch_ns if self._epoch_ns is not None else 0
        first = epoch + int(offset_s * 1e9)
        heapq.heappush(self._tasks, _Task(name, fn, int(period_s * 1e9), first, priority))

    def set_period(self, name: str, period_s: float, first_in_s: float | None = None, stagger_s: float = 0.0) -> int:
        """Give every running task called ``name`` a new period; the first (in due order) is next
        due ``first_in_s`` from now (default: one new period), each further one ``stagger_s`` after
        the one before. Returns how many tasks changed. For a module that retimes itself live
        (the ESVS round)."""
        if period_s <= 0 or stagger_s < 0:
            raise ValueError(f"task {name}: period must be positive and stagger not negative")
        period_ns = int(period_s * 1e9)
        first = time.monotonic_ns() + (period_ns if first_in_s is None else int(first_in_s * 1e9))
        matching = sorted((task for task in self._tasks if task.name == name), key=lambda task: task.due_ns)
        for index, task in enumerate(matching):
            task.period_ns = period_ns
            task.due_ns = first + index * int(stagger_s * 1e9)
        heapq.heapify(self._tasks)
        return len(matching)

    def add_input(self, channel: str, max_age_s: float, msg_type: type | None = None) -> Latest[Any]:
        entry = self.bus.latest(channel, int(max_age_s * 1e9), msg_type)
        self.inputs.append(entry)
        return entry

    def stale_inputs(self) -> list[str]:
        now = self.clock.now_ns()
        return [entry.channel for entry in self.inputs if entry.is_stale(now)]

    def stop(self) -> None:
        self._stop = True

    def run(self, module: Module, duration_s: float | None = None) -> None:
        """Run until :meth:`stop`, SIGINT/SIGTERM, or ``duration_s``."""
        self.module = module
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, lambda *_: self.stop())
        if self.time_client is not None:
            self.add_task("time_request", self.time_client.request, TIME_REQUEST_PERIOD_S, priority=10)
        self.add_task("heartbeat", self._heartbeat, HEARTBEAT_PERIOD_S, priority=9)
        module.on_start()
        self._epoch_ns = time.monotonic_ns()
        self._cpu = CpuMeter(children=module.cpu_counts_children)
        for task in self._tasks:
            task.due_ns += self._epoch_ns
        heapq.heapify(self._tasks)
        self.state = ModuleState.OK
        self.notifier.notify(READY="1", STATUS=f"{module.instance()} running")
        end_ns = None if duration_s is None else time.monotonic_ns() + int(duration_s * 1e9)
        try:
            while not self._stop and (end_ns is None or time.monotonic_ns() < end_ns):
                self._iterate(end_ns)
        finally:
            self.state = ModuleState.STOPPING
            self.notifier.notify(STOPPING="1")
            module.on_stop()
            self._heartbeat()
            self.bus.close()
            self.notifier.close()

    def _iterate(self, end_ns: int | None) -> None:
        now = time.monotonic_ns()
        next_due = self._tasks[0].due_ns if self._tasks else now + 100_000_000
        if end_ns is not None:
            next_due = min(next_due, end_ns)
        self.bus.poll(max(0.0, (next_due - now) / 1e9), POLL_BUDGET)
        now = time.monotonic_ns()
        while self._tasks and self._tasks[0].due_ns <= now:
            task = heapq.heappop(self._tasks)
            lateness = now - task.due_ns
            timing = task.timing
            timing.activations += 1
            timing.max_lateness_ns = max(timing.max_lateness_ns, lateness)
            task.fn()
            # Keep the grid (due += period) so jitter never accumulates into drift; skip the
            # slots an overrun swallowed and count them.
            task.due_ns += task.period_ns
            finished = time.monotonic_ns()
            if task.due_ns <= finished:
                missed = (finished - task.due_ns) // task.period_ns + 1
                timing.overruns += missed
                task.due_ns += missed * task.period_ns
            heapq.heappush(self._tasks, task)
            now = time.monotonic_ns()

    def _heartbeat(self) -> None:
        module = self.module
        assert module is not None
        jitter = max((task.timing.max_lateness_ns for task in self._tasks), default=0)
        overruns = sum(task.timing.overruns for task in self._tasks)
        stale = self.stale_inputs()
        state = self.state
        if state is ModuleState.OK and stale:
            state = ModuleState.DEGRADED
        clock_state, offset, bound = self._clock_status()
        main_period = min((t.period_ns for t in self._tasks if t.name not in ("heartbeat", "time_request")), default=0)
        status = ModuleStatus(
            module.instance(),
            int(state),
            (time.monotonic_ns() - self._started_ns) / 1e9,
            main_period,
            jitter,
            overruns,
            self.restarts,
            self.bus.rejected_total(),
            tuple(stale),
            clock_state,
            offset,
            bound,
            module.status_detail(),
            self._cpu_pct(),
        )
        self.bus.publish(channels.MODULE_STATUS, status)
        if state is not ModuleState.STOPPING:  # the watchdog hears the loop, as the supervisor does
            self.notifier.notify(WATCHDOG="1", STATUS=status.detail or ModuleState(state).name)
        for task in self._tasks:
            task.timing = TaskTiming()

    def _cpu_pct(self) -> float:
        pct = self._cpu.sample() if self._cpu is not None else UNKNOWN_PCT
        return pct if pct == UNKNOWN_PCT else round(pct, 1)

    def _clock_status(self) -> tuple[int, int, int]:
        if isinstance(self.clock, SharedClock):
            local = self.clock.local_ns()
            status = self.clock.estimator.status(local)
            return int(status.state), status.offset_ns, status.error_bound_ns
        return int(SyncState.SYNCED), 0, 0


def make_clock(time_master: bool, clock_offset_ms: float = 0.0, clock_drift_ppm: float = 0.0) -> Clock:
    """The master keeps real time from its start; everyone else synchronises to it (optionally
    through a deliberately skewed local clock, for fault tests)."""
    if time_master:
        return MasterClock()
    if clock_offset_ms or clock_drift_ppm:
        return SharedClock(local=SkewedLocal(int(clock_offset_ms * 1e6), clock_drift_ppm))
    return SharedClock()
