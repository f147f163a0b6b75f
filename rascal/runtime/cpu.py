"""How much of one core a process uses, its descendants included (the ESVS's vision workers and
their fork server are its children), measured from the kernel's accounting between two samples.

Linux's ``/proc/PID/task/TID/children`` lists a thread's children, so the tree is walked without
scanning every process (about 30 us a sample). Elsewhere only the process itself is counted.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

_TICK_NS = 1_000_000_000 // os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 10_000_000
UNKNOWN_PCT = -1.0  # the heartbeat's value for a period too short to judge
MIN_PERIOD_NS = 200_000_000  # shorter, a few ms of start-up work reads as a busy core


def descendants(pid: int) -> list[int]:
    """Every living descendant of ``pid`` (empty where /proc does not say)."""
    found: list[int] = []
    pending = [pid]
    while pending:
        parent = pending.pop()
        try:
            threads = os.listdir(f"/proc/{parent}/task")
        except OSError:
            continue
        for tid in threads:
            try:
                with open(f"/proc/{parent}/task/{tid}/children", "rb") as children:
                    kids = [int(kid) for kid in children.read().split()]
            except (OSError, ValueError):
                continue
            found += kids
            pending += kids
    return found


def process_cpu_ns(pid: int) -> int | None:
    """User + system CPU time of ``pid`` so far (all its threads), or None if it is gone."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as stat:
            fields = stat.read().rpartition(b")")[2].split()
        return (int(fields[11]) + int(fields[12])) * _TICK_NS
    except (OSError, ValueError, IndexError):
        return None


class CpuMeter:
    """Share of one core used by this process and its descendants between two :meth:`sample`
    calls. A descendant that ends between samples takes its last period's CPU with it: the
    heartbeat's 1 s period makes that a small undercount, never a double count."""

    def __init__(
        self,
        own_cpu_ns: Callable[[], int] = time.process_time_ns,
        wall_ns: Callable[[], int] = time.monotonic_ns,
        pid: int | None = None,
        children: bool = True,
    ) -> None:
        """``children=False`` counts the process alone (a supervisor's children are measured
        by their own heartbeats)."""
        self._own = own_cpu_ns
        self._wall = wall_ns
        self._pid = os.getpid() if pid is None else pid
        self._with_children = children
        self._last_wall = wall_ns()
        self._last_own = own_cpu_ns()
        self._children = self._children_cpu()

    def sample(self) -> float:
        """Percent of one core since the last sample (or since the meter was made), or
        UNKNOWN_PCT if that is under MIN_PERIOD_NS (the period then carries on to the next)."""
        wall = self._wall()
        elapsed = wall - self._last_wall
        if elapsed < MIN_PERIOD_NS:
            return UNKNOWN_PCT
        own, children = self._own(), self._children_cpu()
        used = own - self._last_own
        used += sum(cpu - self._children.get(pid, 0) for pid, cpu in children.items())
        self._last_wall, self._last_own, self._children = wall, own, children
        return 100.0 * max(used, 0) / elapsed

    def _children_cpu(self) -> dict[int, int]:
        if not self._with_children:
            return {}
        cpu = {pid: process_cpu_ns(pid) for pid in descendants(self._pid)}
        return {pid: ns for pid, ns in cpu.items() if ns is not None}
