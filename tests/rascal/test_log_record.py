"""`rascal log record`: the live bus into MCAP with the recorder's writer, until Ctrl-C."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from protocol import channels
from rascal.cli import main
from rascal.logread import check_sequences, iter_datagrams
from tests.conftest import ROOT, Processes


def test_ctrl_c_finishes_a_recording_of_the_chosen_channels(
    bus_url: str, key_file: Path, processes: Processes, tmp_path: Path
) -> None:
    processes.module("beacon", "--set", "rate_hz=20")
    out = tmp_path / "bus.mcap"
    command = ["log", "record", channels.OBSTACLES_BEACON, "-o", str(out), "--duration", "20"]
    recorder = subprocess.Popen(
        [sys.executable, "-m", "rascal.cli", *command],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert recorder.stdout is not None and "Ctrl-C ends it" in recorder.stdout.readline()
        time.sleep(1.5)
        recorder.send_signal(signal.SIGINT)
        stdout, stderr = recorder.communicate(timeout=5)
    finally:
        recorder.kill()
    assert recorder.returncode == 0 and stderr == "" and f"into {out}" in stdout, stderr
    recorded = {datagram.channel for datagram in iter_datagrams(out)}
    assert recorded == {channels.OBSTACLES_BEACON}
    report = check_sequences(out)
    assert report.ok, report.problems()
    assert report.recorded[channels.OBSTACLES_BEACON] >= 15


def test_the_recorder_command_its_help_names_runs(capsys: pytest.CaptureFixture[str]) -> None:
    """``python -m rascal.recording --help`` says ``rascal module recorder``, so that must work."""
    with pytest.raises(SystemExit) as exit_:
        main(["module", "recorder", "--help"])
    assert exit_.value.code == 0 and "usage: rascal module recorder" in capsys.readouterr().out
