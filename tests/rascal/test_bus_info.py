"""`rascal bus info`, `--json` for list, info and hz, and Ctrl-C, against a real publisher process
over loopback. The bus and key are given as options after the verb, never by the environment."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from protocol import channels
from rascal.cli import main
from tests.conftest import ROOT, Processes

BEACON = channels.OBSTACLES_BEACON


@pytest.fixture
def beacon(bus_url: str, key_file: Path, processes: Processes, monkeypatch: pytest.MonkeyPatch) -> Iterator[list[str]]:
    """A 20 Hz beacon; yields the global options that reach its bus, which the environment no longer names."""
    processes.module("beacon", "--set", "rate_hz=20")
    monkeypatch.delenv("RASCAL_BUS_URL")
    monkeypatch.delenv("RASCAL_KEY_FILE")
    time.sleep(0.5)
    yield ["--bus", bus_url, "--key-file", str(key_file)]


def test_bus_info_names_the_type_and_the_publisher_with_its_rate(
    beacon: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bus", "info", BEACON, "--duration", "1.5", "--json", *beacon]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["type"] == "ObstacleList" and info["fingerprint"] == "85175bc0e15949c0"
    assert [publisher["source"] for publisher in info["publishers"]] == [3]
    assert abs(info["publishers"][0]["rate_hz"] - 20.0) < 1.0, info
    assert main(["bus", "info", BEACON, "--duration", "0.6", *beacon]) == 0
    text = capsys.readouterr().out
    assert "type: ObstacleList" in text and "source 3: " in text and " Hz, " in text


def test_bus_list_and_hz_as_json(beacon: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main([*beacon[:2], "bus", "list", "--duration", "1", "--json", *beacon[2:]]) == 0
    listed = {row["channel"]: row for row in json.loads(capsys.readouterr().out)["channels"]}
    assert listed[BEACON]["type"] == "ObstacleList" and listed[BEACON]["sources"] == [3]
    assert main(["bus", "hz", BEACON, "--duration", "1.6", "--window", "0.75", "--json", *beacon]) == 0
    reports = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(reports) == 2 and all(abs(report["rate_hz"] - 20.0) < 1.0 for report in reports), reports
    assert all(report["channel"] == BEACON and report["lost"] == 0 for report in reports)


def test_ctrl_c_ends_echo_cleanly_with_status_0(beacon: list[str]) -> None:
    echo = subprocess.Popen(
        [sys.executable, "-m", "rascal.cli", "bus", "echo", BEACON, "--duration", "20", *beacon],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert echo.stdout is not None
        first = json.loads(echo.stdout.readline())
        echo.send_signal(signal.SIGINT)
        out, err = echo.communicate(timeout=5)
    finally:
        echo.kill()
    assert first["channel"] == BEACON and echo.returncode == 0 and err == "", err
    assert all(json.loads(line)["channel"] == BEACON for line in out.splitlines())
