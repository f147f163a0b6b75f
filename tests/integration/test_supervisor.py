"""`rascal run` supervising real processes: a killed module is back within a second, a hung one
is killed and restarted, a module over its CPU budget is reported, and the run ends by itself with
a summary."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from protocol import channels
from protocol.codec import Envelope
from protocol.messages import HealthEvent, ModuleStatus
from tests.conftest import ROOT
from tests.integration.listener import Listener
from tests.integration.stack import rascal_run_command

pytestmark = pytest.mark.slow

BEACON_SOURCE = 3
DEPLOYMENT = """
[deployment]
name = "supervised"
bus = "{bus}"

[modules.time_service]

[modules.beacon]
heartbeat_timeout_s = 1.5

[modules.health]
cpu_budget_pct = 0.01  # it uses more: over budget from its first heartbeat on
"""


def pids_of(module: str, bus_url: str) -> list[int]:
    """Processes running ``modules.<module>`` on this test's bus (by their command lines)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if f"modules.{module}".encode() in argv and bus_url.encode() in argv:
            found.append(int(entry.name))
    return found


def test_rascal_run_restarts_killed_and_hung_modules(bus_url: str, key_file: Path, tmp_path: Path) -> None:
    deploy = tmp_path / "deploy.toml"
    deploy.write_text(DEPLOYMENT.format(bus=bus_url))
    runs = tmp_path / "runs"
    log = (tmp_path / "run.log").open("wb")
    command = rascal_run_command(deploy, runs, 25)
    supervisor = subprocess.Popen(command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    listener = Listener(bus_url, key_file, source_id=913)
    beats: list[float] = []  # arrival times of the beacon's heartbeats
    events: list[HealthEvent] = []

    def on_status(_status: ModuleStatus, env: Envelope) -> None:
        if env.source_id == BEACON_SOURCE:
            beats.append(time.monotonic())

    listener.subscribe(channels.MODULE_STATUS, on_status)
    listener.subscribe(channels.HEALTH, lambda event, _env: events.append(event))
    try:
        assert listener.wait_until(lambda: len(beats) >= 2, timeout_s=20.0), (tmp_path / "run.log").read_text()
        # SIGKILL: back (its first heartbeat, sent as it starts) within a second.
        (victim,) = pids_of("beacon", bus_url)
        killed_at = time.monotonic()
        os.kill(victim, signal.SIGKILL)
        assert listener.wait_until(lambda: beats[-1] > killed_at, timeout_s=5.0)
        assert beats[-1] - killed_at < 1.0
        assert pids_of("beacon", bus_url) != [victim]
        # SIGSTOP: alive but silent; killed after its 1.5 s heartbeat timeout and restarted.
        (hung,) = pids_of("beacon", bus_url)
        stopped_at = time.monotonic()
        os.kill(hung, signal.SIGSTOP)
        assert listener.wait_until(lambda: beats[-1] > stopped_at + 1.5, timeout_s=8.0)
        assert pids_of("beacon", bus_url) not in ([], [hung])
    finally:
        listener.close()
        supervisor.wait(timeout=40)
    assert supervisor.returncode == 0, (tmp_path / "run.log").read_text()
    restarts = [e for e in events if e.code == "module_restart"]
    assert [e.text.split()[0] for e in restarts] == ["beacon", "beacon"]
    assert "SIGKILL" in restarts[0].text and "no heartbeat" in restarts[1].text
    (run_dir,) = runs.iterdir()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["modules"]["beacon"]["restarts"] == 2
    assert summary["modules"]["time_service"]["restarts"] == 0
    assert summary["messages_per_s"][channels.OBSTACLES_BEACON] > 5  # as the recorder counted them
    # CPU: every module's mean over its heartbeats, the total and the supervisor's own.
    cpu = {label: module["cpu_pct"] for label, module in summary["modules"].items()}
    assert set(cpu) == {"recorder", "time_service", "beacon", "health"} and all(0 < pct < 100 for pct in cpu.values())
    assert summary["cpu_pct"]["modules"] == pytest.approx(sum(cpu.values()), abs=0.2)
    assert 0 < summary["cpu_pct"]["supervisor"] < 100
    assert summary["health_events"]["supervisor:cpu_budget"] == 1  # said once, though over it all along
    # Recorded raw, the JSON channels added after the run: Foxglove-ready.
    with (run_dir / "run.mcap").open("rb") as stream:
        summary_record = make_reader(stream).get_summary()
    assert summary_record is not None
    topics = {channel.topic for channel in summary_record.channels.values()}
    assert {channels.OBSTACLES_BEACON, channels.OBSTACLES_BEACON + ".json"} <= topics
    assert not pids_of("beacon", bus_url), "the run stopped its modules"
