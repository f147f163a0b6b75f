"""The ESVS software watchdog (RASCAL's Watchdog TSK): it notices a vision worker that crashed
(its process exited) or hung (no result within ``hang_timeout`` of when one was due), kills it,
and puts another in its place, while the ESVS process itself keeps running its round and
heartbeat.

A worker past its time is not hung while it is still working (a thread running or waiting for a
CPU, state R, or held in the kernel, state D: a page fault waiting for a page, a memory lock) and
has used less than its hang timeout of CPU since the time being judged began: an overloaded
machine starves a working worker, and killing it for that only costs a frame and a cold start on
top (and a thread in D would not even die before the kernel let it go). A worker that sleeps
without a result is hung at its timeout; one that spins, once it has burnt that much CPU. A
worker found asleep is first checked for a result that arrived after the pipe was read: one that
finishes late sends it and goes back to waiting at once, and killing it then would throw the
finished result away.

Each role keeps a hot spare: a standby worker already started, attached to the frame ring and
waiting. Replacing a failed worker is one ``Activate`` message to the spare; a new spare is then
started off the critical path. Workers start from a fork server that has the vision code
imported already, so no child inherits the bus sockets and a start costs a fork, not a Python
start.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from multiprocessing.context import BaseContext
from multiprocessing.process import BaseProcess
from typing import Any, NamedTuple

from modules.esvs.worker import Activate, Hello, Inject, Process, Report, Retime, SetParams, WorkerSpec, run_worker
from protocol.messages import Severity

JOIN_TIMEOUT_S = 2.0
REAP_WAIT_S = 0.02
# A worker replaced for a hang gets twice the time next (up to MAX_BACKOFF times the hang
# timeout), and back half of it after RECOVERY_REPORTS prompt results in a row: an overloaded
# machine slows every frame, and killing slow-but-working workers only makes that worse.
MAX_BACKOFF = 8
RECOVERY_REPORTS = 20
PRELOAD = ["modules.esvs.forkserver", "modules.esvs.worker"]

EventSink = Callable[[Severity, str, str], None]


def worker_context() -> BaseContext:
    """A fork-server context whose server has the vision code loaded: safe with the bus sockets
    (the server is a fresh interpreter, not a fork of this process) and fast to fork from."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(PRELOAD + _main_module())
    return context


def _main_module() -> list[str]:
    """Every child re-runs the parent's main module (as ``__mp_main__``); preloading it in the
    server makes that cheap. ``python -m pkg`` mains (``pkg.__main__``) are never re-run."""
    main = sys.modules.get("__main__")
    name = getattr(getattr(main, "__spec__", None), "name", None)
    if not name or name == "__main__" or name.endswith(".__main__"):
        return []
    return [name]


class Threads(NamedTuple):
    """What the kernel says of a process's threads: CPU time used, and whether any is working
    (running, waiting for a CPU, or held in the kernel) rather than asleep."""

    cpu_ns: int
    working: bool


WORKING_STATES = (b"R", b"D")  # running or runnable; uninterruptible wait in the kernel


def threads_of(pid: int) -> Threads:
    """The CPU time of every thread of ``pid`` (``/proc/PID/task/TID/schedstat``) and whether
    one is working (state R or D). Nothing known (not Linux, or gone): no CPU, not working, so
    no starvation is excused."""
    cpu_ns, working = 0, False
    try:
        threads = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return Threads(0, False)
    for tid in threads:
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat", "rb") as schedstat:
                cpu_ns += int(schedstat.read().split()[0])
            with open(f"/proc/{pid}/task/{tid}/stat", "rb") as stat:
                working |= stat.read().rpartition(b")")[2].split()[0] in WORKING_STATES
        except (OSError, ValueError, IndexError):
            continue
    return Threads(cpu_ns, working)


class _Proc:
    """One worker process and its end of the pipe."""

    def __init__(self, context: BaseContext, spec: WorkerSpec, now_ns: int) -> None:
        parent, child = context.Pipe()
        self.process: BaseProcess = context.Process(
            target=run_worker, args=(spec, child), name=f"esvs-{spec.role}", daemon=True
        )
        self.process.start()
        child.close()
        self.conn: Any = parent
        self.pid = self.process.pid or 0
        self.started_ns = now_ns
        self.scheduling = ""
        self.ready = False  # said hello
        self.broken = False  # the pipe closed under us: dead or dying

    def send(self, message: object) -> bool:
        if self.broken:
            return False
        try:
            self.conn.send(message)
        except (BrokenPipeError, ConnectionResetError, OSError):
            self.broken = True
            return False
        return True

    def receive(self) -> list[object]:
        messages: list[object] = []
        if self.broken:
            return messages
        try:
            while self.conn.poll():
                messages.append(self.conn.recv())
        except (EOFError, OSError):
            self.broken = True
        return messages

    def pending(self) -> bool:
        """Something from the worker is waiting in the pipe (the next ``receive`` gets it)."""
        if self.broken:
            return False
        try:
            return bool(self.conn.poll())
        except (EOFError, OSError):
            return False

    def exit_status(self) -> str | None:
        """Why the process is gone, or None while it lives."""
        if self.broken and self.process.exitcode is None:
            self.process.join(REAP_WAIT_S)  # its pipe closed as it died: give the exit status a moment
        if self.process.exitcode is not None:
            return f"crashed (exit code {self.process.exitcode})"
        return "crashed (its pipe closed)" if self.broken else None

    def kill(self) -> None:
        if self.process.exitcode is None:
            self.process.kill()
            self.process.join(JOIN_TIMEOUT_S)
        self.conn.close()

    def stop(self) -> None:
        """Close the pipe (the worker exits on EOF), then make sure it is gone."""
        self.conn.close()
        if self.process.exitcode is None:
            self.process.join(0.5)
        if self.process.exitcode is None:
            self.process.kill()
            self.process.join(JOIN_TIMEOUT_S)


class Supervised:
    """One role's active worker, its spare, and what the watchdog knows of them."""

    def __init__(
        self,
        context: BaseContext,
        spec: WorkerSpec,
        hang_timeout_ns: int,
        startup_timeout_ns: int,
        now_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.context = context
        self.spec = spec
        self.hang_timeout_ns = hang_timeout_ns
        self.startup_timeout_ns = startup_timeout_ns
        self.now_ns = now_ns
        self.active: _Proc | None = None
        self.spare: _Proc | None = None
        self.activated = False  # the active worker has been told to work and has said hello
        self.outstanding_since_ns: int | None = None  # round-activated: a frame handed over, no report yet
        self.last_seen_ns = 0  # end of the last activation (or the start): the grid's next slot is due after it
        self.cpu_ns = 0  # the active worker's CPU time when the time being judged began
        self.restarts = 0
        self.crashes = 0
        self.hangs = 0
        self.spare_restarts = 0
        self.promoted_spare = False  # the last replacement was the spare (rather than a cold start)
        self.backoff = 1
        self.prompt_reports = 0
        self.last_scheduling = ""

    @property
    def role(self) -> str:
        return self.spec.role

    @property
    def pid(self) -> int:
        return self.active.pid if self.active is not None else 0

    @property
    def scheduling(self) -> str:
        """What the active worker runs under (the last one's, once stopped)."""
        if self.active is not None and self.active.scheduling:
            self.last_scheduling = self.active.scheduling
        return self.last_scheduling

    @property
    def ready(self) -> bool:
        return self.active is not None and self.activated and not self.active.broken

    @property
    def idle(self) -> bool:
        """Ready for the round to hand it a frame."""
        return self.ready and self.outstanding_since_ns is None

    def start(self) -> None:
        self._activate(_Proc(self.context, self.spec, self.now_ns()))
        self.spare = _Proc(self.context, self.spec, self.now_ns())

    def _activate(self, proc: _Proc) -> None:
        self.active = proc
        self.activated = proc.ready
        self.outstanding_since_ns = None
        self.last_seen_ns = self.now_ns()
        self.cpu_ns = threads_of(proc.pid).cpu_ns
        proc.send(Activate())

    def send(self, message: Process | SetParams | Retime | Inject) -> bool:
        """Hand ``message`` to the active worker; parameters and timing also go to the spare and
        into the spec, so any worker started later starts with them."""
        if isinstance(message, SetParams):
            self.spec = replace(self.spec, params=message.params)
        elif isinstance(message, Retime):
            self.spec = replace(
                self.spec, period_ns=message.period_ns, offset_ns=message.offset_ns, epoch_ns=message.epoch_ns
            )
        if isinstance(message, (SetParams, Retime)) and self.spare is not None:
            self.spare.send(message)
        if self.active is None or not self.active.send(message):
            return False
        if isinstance(message, Process):
            self.outstanding_since_ns = self.now_ns()
            self.cpu_ns = threads_of(self.active.pid).cpu_ns
        return True

    def drain(self) -> tuple[list[Report], Hello | None]:
        """Everything the workers sent since the last call; the hello, if the active worker
        became ready now."""
        reports: list[Report] = []
        hello = None
        if self.spare is not None:
            for message in self.spare.receive():
                if isinstance(message, Hello):
                    self.spare.ready, self.spare.scheduling = True, message.scheduling
        active = self.active
        if active is None:
            return reports, hello
        for message in active.receive():
            if isinstance(message, Report):
                reports.append(message)
                self.outstanding_since_ns = None
                self.last_seen_ns = message.finished_ns
                self.cpu_ns = threads_of(active.pid).cpu_ns
                self._recover(message)
            elif isinstance(message, Hello):
                active.ready, active.scheduling = True, message.scheduling
                self.activated = True
                self.last_seen_ns = self.now_ns()
                hello = message
        return reports, hello

    @property
    def timeout_ns(self) -> int:
        """The hang timeout now, after any back-off."""
        return self.hang_timeout_ns * self.backoff

    def _recover(self, report: Report) -> None:
        if self.backoff == 1:
            return
        prompt = report.finished_ns - report.activated_ns <= self.hang_timeout_ns
        self.prompt_reports = self.prompt_reports + 1 if prompt else 0
        if self.prompt_reports >= RECOVERY_REPORTS:
            self.backoff //= 2
            self.prompt_reports = 0

    def fault(self) -> str | None:
        """Why the active worker must be replaced now, or None while it is healthy."""
        active = self.active
        if active is None:
            return "was never started"
        status = active.exit_status()
        if status is not None:
            return status
        now = self.now_ns()
        if not self.activated:
            waited = now - active.started_ns
            return f"did not start within {waited / 1e9:.1f} s" if waited > self.startup_timeout_ns else None
        if self.spec.periodic:
            late, since = now - self.spec.activation_at_or_after(self.last_seen_ns), "its activation was due"
        elif self.outstanding_since_ns is not None:
            late, since = now - self.outstanding_since_ns, "it was handed a frame"
        else:
            return None
        if late <= self.timeout_ns:
            return None
        threads = threads_of(active.pid)
        used = threads.cpu_ns - self.cpu_ns
        if threads.working and used <= self.timeout_ns:
            return None  # starved or held up by the kernel, not hung
        if active.pending():
            # It answered since the drain and went back to waiting: read after its state, the pipe
            # shows any result sent before it slept. The next check collects it.
            return None
        return f"hung: no result {late / 1e6:.0f} ms after {since} ({used / 1e6:.0f} ms of CPU used)"

    def restart(self, reason: str) -> None:
        """Kill the active worker and put the spare (or, without a ready one, a new worker) in its place."""
        if reason.startswith(("hung", "did not start")):
            self.hangs += 1
            self.backoff = min(self.backoff * 2, MAX_BACKOFF)
            self.prompt_reports = 0
        else:
            self.crashes += 1
        self.restarts += 1
        if self.active is not None:
            self.active.kill()
        spare, self.spare = self.spare, None
        self.promoted_spare = spare is not None and spare.ready and spare.exit_status() is None
        if self.promoted_spare:
            assert spare is not None
            self._activate(spare)
        else:
            if spare is not None:
                spare.kill()
            self._activate(_Proc(self.context, self.spec, self.now_ns()))
        self.spare = _Proc(self.context, self.spec, self.now_ns())

    def check_spare(self) -> None:
        """A spare that died or never started is replaced quietly (it was doing nothing yet)."""
        spare = self.spare
        if spare is None:
            return
        stuck = not spare.ready and self.now_ns() - spare.started_ns > self.startup_timeout_ns
        if stuck or spare.exit_status() is not None:
            spare.kill()
            self.spare_restarts += 1
            self.spare = _Proc(self.context, self.spec, self.now_ns())

    def stop(self) -> None:
        _ = self.scheduling  # keep what it ran under for the last status
        for proc in (self.active, self.spare):
            if proc is not None:
                proc.stop()
        self.active = self.spare = None


class Watchdog:
    """All vision workers of one ESVS: started together, checked together, replaced alone."""

    def __init__(
        self,
        context: BaseContext,
        specs: list[WorkerSpec],
        hang_timeout_s: float,
        startup_timeout_s: float,
        on_event: EventSink,
        now_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if hang_timeout_s <= 0 or startup_timeout_s <= 0:
            raise ValueError("hang and startup timeouts must be positive")
        self.on_event = on_event
        self.workers = {
            spec.role: Supervised(context, spec, int(hang_timeout_s * 1e9), int(startup_timeout_s * 1e9), now_ns)
            for spec in specs
        }

    @property
    def restarts(self) -> int:
        return sum(worker.restarts for worker in self.workers.values())

    def set_hang_timeout(self, hang_timeout_s: float) -> None:
        for worker in self.workers.values():
            worker.hang_timeout_ns = int(hang_timeout_s * 1e9)

    def start(self) -> None:
        for worker in self.workers.values():
            worker.start()

    def check(self) -> list[Report]:
        """Collect results, then replace any worker that crashed or hung."""
        reports: list[Report] = []
        for worker in self.workers.values():
            got, hello = worker.drain()
            reports += got
            if hello is not None:
                self._started(worker, "")
            reason = worker.fault()
            if reason is not None:
                old_pid = worker.pid
                worker.restart(reason)
                self.on_event(
                    Severity.WARNING,
                    "worker_restart",
                    f"{worker.role} worker pid={old_pid} {reason}; killed and replaced (restart {worker.restarts})",
                )
                if worker.ready:
                    self._started(worker, " (the spare)")
            worker.check_spare()
        return reports

    def broadcast(self, message: SetParams | Retime | Inject, roles: tuple[str, ...] | None = None) -> None:
        for worker in self.workers.values():
            if roles is None or worker.role in roles:
                worker.send(message)

    def stop(self) -> None:
        for worker in self.workers.values():
            worker.stop()

    def _started(self, worker: Supervised, how: str) -> None:
        self.on_event(Severity.INFO, "worker_started", f"{worker.role} pid={worker.pid} sched={worker.scheduling}{how}")
