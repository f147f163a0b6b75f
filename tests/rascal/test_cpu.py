"""CPU per process, children included: what the heartbeat reports and the supervisor budgets."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import pytest

from rascal.run import cpu_list
from rascal.runtime.cpu import UNKNOWN_PCT, CpuMeter, descendants, process_cpu_ns
from rascal.supervisor import CPU_BUDGET_BEATS, CpuBooks

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc (Linux)")

# A child that spins for a while, and a grandchild that sleeps (as the ESVS's fork server's workers).
SPIN = "import time\nend = time.process_time() + {s}\nwhile time.process_time() < end: pass\n"
NEST = (
    "import subprocess, sys, time\n"
    "subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(5)'])\n"
    "time.sleep(5)\n"
)


def test_a_busy_child_is_counted_and_only_with_children() -> None:
    with_children, alone = CpuMeter(), CpuMeter(children=False)
    child = subprocess.Popen([sys.executable, "-c", SPIN.format(s=0.6)])
    try:
        time.sleep(0.3)
        assert child.pid in descendants(os.getpid())
        time.sleep(0.5)
        # Still alive (it spins 0.6 s of CPU after a start-up of its own): it is in the sample.
        counted, own = with_children.sample(), alone.sample()
    finally:
        child.kill()
        child.wait()
    assert counted > own + 30.0, (counted, own)  # about 0.5 s of its CPU in 0.8 s of wall time
    assert own < 30.0


def test_grandchildren_are_found_and_a_gone_process_has_no_cpu() -> None:
    child = subprocess.Popen([sys.executable, "-c", NEST])
    try:
        deadline = time.monotonic() + 5.0
        while len(descendants(child.pid)) < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        (grandchild,) = descendants(child.pid)
        assert process_cpu_ns(grandchild) is not None
    finally:
        for pid in descendants(child.pid):
            subprocess.run(["kill", "-9", str(pid)], check=False)
        child.kill()
        child.wait()
    assert process_cpu_ns(child.pid) is None  # reaped
    assert descendants(child.pid) == []


def test_the_meter_reads_a_share_of_one_core_between_samples() -> None:
    cpu, wall = [0], [0]
    meter = CpuMeter(own_cpu_ns=lambda: cpu[0], wall_ns=lambda: wall[0], children=False)
    cpu[0], wall[0] = 250_000_000, 1_000_000_000
    assert meter.sample() == pytest.approx(25.0)
    cpu[0], wall[0] = 1_250_000_000, 1_500_000_000
    assert meter.sample() == pytest.approx(200.0)  # two cores' worth: threads
    cpu[0], wall[0] = 1_260_000_000, 1_510_000_000
    assert meter.sample() == UNKNOWN_PCT  # 10 ms: too short to judge; it carries on
    cpu[0], wall[0] = 1_300_000_000, 1_900_000_000
    assert meter.sample() == pytest.approx(12.5)


def test_over_budget_for_ten_beats_is_said_once_until_it_comes_back_under() -> None:
    books = CpuBooks(budget_pct=10.0)
    said = [books.add(pct) for pct in [12.0] * (CPU_BUDGET_BEATS - 1) + [9.0] + [12.0] * (CPU_BUDGET_BEATS + 5)]
    assert said.count(True) == 1 and said.index(True) == 2 * CPU_BUDGET_BEATS - 1
    assert books.add(5.0) is False
    assert [books.add(11.0) for _ in range(CPU_BUDGET_BEATS)][-1] is True  # a new run over it
    assert books.mean_pct == pytest.approx(books.total_pct / books.beats) and books.peak_pct == 12.0


@pytest.mark.parametrize(("text", "cpus"), [("0", {0}), ("0,2", {0, 2}), ("1-3", {1, 2, 3}), ("0,2-3", {0, 2, 3})])
def test_rascal_run_takes_cpu_lists_as_taskset_writes_them(text: str, cpus: set[int]) -> None:
    assert cpu_list(text) == cpus


@pytest.mark.parametrize("text", ["", "x", "1-", "-1", "0,,1"])
def test_a_bad_cpu_list_is_refused(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match="expected CPU numbers"):
        cpu_list(text)
