"""A stop that stays: the operator's order outlives a restart of control, and `rascal stop |
pause | resume` repeat their order until control's commands show it in force."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path as FilePath

import pytest

from modules.control.stop_latch import RUN, StopLatch, StopOrder
from protocol.messages import StopMode
from rascal.operator_stop import in_force
from tests.conftest import ROOT, Processes
from tests.modules.control.test_control_process import Stand

# -- the latch --------------------------------------------------------------------------------


def test_a_missing_file_is_run_and_memory_only_latches_nothing(tmp_path: FilePath) -> None:
    assert StopLatch(tmp_path / "control.stop.json").load() == (RUN, None)
    memory = StopLatch(None)
    memory.store(StopOrder(StopMode.ESTOP, "x"))
    assert memory.load() == (RUN, None)


def test_a_pause_comes_back_as_it_was_and_an_estop_as_a_hold_until_run(tmp_path: FilePath) -> None:
    latch = StopLatch(tmp_path / "control.stop.json")
    latch.store(StopOrder(StopMode.PAUSE, "lunch"))
    assert latch.load() == (StopOrder(StopMode.PAUSE, "lunch"), None)
    latch.store(StopOrder(StopMode.ESTOP, "rock ahead"))
    order, problem = latch.load()
    assert problem is None and order.mode is StopMode.PAUSE and "e-stop before restart (rock ahead)" in order.reason
    latch.store(RUN)
    assert latch.load() == (RUN, None)
    assert [p.name for p in tmp_path.iterdir()] == ["control.stop.json"]  # no temporary left behind
    assert (tmp_path / "control.stop.json").stat().st_mode & 0o777 == 0o600


@pytest.mark.parametrize("text", ["{not json", '{"mode": "SIDEWAYS"}', "[]", '{"reason": "no mode"}'])
def test_an_unreadable_file_holds_the_vehicle_and_says_why(tmp_path: FilePath, text: str) -> None:
    path = tmp_path / "control.stop.json"
    path.write_text(text)
    order, problem = StopLatch(path).load()
    assert order.mode is StopMode.PAUSE
    assert problem is not None and str(path) in problem


def test_what_shows_an_order_in_force() -> None:
    assert in_force(StopMode.ESTOP, "estop: operator stop")
    assert not in_force(StopMode.ESTOP, "pause: lunch")
    assert in_force(StopMode.PAUSE, "pause: lunch") and in_force(StopMode.PAUSE, "estop: earlier")
    assert in_force(StopMode.RUN, "") and in_force(StopMode.RUN, "PATH stale (0.6 s old)")
    assert not in_force(StopMode.RUN, "pause: e-stop before restart (rock)")


# -- real processes ---------------------------------------------------------------------------


def _order(stand: Stand, word: str, *extra: str) -> subprocess.CompletedProcess[str]:
    """`rascal WORD` as an operator runs it, while the stand keeps the vehicle's inputs flowing."""
    tool = subprocess.Popen(
        [sys.executable, "-m", "rascal.cli", word, "--timeout", "5", *extra],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    stand.run_until(lambda: tool.poll() is not None, 15.0)
    out, _ = tool.communicate(timeout=5.0)
    return subprocess.CompletedProcess(tool.args, tool.returncode, out)


@pytest.mark.slow
def test_an_estop_survives_a_restart_of_control_until_an_explicit_resume(
    bus_url: str, key_file: FilePath, processes: Processes, scenario: FilePath, tmp_path: FilePath
) -> None:
    stop_file = tmp_path / "control.stop.json"
    control_args = ("--set", f"stop_file={stop_file}")
    processes.module("time_service")
    processes.module("sim", "--set", f"scenario={scenario}")
    control = processes.module("control", *control_args)
    stand = Stand(bus_url, key_file, scenario)
    try:
        assert stand.run_until(lambda: stand.speed() > 3.0, 30.0), processes.log("control")

        stopped = _order(stand, "stop", "--reason", "test e-stop")
        assert stopped.returncode == 0 and "control obeyed the e-stop" in stopped.stdout, stopped.stdout
        assert "clock synchronised" in stopped.stdout
        assert stand.run_until(lambda: stand.speed() == 0.0, 10.0), processes.log("control")

        # Killed and restarted (as the supervisor would): it comes back holding, not driving.
        control.send_signal(signal.SIGKILL)
        control.wait(timeout=5.0)
        restarted_at = len(stand.commands)
        processes.module("control", *control_args, label="control-restarted")
        assert stand.run_until(lambda: len(stand.commands) >= restarted_at + 100, 20.0), processes.log(
            "control-restarted"
        )
        after = [cmd for _t, cmd in stand.commands[restarted_at:]]
        assert all(cmd.brake == 1.0 and cmd.throttle == 0.0 for cmd in after)
        assert all(cmd.stop_reason.startswith("pause: e-stop before restart (test e-stop)") for cmd in after)
        assert stand.speed() == 0.0

        resumed = _order(stand, "resume")
        assert resumed.returncode == 0 and "control obeyed the resume" in resumed.stdout, resumed.stdout
        assert stand.run_until(lambda: stand.speed() > 1.0, 15.0), processes.log("control-restarted")
    finally:
        stand.listener.close()


@pytest.mark.slow
def test_an_order_nobody_obeys_is_reported_as_not_confirmed(bus_url: str, key_file: FilePath) -> None:
    del key_file  # exported to the tool through RASCAL_KEY_FILE
    result = subprocess.run(
        [sys.executable, "-m", "rascal.cli", "pause", "--timeout", "1"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=30.0,
        env={**os.environ, "RASCAL_BUS_URL": bus_url},
    )
    assert result.returncode == 1
    assert "pause NOT confirmed: no actuator command heard" in result.stderr
    assert "no time master answered" in result.stderr
