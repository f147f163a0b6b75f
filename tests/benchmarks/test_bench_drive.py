"""The drive benchmark's seeded copies of the default deployment, its pass/fail rule, and how it
stops the stack it started."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from benchmarks.bench_drive import Stopped, _raise_stopped, run_stack, seeded_deployment
from benchmarks.leaderboard import meets_targets
from modules.sim.scenario import load_scenario
from rascal.runtime.deployment import load_deployment

GOOD = {
    "finished": True,
    "collisions": 0,
    "corridor_exits": 0,
    "hazard_entries": 0,
    "speed_ratio": 0.81,
    "cross_track_rms_m": 0.12,
}


def test_a_seeded_copy_changes_only_the_seed_and_the_bus(tmp_path: Path) -> None:
    default = load_deployment()
    copy = load_deployment(seeded_deployment(2007, tmp_path))
    assert copy.scenario is not None and default.scenario is not None
    seeded, original = load_scenario(copy.scenario), load_scenario(default.scenario)
    assert seeded.seed == 2007 and original.seed != 2007
    assert seeded.route.length_m == original.route.length_m
    assert [o.name for o in seeded.world.obstacles] == [o.name for o in original.world.obstacles]
    assert seeded.world.obstacles != original.world.obstacles  # the random ones moved
    assert copy.course == default.course
    assert copy.bus != default.bus and copy.bus.endswith("?ttl=0") and copy.bus.startswith("udpm://239.255.")
    assert [(m.label, m.source_id) for m in copy.modules] == [(m.label, m.source_id) for m in default.modules]


def test_every_target_must_be_met() -> None:
    assert meets_targets(GOOD)
    for key, bad in (
        ("finished", False),
        ("collisions", 1),
        ("corridor_exits", 1),
        ("hazard_entries", 1),
        ("speed_ratio", 0.79),
        ("cross_track_rms_m", 0.31),
    ):
        assert not meets_targets({**GOOD, key: bad}), key
    assert not meets_targets({"seed": 1, "finished": False})


# A stand-in for `rascal run`: it records that it was told to stop, as rascal run stops its modules.
STACK = """
import pathlib, signal, sys, time
flag = pathlib.Path(sys.argv[1])
signal.signal(signal.SIGTERM, lambda *_: (flag.write_text("stopped"), sys.exit(0)))
flag.write_text("running")
time.sleep(60)
"""


def _wait_for(path: Path, text: str, limit_s: float = 10.0) -> None:
    deadline = time.monotonic() + limit_s
    while not (path.exists() and path.read_text() == text):
        assert time.monotonic() < deadline, f"{path} never said {text!r}"
        time.sleep(0.02)


def test_a_stack_past_its_timeout_is_told_to_stop(tmp_path: Path) -> None:
    flag = tmp_path / "flag"
    with (tmp_path / "log").open("w") as log, pytest.raises(subprocess.TimeoutExpired):
        run_stack([sys.executable, "-c", STACK, str(flag)], log, timeout_s=1.0, grace_s=5.0)
    assert flag.read_text() == "stopped"


def test_sigterm_to_the_benchmark_stops_the_stack_it_started(tmp_path: Path) -> None:
    flag = tmp_path / "flag"
    previous = signal.signal(signal.SIGTERM, _raise_stopped)
    timer = threading.Thread(target=lambda: (_wait_for(flag, "running"), os.kill(os.getpid(), signal.SIGTERM)))
    timer.start()
    try:
        with (tmp_path / "log").open("w") as log, pytest.raises(Stopped):
            run_stack([sys.executable, "-c", STACK, str(flag)], log, timeout_s=30.0, grace_s=5.0)
    finally:
        signal.signal(signal.SIGTERM, previous)
        timer.join()
    assert flag.read_text() == "stopped"


def test_a_stack_that_ignores_sigterm_is_killed_after_the_grace(tmp_path: Path) -> None:
    # A stand-in for a hung rascal run: it ignores SIGTERM and would outlive the whole test.
    stubborn = "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); time.sleep(60)"
    start = time.monotonic()
    with (tmp_path / "log").open("w") as log, pytest.raises(subprocess.TimeoutExpired):
        run_stack([sys.executable, "-c", stubborn], log, timeout_s=0.5, grace_s=0.5)
    assert time.monotonic() - start < 10.0
