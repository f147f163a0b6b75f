"""The simulator and every simulated sensor as separate processes on the signed loopback bus."""

from __future__ import annotations

import math
import time
from collections import defaultdict
from pathlib import Path

import pytest

from modules.sim.scenario import load_scenario
from protocol import channels
from protocol.auth import load_keyring
from protocol.codec import Envelope
from protocol.messages import SimTruth
from rascal.runtime.bus import Bus
from rascal.runtime.clock import SharedClock
from rascal.runtime.timeclient import TimeClient
from tests.conftest import Processes

pytestmark = pytest.mark.slow

LIDAR_SOURCE_IDS = {"lidar_h_left": 21, "lidar_h_right": 22, "lidar_v_left": 23, "lidar_v_right": 24}
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


LIDAR_FAULT = """
[[fault]]
sensors = ["lidars"]
kind = "silence"
start_s = 3.0
"""


def test_lidars_see_the_rock_within_20_cm_and_fall_silent_on_schedule(
    bus_url: str, key_file: Path, processes: Processes, tmp_path: Path
) -> None:
    (tmp_path / "course.rddf").write_text(RDDF)
    scenario = tmp_path / "lidar.toml"
    scenario.write_text(SCENARIO.split("[[fault]]")[0] + LIDAR_FAULT)
    rock = next(o for o in load_scenario(scenario).world.obstacles if o.name == "rock")
    processes.module("time_service")
    processes.module("sim", "--set", f"scenario={scenario}")
    for name, source_id in LIDAR_SOURCE_IDS.items():
        processes.module(
            "lidar",
            "--source-id",
            str(source_id),
            "--set",
            f"sensor={name}",
            "--set",
            f"scenario={scenario}",
            label=name,
        )
    clock = SharedClock()
    bus = Bus.open(bus_url, source_id=911, clock=clock, keyring=load_keyring(key_file))
    time_client = TimeClient(bus, clock)
    truth_at: dict[int, SimTruth] = {}
    scans: list[tuple[float, str, int, object]] = []  # (scenario time, channel, source, message)

    def on_truth(truth: SimTruth, env: Envelope) -> None:
        truth_at[env.t_meas_ns] = truth

    def on_lidar(channel: str):
        def handler(msg: object, env: Envelope) -> None:
            truth = truth_at.get(env.t_meas_ns)
            scans.append((truth.scenario_time_s if truth else -1.0, channel, env.source_id, (msg, truth)))

        return handler

    bus.subscribe(channels.SIM_TRUTH, on_truth)
    bus.subscribe(channels.OBSTACLES_LIDAR, on_lidar(channels.OBSTACLES_LIDAR))
    bus.subscribe(channels.SURFACE_PROFILE, on_lidar(channels.SURFACE_PROFILE))
    deadline = time.monotonic() + 25.0
    next_sync = 0.0
    latest = lambda: max((t.scenario_time_s for t in truth_at.values()), default=0.0)  # noqa: E731
    while time.monotonic() < deadline and latest() < 5.0:
        if time.monotonic() > next_sync:
            time_client.request()
            next_sync = time.monotonic() + 0.1
        bus.poll(0.01)
    bus.close()
    assert latest() >= 5.0, processes.log("sim")

    before = [s for s in scans if 1.0 <= s[0] < 2.9]
    for source_id in LIDAR_SOURCE_IDS.values():
        count = sum(s[2] == source_id for s in before)
        assert count / 1.9 == pytest.approx(25, rel=0.25), f"lidar {source_id}: {count} in 1.9 s"
    assert not [s for s in scans if s[0] >= 3.05], "a lidar spoke during the silence fault"

    errors = []
    for _t, channel, _source, (msg, truth) in before:
        if channel != channels.OBSTACLES_LIDAR or truth is None:
            continue
        for obstacle in msg.obstacles:
            c, s = math.cos(truth.yaw_rad), math.sin(truth.yaw_rad)
            east = truth.east_m + c * obstacle.x_m - s * obstacle.y_m
            north = truth.north_m + s * obstacle.x_m + c * obstacle.y_m
            errors.append(math.hypot(east - rock.east_m, north - rock.north_m))
    assert errors, "no horizontal lidar reported the rock"
    assert max(errors) <= 0.2
