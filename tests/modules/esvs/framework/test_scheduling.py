"""Worker priorities: SCHED_FIFO where the OS allows, a nice value (said so) where it refuses."""

from __future__ import annotations

import os

import pytest

from modules.esvs import scheduling


def test_fifo_is_used_when_allowed(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple] = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda pid, policy, param: calls.append((pid, policy, param)))
    assert scheduling.apply("fifo", 45, 0) == "SCHED_FIFO 45"
    assert calls == [(0, os.SCHED_FIFO, os.sched_param(45))]
    scheduling.apply("fifo", 50, 0, reset_on_fork=True)
    assert calls[-1][1] == os.SCHED_FIFO | os.SCHED_RESET_ON_FORK


def test_a_refused_fifo_falls_back_to_nice_and_says_why(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_args: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    niced: list[int] = []
    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    monkeypatch.setattr(os, "setpriority", lambda which, who, nice: niced.append(nice))
    text = scheduling.apply("fifo", 25, 10)
    assert text.startswith("nice 10 (SCHED_FIFO 25 refused: PermissionError")
    assert niced == [10]
    assert scheduling.apply("nice", 25, 3) == "nice 3"
    monkeypatch.setattr(os, "setpriority", refuse)
    assert scheduling.apply("nice", 25, 3).startswith("default scheduling (nice 3 refused")
    assert scheduling.apply("none", 25, 3) == "default scheduling"


def test_fallback_nice_values_keep_the_priority_order() -> None:
    nices = [scheduling.fallback_nice(priority, 45) for priority in (45, 25, 20, 1)]
    assert nices == [0, 10, 13, 19]
    assert scheduling.fallback_nice(50, 45) == 0


def test_priorities_and_policies_are_checked() -> None:
    with pytest.raises(ValueError, match="policy"):
        scheduling.apply("deadline", 10, 0)
    with pytest.raises(ValueError, match=r"1\.\.99"):
        scheduling.check("fifo", 100)


def test_the_current_class_is_described() -> None:
    assert scheduling.current().startswith(("nice ", "SCHED_FIFO "))
