"""The simulator and every sensor stub as separate processes on the signed loopback bus."""

from __future__ import annotations

import time
from collections import defaultdict
from pathlib import Path

import pytest

from protocol import channels
from protocol.auth import load_keyring
from protocol.codec import Envelope
from protocol.messages import SimTruth
from rascal.bus import Bus
from rascal.clock import SharedClock
from rascal.timeclient import TimeClient
from tests.conftest import Processes

pytestmark = pytest.mark.slow

RDDF = "1,34.8650000,-116.8900000,30,25\n2,34.8650000,-116.8790000,30,25\n"
SCENARIO = """
[scenario]
rddf = "course.rddf"
seed = 7

[[obstacle]]
name = "rock"
shape = "cylinder"
at_m = 25.0
offset_m = 2.0
radius_m = 0.5
height_m = 1.2

[[fault]]
sensors = ["gps"]
kind = "outage"
start_s = 2.0
end_s = 3.0
"""


@pytest.fixture
def scenario(tmp_path: Path) -> Path:
    (tmp_path / "course.rddf").write_text(RDDF)
    path = tmp_path / "scenario.toml"
    path.write_text(SCENARIO)
    return path


def test_simulator_and_nav_sensors_run_as_processes(
    bus_url: str, key_file: Path, processes: Processes, scenario: Path
) -> None:
    processes.module("time_service")
    processes.module("sim", "--set", f"scenario={scenario}")
    processes.module("nav_sensors", "--set", f"scenario={scenario}")
    clock = SharedClock()
    bus = Bus.open(bus_url, source_id=910, clock=clock, keyring=load_keyring(key_file))
    time_client = TimeClient(bus, clock)
    arrivals: dict[str, list[float]] = defaultdict(list)  # scenario time of each message
    latest_truth: list[SimTruth] = []

    def on_truth(truth: SimTruth, _env: Envelope) -> None:
        latest_truth.append(truth)
        arrivals[channels.SIM_TRUTH].append(truth.scenario_time_s)

    def record(channel: str):
        return lambda _msg, _env: arrivals[channel].append(latest_truth[-1].scenario_time_s if latest_truth else -1)

    bus.subscribe(channels.SIM_TRUTH, on_truth)
    for channel in (channels.IMU, channels.GPS, channels.WHEEL_SPEED, channels.MAG_HEADING):
        bus.subscribe(channel, record(channel))
    deadline = time.monotonic() + 20.0
    next_sync = 0.0
    while time.monotonic() < deadline and (not latest_truth or latest_truth[-1].scenario_time_s < 5.0):
        if time.monotonic() > next_sync:
            time_client.request()
            next_sync = time.monotonic() + 0.1
        bus.poll(0.01)
    bus.close()
    assert latest_truth and latest_truth[-1].scenario_time_s >= 5.0, processes.log("sim")

    def rate(channel: str, start_s: float, end_s: float) -> float:
        return sum(start_s <= t < end_s for t in arrivals[channel]) / (end_s - start_s)

    assert rate(channels.SIM_TRUTH, 1.0, 5.0) == pytest.approx(100, rel=0.1)
    assert rate(channels.IMU, 1.0, 5.0) == pytest.approx(100, rel=0.15), processes.log("nav_sensors")
    assert rate(channels.WHEEL_SPEED, 1.0, 5.0) == pytest.approx(50, rel=0.15)
    assert rate(channels.MAG_HEADING, 1.0, 5.0) == pytest.approx(40, rel=0.15)  # two magnetometers
    # The GPS outage on the fault schedule, 2-3 s of scenario time (allowing one 10 Hz period of skew).
    assert rate(channels.GPS, 0.5, 1.9) == pytest.approx(10, rel=0.2)
    assert rate(channels.GPS, 2.1, 2.9) == 0
    assert rate(channels.GPS, 3.1, 4.9) == pytest.approx(10, rel=0.2)
