"""Vision workers under the watchdog: results for the frame handed over, and a crashed (SIGKILL,
injected exit) or hung (injected sleep) worker replaced by a new process that works again; a
worker starved of CPU (runnable, not run) is left to finish, and one that finished late is not
killed for being found asleep with its result still in the pipe."""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
from collections.abc import Iterator

import pytest

from modules.esvs.frames import RingWriter
from modules.esvs.settings import EsvsConfig, vision_params
from modules.esvs.watchdog import RECOVERY_REPORTS, Watchdog, threads_of, worker_context
from modules.esvs.worker import CRASH_EXIT_CODE, Inject, Process, SetParams, WorkerSpec
from tests.modules.esvs.framework.rings import HEIGHT, WIDTH, ring_name_fixture
from tests.modules.esvs.framework.workers import SCENE, Events, pump, write_frames

HANG_TIMEOUT_S = 0.3


@pytest.fixture
def ring_name() -> Iterator[str]:
    yield from ring_name_fixture()


@pytest.fixture
def writer(ring_name: str) -> Iterator[RingWriter]:
    ring = RingWriter(ring_name, HEIGHT, WIDTH)
    yield ring
    ring.close()


def watchdog_for(specs: list[WorkerSpec], events: Events) -> Watchdog:
    return Watchdog(worker_context(), specs, HANG_TIMEOUT_S, 30.0, events)


@pytest.fixture
def vision(writer: RingWriter) -> Iterator[tuple[Watchdog, Events]]:
    events = Events()
    watchdog = watchdog_for([WorkerSpec("vision", writer.name)], events)
    watchdog.start()
    try:
        yield watchdog, events
    finally:
        watchdog.stop()


def ready(watchdog: Watchdog) -> None:
    pump(watchdog, lambda _reports: all(w.ready for w in watchdog.workers.values()))


def process_one(watchdog: Watchdog, writer: RingWriter) -> list:
    (seq,) = write_frames(writer)
    worker = watchdog.workers["vision"]
    assert worker.send(Process(writer.generation, seq))
    return [r for r in pump(watchdog, lambda reports: any(r.seq == seq for r in reports)) if r.seq == seq]


def test_a_worker_reports_what_it_saw_in_the_frame_it_was_handed(
    vision: tuple[Watchdog, Events], writer: RingWriter
) -> None:
    watchdog, events = vision
    ready(watchdog)
    (report,) = process_one(watchdog, writer)
    assert report.generation == writer.generation
    assert report.t_exposure_ns == 1_000_000_000 + (report.seq - 1) * 1_000_000
    assert report.obstacles is not None and len(report.obstacles.obstacles) == len(SCENE.boxes)
    assert report.lanes is not None and len(report.lanes.borders) == len(SCENE.stripes)
    assert report.activated_ns <= report.finished_ns
    assert events.codes() == ["worker_started"]
    assert watchdog.workers["vision"].idle


def test_a_killed_worker_is_replaced_and_the_new_one_works(vision: tuple[Watchdog, Events], writer: RingWriter) -> None:
    watchdog, events = vision
    worker = watchdog.workers["vision"]
    for restart in (1, 2):
        ready(watchdog)
        old_pid = worker.pid
        os.kill(old_pid, signal.SIGKILL)
        pump(watchdog, lambda _reports, n=restart: worker.restarts == n)
        assert worker.crashes == restart and worker.pid != old_pid
        ready(watchdog)
        assert process_one(watchdog, writer)
    restarts = [text for _severity, code, text in events.items if code == "worker_restart"]
    assert len(restarts) == 2 and all("crashed" in text for text in restarts)


def test_an_injected_hang_is_noticed_and_the_worker_replaced(
    vision: tuple[Watchdog, Events], writer: RingWriter
) -> None:
    watchdog, events = vision
    worker = watchdog.workers["vision"]
    ready(watchdog)
    hung_pid = worker.pid
    assert worker.send(Inject("hang", 30.0))
    (seq,) = write_frames(writer)
    assert worker.send(Process(writer.generation, seq))
    pump(watchdog, lambda _reports: worker.restarts == 1)
    assert worker.hangs == 1 and worker.crashes == 0
    assert any(code == "worker_restart" and "hung" in text for _s, code, text in events.items)
    with pytest.raises(ProcessLookupError):
        os.kill(hung_pid, 0)  # killed and reaped
    # The next worker gets twice the time, until it has been prompt for a while.
    assert worker.timeout_ns == 2 * worker.hang_timeout_ns
    ready(watchdog)
    for _ in range(RECOVERY_REPORTS):
        assert process_one(watchdog, writer)
    assert worker.timeout_ns == worker.hang_timeout_ns


STARVE_S = 1.5  # five hang timeouts


def _spin(seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pass


def _schedule(pid: int, cpus: set[int], policy: int) -> None:
    """Every thread of ``pid`` onto ``cpus`` under ``policy``."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        os.sched_setaffinity(int(tid), cpus)
        os.sched_setscheduler(int(tid), policy, os.sched_param(0))


def test_a_worker_starved_of_cpu_is_not_taken_for_hung(vision: tuple[Watchdog, Events], writer: RingWriter) -> None:
    watchdog, events = vision
    worker = watchdog.workers["vision"]
    ready(watchdog)
    if not hasattr(os, "SCHED_IDLE") or not threads_of(worker.pid).cpu_ns:
        pytest.skip("needs Linux's SCHED_IDLE and per-thread schedstat")
    cpus = os.sched_getaffinity(0)
    cpu = min(cpus)
    # SCHED_IDLE beside a busy process on its one CPU: runnable, and run only when nothing else wants it.
    try:
        _schedule(worker.pid, {cpu}, os.SCHED_IDLE)
    except PermissionError as exc:
        pytest.skip(f"this machine refuses SCHED_IDLE: {exc}")
    hog = multiprocessing.get_context("fork").Process(target=_spin, args=(STARVE_S,), daemon=True)
    hog.start()
    try:
        assert hog.pid is not None
        os.sched_setaffinity(hog.pid, {cpu})
        (seq,) = write_frames(writer)
        assert worker.send(Process(writer.generation, seq))
        starved = pump(watchdog, lambda _got: not hog.is_alive(), timeout_s=STARVE_S + 5.0)
    finally:
        hog.join(STARVE_S + 5.0)
    assert not starved, "the frame was done while the hog ran: the worker was not starved, the test proves nothing"
    assert worker.restarts == 0, events.items
    _schedule(worker.pid, cpus, os.SCHED_OTHER)
    # Stop at a restart too: the replacement never gets this frame, and the events say why.
    reports = pump(watchdog, lambda got: any(r.seq == seq for r in got) or worker.restarts > 0)
    assert worker.restarts == 0, events.items
    assert [r.seq for r in reports] == [seq]


def test_a_late_result_sent_after_the_pipe_was_read_is_not_taken_for_a_hang(writer: RingWriter) -> None:
    """A late worker that sends its result and goes back to waiting between the watchdog's read
    of the pipe and its look at the worker's threads is found asleep past its time: the result
    waiting in the pipe says it is not hung."""
    clock = [time.monotonic_ns()]
    events = Events()
    watchdog = Watchdog(
        worker_context(), [WorkerSpec("vision", writer.name)], HANG_TIMEOUT_S, 30.0, events, lambda: clock[0]
    )
    watchdog.start()
    try:
        worker = watchdog.workers["vision"]
        ready(watchdog)
        (seq,) = write_frames(writer)
        assert worker.send(Process(writer.generation, seq))
        assert worker.active is not None and worker.active.conn.poll(20.0)  # the result waits, unread
        deadline = time.monotonic() + 5.0
        while threads_of(worker.pid).working:  # it sent the result; now it waits for the next frame
            assert time.monotonic() < deadline, "the worker never went back to waiting"
            time.sleep(0.001)
        clock[0] += 2 * worker.timeout_ns  # by the watchdog's clock the result is late
        assert worker.fault() is None
        reports = pump(watchdog, lambda got: any(r.seq == seq for r in got) or worker.restarts > 0)
        assert worker.restarts == 0, events.items
        assert [r.seq for r in reports] == [seq]
    finally:
        watchdog.stop()


def test_a_process_is_seen_running_and_using_cpu() -> None:
    me = threads_of(os.getpid())
    assert me.working and me.cpu_ns > 0  # this thread is running as it reads
    assert threads_of(2**22 + 1) == (0, False)  # beyond pid_max: nothing known, nothing excused


def test_an_injected_crash_reports_its_exit_code(vision: tuple[Watchdog, Events], writer: RingWriter) -> None:
    watchdog, events = vision
    worker = watchdog.workers["vision"]
    ready(watchdog)
    assert worker.send(Inject("crash"))
    (seq,) = write_frames(writer)
    worker.send(Process(writer.generation, seq))
    pump(watchdog, lambda _reports: worker.restarts == 1)
    assert any(f"exit code {CRASH_EXIT_CODE}" in text for _s, code, text in events.items if code == "worker_restart")


def test_new_parameters_reach_the_worker_and_survive_its_restart(
    vision: tuple[Watchdog, Events], writer: RingWriter
) -> None:
    watchdog, _events = vision
    worker = watchdog.workers["vision"]
    ready(watchdog)
    strict = vision_params(EsvsConfig(min_obstacle_points=100_000))
    watchdog.broadcast(SetParams(strict))
    (report,) = process_one(watchdog, writer)
    assert report.obstacles is not None and report.obstacles.obstacles == ()
    os.kill(worker.pid, signal.SIGKILL)
    pump(watchdog, lambda _reports: worker.restarts == 1)
    ready(watchdog)
    (report,) = process_one(watchdog, writer)
    assert report.obstacles is not None and report.obstacles.obstacles == ()


def test_cambada_workers_run_on_their_own_timers_and_report_idle_without_a_new_frame(writer: RingWriter) -> None:
    events = Events()
    period_ns = 40_000_000
    specs = [
        WorkerSpec("obstacles", writer.name, period_ns=period_ns, epoch_ns=0),
        WorkerSpec("lanes", writer.name, period_ns=2 * period_ns, offset_ns=period_ns // 2, epoch_ns=0),
    ]
    watchdog = watchdog_for(specs, events)
    watchdog.start()
    try:
        ready(watchdog)
        (seq,) = write_frames(writer)

        def saw_it_then_idled(reports: list) -> bool:
            for role in ("obstacles", "lanes"):
                seqs = [r.seq for r in reports if r.role == role]
                if seq not in seqs or 0 not in seqs[seqs.index(seq) :]:
                    return False
            return True

        reports = pump(watchdog, saw_it_then_idled)
    finally:
        watchdog.stop()
    with_frame = {r.role: r for r in reports if r.seq == seq}
    assert with_frame["obstacles"].obstacles is not None and with_frame["obstacles"].lanes is None
    assert len(with_frame["obstacles"].obstacles.obstacles) == len(SCENE.boxes)
    assert with_frame["lanes"].lanes is not None and with_frame["lanes"].obstacles is None
    assert len(with_frame["lanes"].lanes.borders) == len(SCENE.stripes)
    for role, spec in zip(("obstacles", "lanes"), specs, strict=True):
        activations = [r.activated_ns for r in reports if r.role == role]
        slots = [(t - spec.epoch_ns - spec.offset_ns) // spec.period_ns for t in activations]
        assert slots == sorted(set(slots)), f"{role}: two activations in one slot of its grid"
    assert watchdog.restarts == 0


def test_a_silent_periodic_worker_counts_as_hung(writer: RingWriter) -> None:
    events = Events()
    watchdog = watchdog_for([WorkerSpec("obstacles", writer.name, period_ns=50_000_000)], events)
    watchdog.start()
    try:
        ready(watchdog)
        worker = watchdog.workers["obstacles"]
        worker.send(Inject("hang", 30.0))
        pump(watchdog, lambda _reports: worker.restarts == 1)
        assert worker.hangs == 1
        ready(watchdog)
    finally:
        watchdog.stop()


def test_a_stopped_worker_exits(vision: tuple[Watchdog, Events]) -> None:
    watchdog, _events = vision
    ready(watchdog)
    worker = watchdog.workers["vision"]
    assert worker.active is not None and worker.spare is not None
    processes = [worker.active.process, worker.spare.process]
    watchdog.stop()
    assert [process.exitcode for process in processes] == [0, 0]  # both left on their own when the pipe closed


def test_worker_specs_are_checked() -> None:
    with pytest.raises(ValueError, match="role"):
        WorkerSpec("ball", "ring")
    with pytest.raises(ValueError, match="policy"):
        WorkerSpec("vision", "ring", policy="rr")
    with pytest.raises(ValueError, match="negative"):
        WorkerSpec("lanes", "ring", period_ns=-1)
    spec = WorkerSpec("lanes", "ring", period_ns=100, offset_ns=30, epoch_ns=1000)
    assert [spec.activation_at_or_after(t) for t in (0, 1030, 1031, 1130, 1131)] == [1030, 1030, 1130, 1130, 1230]


def spare_ready(watchdog: Watchdog) -> None:
    pump(watchdog, lambda _reports: all(w.spare is not None and w.spare.ready for w in watchdog.workers.values()))


def test_the_spare_takes_over_at_once_and_a_new_spare_is_started(
    vision: tuple[Watchdog, Events], writer: RingWriter
) -> None:
    watchdog, events = vision
    worker = watchdog.workers["vision"]
    ready(watchdog)
    spare_ready(watchdog)
    assert worker.spare is not None
    active_pid, spare_pid = worker.pid, worker.spare.pid
    os.kill(active_pid, signal.SIGKILL)
    pump(watchdog, lambda _reports: worker.restarts == 1)
    assert worker.promoted_spare and worker.pid == spare_pid and worker.ready
    assert worker.spare is not None and worker.spare.pid not in (active_pid, spare_pid)
    assert events.items[-1][1:] == ("worker_started", f"vision pid={spare_pid} sched=default scheduling (the spare)")
    assert process_one(watchdog, writer)


def test_a_worker_lost_with_its_spare_is_replaced(vision: tuple[Watchdog, Events], writer: RingWriter) -> None:
    """Both processes killed: the role comes back, cold, or through a spare the watchdog started
    in the meantime (under load it can be ready before the active worker's death is noticed)."""
    watchdog, _events = vision
    worker = watchdog.workers["vision"]
    ready(watchdog)
    spare_ready(watchdog)
    assert worker.spare is not None
    spare = worker.spare.process
    os.kill(worker.spare.pid, signal.SIGKILL)
    spare.join(5)
    os.kill(worker.pid, signal.SIGKILL)
    pump(watchdog, lambda _reports: worker.restarts == 1)
    assert worker.pid not in (spare.pid,)
    ready(watchdog)
    assert process_one(watchdog, writer)
    spare_ready(watchdog)
