"""Link faults between real processes: a receiver behind 20 % loss and 20 ms jitter hears ~80 %
of a stream that a clean receiver beside it hears whole; a deployment's ``[[faults]]`` reach
only the module they name."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from protocol import channels
from protocol.codec import Envelope
from protocol.messages import ModuleStatus
from tests.conftest import ROOT, env_with
from tests.integration.listener import Listener
from tests.integration.stack import rascal_run_command

pytestmark = pytest.mark.slow

RATE_HZ = 200
COUNT = 1600  # 8 s
HEALTH_SOURCE = 2
BEACON_SOURCE = 3


def echo(channel: str, duration_s: float, log: Path, **env: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "rascal.cli", "bus", "echo", channel, "--duration", str(duration_s)],
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
        cwd=ROOT,
        env=env_with(**env),
    )


def seqs_in(log: Path) -> list[int]:
    return [json.loads(line)["seq"] for line in log.read_text().splitlines() if line.startswith("{")]


def test_a_receiver_behind_loss_and_jitter_hears_about_80_percent(bus_url: str, key_file: Path, tmp_path: Path) -> None:
    faulty_log, clean_log = tmp_path / "faulty.log", tmp_path / "clean.log"
    faults = "channels=WHEEL_SPEED,loss_pct=20,jitter_ms=20,seed=9"
    receivers = [
        echo(channels.WHEEL_SPEED, 20.0, faulty_log, RASCAL_FAULTS=faults),
        echo(channels.WHEEL_SPEED, 20.0, clean_log),
    ]
    time.sleep(3.0)  # let both start listening; the window below copes with either starting late
    body = '{"speed_mps": 5, "odometer_m": 1}'
    publish = ["bus", "pub", channels.WHEEL_SPEED, body, "--rate", str(RATE_HZ), "--count", str(COUNT)]
    publisher = subprocess.run(
        [sys.executable, "-m", "rascal.cli", *publish], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert publisher.returncode == 0, publisher.stderr
    for receiver in receivers:
        receiver.wait(timeout=40)
    faulty, clean = seqs_in(faulty_log), seqs_in(clean_log)
    # Compare over the stretch both heard (from the later first to the earlier last message).
    low, high = max(min(faulty), min(clean)), min(max(faulty), max(clean))
    window = high - low + 1
    assert window > COUNT // 2, (len(faulty), len(clean))
    clean_in = {seq for seq in clean if low <= seq <= high}
    faulty_in = [seq for seq in faulty if low <= seq <= high]
    assert len(clean_in) >= 0.99 * window, "the receiver without faults lost messages"
    assert len(set(faulty_in)) == len(faulty_in), "a duplicate got through"
    assert abs(len(faulty_in) / window - 0.8) < 0.05, (len(faulty_in), window)
    assert faulty_in != sorted(faulty_in), "20 ms of jitter at 5 ms spacing must reorder some"


DEPLOYMENT = """
[deployment]
name = "faulty-link"
bus = "{bus}"

[modules.time_service]

[modules.beacon]

[modules.health]

[[faults]]
modules = ["health"]
channels = "MODULE_STATUS"
corrupt_pct = 50
seed = 4
"""


def test_deployment_faults_reach_only_the_module_they_name(bus_url: str, key_file: Path, tmp_path: Path) -> None:
    deploy = tmp_path / "deploy.toml"
    deploy.write_text(DEPLOYMENT.format(bus=bus_url))
    runs = tmp_path / "runs"
    command = rascal_run_command(deploy, runs, 14)
    supervisor = subprocess.Popen(command, cwd=ROOT, stdout=(tmp_path / "run.log").open("wb"), stderr=subprocess.STDOUT)
    listener = Listener(bus_url, key_file, source_id=914)
    rejected: dict[int, int] = {}

    def on_status(status: ModuleStatus, envelope: Envelope) -> None:
        rejected[envelope.source_id] = status.rx_rejected

    listener.subscribe(channels.MODULE_STATUS, on_status)
    try:
        heard = listener.wait_until(lambda: rejected.get(HEALTH_SOURCE, 0) >= 3, timeout_s=25.0)
        assert heard, (rejected, (tmp_path / "run.log").read_text())
    finally:
        listener.close()
        supervisor.wait(timeout=40)
    # The others hear the same heartbeats uncorrupted.
    assert rejected.get(BEACON_SOURCE) == 0 and rejected.get(1) == 0, rejected
    (run_dir,) = runs.iterdir()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["modules"]["health"]["rx_rejected"] > 0
    assert summary["modules"]["beacon"]["rx_rejected"] == 0
    # Each process with faults logs what they did as it exits; the others have none.
    health_log = (run_dir / "health.log").read_text().splitlines()
    assert "corrupted" in next(line for line in health_log if line.startswith("link faults"))
    assert "link faults" not in (run_dir / "beacon.log").read_text()
