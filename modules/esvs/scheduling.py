"""Process priorities for the ESVS round and its vision workers (CAMBADA: Linux SCHED_FIFO with
priorities 15-50, so a more important process preempts a less important one at once).

``apply(policy, priority, nice)`` sets the calling process's scheduling and returns one line
saying what it got, for the module status. SCHED_FIFO needs CAP_SYS_NICE (and a container may
refuse it even to root); the fallback is a nice value, which only weights the time-sharing
scheduler and cannot preempt, and the line says so.
"""

from __future__ import annotations

import os

POLICIES = ("fifo", "nice", "none")
FIFO_MIN, FIFO_MAX = 1, 99


def check(policy: str, priority: int) -> None:
    if policy not in POLICIES:
        raise ValueError(f"scheduling policy must be one of {POLICIES}, not {policy!r}")
    if not FIFO_MIN <= priority <= FIFO_MAX:
        raise ValueError(f"SCHED_FIFO priority must be in {FIFO_MIN}..{FIFO_MAX}, not {priority}")


def fallback_nice(priority: int, top_priority: int) -> int:
    """The nice value standing in for ``priority`` when SCHED_FIFO is refused: the most important
    process keeps 0 (raising priority needs the privilege that was just refused), the others step
    down one nice level per two priority levels below it."""
    return max(0, min(19, (top_priority - priority + 1) // 2))


def apply(policy: str, priority: int, nice: int, *, reset_on_fork: bool = False) -> str:
    """Give this process ``priority`` under SCHED_FIFO, or ``nice`` under the default scheduler.
    ``reset_on_fork`` keeps children (e.g. a fork server) out of the real-time class."""
    check(policy, priority)
    if policy == "none":
        return "default scheduling"
    refused = ""
    if policy == "fifo":
        flags = os.SCHED_FIFO | (os.SCHED_RESET_ON_FORK if reset_on_fork else 0)
        try:
            os.sched_setscheduler(0, flags, os.sched_param(priority))
            return f"SCHED_FIFO {priority}"
        except (OSError, AttributeError) as exc:  # PermissionError is an OSError; AttributeError: not Linux
            refused = f" (SCHED_FIFO {priority} refused: {exc.__class__.__name__}: {exc})"
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except OSError as exc:
        return f"default scheduling (nice {nice} refused: {exc}){refused}"
    return f"nice {nice}{refused}"


def current() -> str:
    """What this process runs under now."""
    try:
        policy = os.sched_getscheduler(0)
        if policy == os.SCHED_FIFO:
            return f"SCHED_FIFO {os.sched_getparam(0).sched_priority}"
    except (OSError, AttributeError):
        pass
    return f"nice {os.getpriority(os.PRIO_PROCESS, 0)}"
