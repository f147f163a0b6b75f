"""The whole stack drives a short course: simulator, navigation sensors, four lidars, stereo
camera and ESVS, INS, brain and control, each its own process on the signed loopback bus under
`rascal run`. Mid-drive the brain is killed: control brakes within its path timeout, the
supervisor restarts the brain, and the drive resumes and finishes with no collision."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from protocol import channels
from protocol.codec import Envelope
from protocol.messages import ActuatorCommand, SimTruth
from tests.conftest import ROOT
from tests.integration.listener import Listener
from tests.integration.test_supervisor import pids_of

pytestmark = pytest.mark.slow

# About 300 m: east, then a gentle bend to the north-east; 25 mph limit, 40 ft boundary.
RDDF = "1,34.8650000,-116.8900000,40,25\n2,34.8650000,-116.8880000,40,25\n3,34.8660000,-116.8870000,40,25\n"
SCENARIO = """
[scenario]
rddf = "course.rddf"
seed = 3

[road]
half_width_m = 3.0

[[obstacle]]
name = "rock"
shape = "cylinder"
at_m = 120.0
offset_m = 0.8
radius_m = 0.6
height_m = 1.0
"""
MODULES = """
[modules.time_service]
[modules.sim]
[modules.nav_sensors]
[modules.lidar_h_left]
module = "lidar"
source_id = 21
set = {{ sensor = "lidar_h_left" }}
[modules.lidar_h_right]
module = "lidar"
source_id = 22
set = {{ sensor = "lidar_h_right" }}
[modules.lidar_v_left]
module = "lidar"
source_id = 23
set = {{ sensor = "lidar_v_left" }}
[modules.lidar_v_right]
module = "lidar"
source_id = 24
set = {{ sensor = "lidar_v_right" }}
[modules.stereo_camera]
set = {{ ring_name = "{ring}" }}
[modules.esvs]
set = {{ ring_name = "{ring}" }}
[modules.ins]
[modules.brain]
[modules.control]
[modules.referee]
"""
BRAIN_KILL_AT_M = 90.0
PATH_MAX_AGE_S = 0.5  # control's default


def write_deployment(tmp_path: Path, bus_url: str) -> Path:
    (tmp_path / "course.rddf").write_text(RDDF)
    (tmp_path / "scenario.toml").write_text(SCENARIO)
    head = f'[deployment]\nname = "short"\nbus = "{bus_url}"\nscenario = "scenario.toml"\ncourse = "course.rddf"\n'
    deploy = tmp_path / "deploy.toml"
    deploy.write_text(head + MODULES.format(ring=f"rascal-test-{os.getpid()}-{tmp_path.name[-8:]}"))
    return deploy


def test_the_stack_drives_a_short_course_and_survives_losing_the_brain(
    bus_url: str, key_file: Path, tmp_path: Path
) -> None:
    deploy = write_deployment(tmp_path, bus_url)
    runs = tmp_path / "runs"
    log = (tmp_path / "run.log").open("wb")
    command = [sys.executable, "-m", "rascal.cli", "run", str(deploy), "--duration", "240", "--runs-dir", str(runs)]
    supervisor = subprocess.Popen(command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    listener = Listener(bus_url, key_file, source_id=914)
    truth: list[SimTruth] = []
    commands: list[tuple[float, ActuatorCommand]] = []
    listener.subscribe(channels.SIM_TRUTH, lambda msg, _env: truth.append(msg))

    def on_command(command: ActuatorCommand, _env: Envelope) -> None:
        commands.append((time.monotonic(), command))

    listener.subscribe(channels.ACTUATOR_COMMAND, on_command)
    try:
        reached = listener.wait_until(lambda: bool(truth) and truth[-1].progress_m >= BRAIN_KILL_AT_M, 150.0)
        assert reached, (tmp_path / "run.log").read_text()[-3000:]
        (brain,) = pids_of("brain", bus_url)
        killed_at = time.monotonic()
        os.kill(brain, signal.SIGKILL)

        def path_stale_brakes() -> list[float]:
            return [t for t, c in commands if t > killed_at and c.brake >= 0.99 and "PATH" in c.stop_reason]

        assert listener.wait_until(lambda: bool(path_stale_brakes()), 5.0)
        reaction_s = path_stale_brakes()[0] - killed_at
        print(f"brain killed at {truth[-1].progress_m:.0f} m: control braking after {reaction_s * 1000:.0f} ms")
        assert reaction_s <= PATH_MAX_AGE_S + 0.15  # the path's age limit, plus one 50 Hz control tick and slack
    finally:
        listener.close()
    supervisor.wait(timeout=300)
    assert supervisor.returncode == 0, (tmp_path / "run.log").read_text()[-3000:]
    (run_dir,) = runs.iterdir()
    summary = json.loads((run_dir / "summary.json").read_text())
    drive = summary["drive"]
    print(json.dumps(drive))
    assert summary["finished"] and drive["finished"]
    assert drive["collisions"] == 0 and drive["corridor_exits"] == 0
    assert drive["cross_track_rms_m"] <= 0.3
    assert drive["min_clearance_m"] > 0.3
    assert summary["modules"]["brain"]["restarts"] == 1
