"""One publisher process and one subscriber process per measurement, bounded in count and time.

The parent starts the subscriber, waits until it has subscribed, starts the publisher, and
collects both results through pipes. Children are always stopped in a ``finally`` (terminate,
then kill), and every loop in them ends on a message count or a deadline, whichever is first;
that holds for the busy mode too, where neither child ever sleeps.
"""

from __future__ import annotations

import multiprocessing
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from multiprocessing.synchronize import Event
from typing import Any

from benchmarks.bus_peers import Contender

READY_TIMEOUT_S = 10.0
# The subscriber stops this long after the last datagram once the publisher is done: long
# enough to drain a full receive buffer, short enough not to pad the run.
DRAIN_IDLE_S = 0.3
POLL_S = 0.02
# Sleep when ahead of schedule by more than this, spin for the rest: sleep() overshoots by tens
# of microseconds, which would bunch a 1 kHz stream into pairs.
SPIN_NS = 100_000
# Re-check the deadline at least every this many sends when the publisher falls behind.
MAX_BURST = 256
STOP_GRACE_S = 1.0


class BenchError(RuntimeError):
    """A measurement could not complete (a child failed, hung or never got ready)."""


@dataclass(frozen=True)
class PublisherResult:
    sent: int
    elapsed_s: float
    send_drops: int

    @property
    def rate_hz(self) -> float:
        return self.sent / self.elapsed_s if self.elapsed_s > 0 else 0.0


@dataclass(frozen=True)
class SubscriberResult:
    received: int
    latencies_ns: list[int]


@dataclass(frozen=True)
class PairResult:
    publisher: PublisherResult
    subscriber: SubscriberResult

    @property
    def lost(self) -> int:
        return max(0, self.publisher.sent - self.subscriber.received)


@dataclass(frozen=True)
class _ChildError:
    text: str


class _Recorder:
    """The subscriber's handler: one-way latency of every message, taken after decode."""

    def __init__(self) -> None:
        self.latencies_ns: list[int] = []
        self._clock = time.monotonic_ns

    def __call__(self, t_send_ns: int) -> None:
        self.latencies_ns.append(self._clock() - t_send_ns)


def run_pair(
    contender: Contender, rate_hz: float, count: int, keep_latencies: bool, *, busy: bool = False
) -> PairResult:
    """Send ``count`` messages at ``rate_hz`` from one process to another; both sides' results.

    By default the publisher keeps a schedule (sleeping when well ahead) and the subscriber waits
    in ``pump(POLL_S)``. With ``busy`` the publisher spins ``1 / rate_hz`` between sends and
    never catches up, and the subscriber calls ``pump(0.0)`` in a tight loop: no process sleeps.
    """
    ctx = multiprocessing.get_context("fork")  # contenders hold generated LCM modules: no pickling
    ready, done = ctx.Event(), ctx.Event()
    sub_out, sub_in = ctx.Pipe(duplex=False)
    pub_out, pub_in = ctx.Pipe(duplex=False)
    send_limit_s = 2.0 * count / rate_hz + 2.0
    subscriber = ctx.Process(
        target=_child,
        args=(sub_in, _subscribe, contender, count, ready, done, send_limit_s + 5.0, keep_latencies, busy),
        daemon=True,
    )
    publisher = ctx.Process(
        target=_child, args=(pub_in, _publish, contender, rate_hz, count, send_limit_s, busy), daemon=True
    )
    try:
        subscriber.start()
        if not ready.wait(READY_TIMEOUT_S):
            raise BenchError(f"{contender.name}: subscriber not ready after {READY_TIMEOUT_S:.0f} s")
        publisher.start()
        pub_result = _result(pub_out, send_limit_s + READY_TIMEOUT_S, contender.name)
        done.set()
        sub_result = _result(sub_out, send_limit_s + READY_TIMEOUT_S, contender.name)
        return PairResult(pub_result, sub_result)
    finally:
        for process in (publisher, subscriber):
            _stop(process)


def _child(conn: Connection, body: Callable[..., Any], *args: Any) -> None:
    try:
        conn.send(body(*args))
    except Exception:
        conn.send(_ChildError(traceback.format_exc()))
    finally:
        conn.close()


def _result(conn: Connection, timeout_s: float, name: str) -> Any:
    if not conn.poll(timeout_s):
        raise BenchError(f"{name}: no result within {timeout_s:.0f} s")
    result = conn.recv()
    if isinstance(result, _ChildError):
        raise BenchError(f"{name}: child failed:\n{result.text}")
    return result


def _stop(process: BaseProcess) -> None:
    if process.pid is None:
        return  # never started
    process.join(STOP_GRACE_S)
    if process.is_alive():
        process.terminate()
        process.join(STOP_GRACE_S)
    if process.is_alive():
        process.kill()
        process.join(STOP_GRACE_S)


def _publish(contender: Contender, rate_hz: float, count: int, limit_s: float, busy: bool) -> PublisherResult:
    sender = contender.sender()
    send_all = spaced_send if busy else paced_send
    try:
        sent, elapsed_s = send_all(sender.send, rate_hz, count, limit_s)
        return PublisherResult(sent, elapsed_s, sender.dropped())
    finally:
        sender.close()


def paced_send(send: Callable[[], None], rate_hz: float, count: int, limit_s: float) -> tuple[int, float]:
    """Call ``send`` ``count`` times on a fixed schedule; when behind, catch up back to back.

    Returns (sends made, seconds from the first send to the end of the last)."""
    period_ns = 1e9 / rate_hz
    start = time.monotonic_ns()
    stop = start + int(limit_s * 1e9)
    sent = 0
    now = start
    while sent < count and now < stop:
        due = min(count, int((now - start) / period_ns) + 1, sent + MAX_BURST)
        if due > sent:
            for _ in range(due - sent):
                send()
            sent = due
        else:
            ahead_ns = start + sent * period_ns - now
            if ahead_ns > SPIN_NS:
                time.sleep((ahead_ns - SPIN_NS) / 1e9)
        now = time.monotonic_ns()
    return sent, (now - start) / 1e9


def spaced_send(send: Callable[[], None], rate_hz: float, count: int, limit_s: float) -> tuple[int, float]:
    """Call ``send`` ``count`` times, each ``1 / rate_hz`` after the previous one began, spinning
    in between. A send held up (the process was preempted) goes as soon as it can, and the gap
    counts from there.

    Never catching up back to back keeps at most one message in flight whenever the gap is longer
    than a delivery, so no sample includes queueing behind an earlier one. Returns as paced_send."""
    gap_ns = round(1e9 / rate_hz)
    start = time.monotonic_ns()
    stop = start + int(limit_s * 1e9)
    sent = 0
    due = now = start
    while sent < count and now < stop:
        if now >= due:
            send()
            sent += 1
            due = now + gap_ns
        now = time.monotonic_ns()
    return sent, (now - start) / 1e9


def _subscribe(
    contender: Contender, expected: int, ready: Event, done: Event, limit_s: float, keep_latencies: bool, busy: bool
) -> SubscriberResult:
    recorder = _Recorder()
    receiver = contender.receiver(recorder)
    try:
        ready.set()
        _receive_until_quiet(receiver.pump, 0.0 if busy else POLL_S, recorder, expected, done, limit_s)
    finally:
        receiver.close()
    latencies = recorder.latencies_ns if keep_latencies else []
    return SubscriberResult(len(recorder.latencies_ns), latencies)


def _receive_until_quiet(
    pump: Callable[[float], int], poll_s: float, recorder: _Recorder, expected: int, done: Event, limit_s: float
) -> None:
    """Pump until all ``expected`` arrived, or the publisher is done and the bus went quiet.

    With ``poll_s`` 0.0 this is a busy loop; the deadline bounds it like the sleeping one."""
    now = time.monotonic()
    deadline = now + limit_s
    last_traffic = now
    while len(recorder.latencies_ns) < expected and now < deadline:
        handled = pump(poll_s)
        now = time.monotonic()
        if handled:
            last_traffic = now
        # Idle time first: done.is_set() takes a lock, too dear to ask on every busy poll.
        elif now - last_traffic > DRAIN_IDLE_S and done.is_set():
            break
