"""EsvsClient against a scripted ESVS on an in-process bus: typed reports, sequence gaps,
staleness and its recovery, status and health filtering, and what the client sends."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest

from esvs_client import EsvsClient, LaneReport, ObstacleReport
from protocol import channels
from protocol.auth import Keyring
from protocol.messages import (
    ConfigUpdate,
    Frame,
    HealthEvent,
    LaneBorder,
    LaneBorders,
    ModuleStatus,
    NavQuality,
    Obstacle,
    ObstacleList,
    Sensor,
    Severity,
    VehicleState,
)
from protocol.transport import MemTransport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import ManualClock

ROCK = Obstacle(20.9, 0.5, 1.3, 1.2, 1.2, 0.0, 0.9, 20.3)
EDGE = LaneBorder(1, 3.0, 0.0, 0.0, 12.0, 36.0, 0.8)


class FakeTime:
    def __init__(self) -> None:
        self.t_ns = 5_000_000_000

    def __call__(self) -> int:
        return self.t_ns

    def advance(self, seconds: float) -> None:
        self.t_ns += int(seconds * 1e9)


@dataclass
class Rig:
    esvs: Bus
    other: Bus
    client: EsvsClient
    time: FakeTime
    clock: ManualClock
    seen: dict[str, list] = field(default_factory=dict)

    def report(self, bus: Bus | None = None, skip: int = 0) -> None:
        """The ESVS publishes one obstacle and one lane report (``skip`` of each lost first)."""
        bus = bus or self.esvs
        for _ in range(skip):
            bus.encode(channels.OBSTACLES_ESVS, ObstacleList(Sensor.ESVS, Frame.VEHICLE, (ROCK,)))
        bus.publish(channels.OBSTACLES_ESVS, ObstacleList(Sensor.ESVS, Frame.VEHICLE, (ROCK,)), self.clock.t_ns - 150)
        bus.publish(channels.LANE_BORDERS, LaneBorders(Sensor.ESVS, (EDGE,)), self.clock.t_ns - 150)


@pytest.fixture
def rig() -> Iterator[Rig]:
    hub, keyring, clock, fake_time = uuid.uuid4().hex, Keyring.generate(), ManualClock(), FakeTime()
    seen: dict[str, list] = {name: [] for name in ("obstacles", "lanes", "status", "health", "stale")}
    client_bus = Bus(MemTransport(hub), 50, keyring, clock)
    client = EsvsClient(
        client_bus,
        source_id=20,
        stale_rounds=3,
        on_obstacles=seen["obstacles"].append,
        on_lanes=seen["lanes"].append,
        on_status=seen["status"].append,
        on_health=seen["health"].append,
        on_stale=seen["stale"].append,
        now_ns=fake_time,
    )
    esvs, other = Bus(MemTransport(hub), 20, keyring, clock), Bus(MemTransport(hub), 21, keyring, clock)
    yield Rig(esvs, other, client, fake_time, clock, seen)
    for bus in (esvs, other, client_bus):
        bus.close()


def test_reports_arrive_typed_with_their_frame_time(rig: Rig) -> None:
    rig.report()
    rig.client.poll()
    (obstacles,) = rig.seen["obstacles"]
    (lanes,) = rig.seen["lanes"]
    assert isinstance(obstacles, ObstacleReport) and isinstance(lanes, LaneReport)
    assert obstacles.obstacles == (ROCK,) and lanes.borders == (EDGE,)
    assert obstacles.frame_time_ns == rig.clock.t_ns - 150 and obstacles.source_id == 20
    assert obstacles.age_ns == obstacles.received_ns - obstacles.frame_time_ns
    assert rig.client.last_obstacles == obstacles and rig.client.obstacle_reports == 1
    assert rig.client.gaps == 0


def test_sequence_gaps_count_the_reports_lost_on_the_way(rig: Rig) -> None:
    rig.report()
    rig.report(skip=2)
    rig.report()
    rig.client.poll()
    assert rig.client.obstacle_reports == 3
    assert rig.client.gaps == 2


def test_silence_for_n_rounds_is_stale_until_reports_resume(rig: Rig) -> None:
    rig.report()
    rig.client.poll()
    rig.time.advance(0.29)
    rig.client.poll()
    assert not rig.client.stale and rig.seen["stale"] == []
    rig.time.advance(0.02)  # 3 rounds of 100 ms without a report
    rig.client.poll()
    rig.client.poll()
    assert rig.client.stale and rig.seen["stale"] == [True]
    rig.report()
    rig.client.poll()
    assert not rig.client.stale and rig.seen["stale"] == [True, False]
    assert rig.client.stale_events == 1


def test_the_round_period_comes_from_the_esvs_status(rig: Rig) -> None:
    status = ModuleStatus("esvs", 1, 3.0, 50_000_000, 1000, 0, 0, 0, (), 1, 0, 0, "monolithic")
    rig.esvs.publish(channels.MODULE_STATUS, status)
    rig.other.publish(channels.MODULE_STATUS, status._replace(module="lidar_h_left", loop_period_ns=40_000_000))
    rig.client.poll()
    assert rig.seen["status"] == [status] and rig.client.status == status
    assert rig.client.stale_after_s == pytest.approx(0.15)


def test_only_the_chosen_esvs_is_heard(rig: Rig) -> None:
    rig.report(bus=rig.other)  # another device on the same channels
    rig.other.publish(channels.HEALTH, HealthEvent("esvs", int(Severity.WARNING), "worker_restart", "x"))
    rig.esvs.publish(channels.HEALTH, HealthEvent("esvs", int(Severity.INFO), "config", "y"))
    rig.esvs.publish(channels.HEALTH, HealthEvent("sim", int(Severity.INFO), "collision", "z"))
    rig.client.poll()
    assert rig.seen["obstacles"] == [] and rig.seen["lanes"] == []
    assert [event.code for event in rig.seen["health"]] == ["config"]


def test_vehicle_state_and_configuration_go_to_the_esvs(rig: Rig) -> None:
    heard: dict[str, list] = {channels.VEHICLE_STATE: [], channels.CONFIG: []}
    for channel, messages in heard.items():
        rig.esvs.subscribe(channel, lambda message, envelope, m=messages: m.append((message, envelope)))
    state = VehicleState(1.0, 2.0, 0.0, 0.5, 4.0, 3.5, 1.9, 0.0, tuple([0.0] * 25), int(NavQuality.DGPS))
    rig.client.send_vehicle_state(state, t_meas_ns=123)
    rig.client.configure("round_period_s", 0.05)
    rig.client.configure("allow_fault_injection", True)
    rig.esvs.poll()
    ((sent, envelope),) = heard[channels.VEHICLE_STATE]
    assert sent == state and envelope.t_meas_ns == 123
    assert [message for message, _envelope in heard[channels.CONFIG]] == [
        ConfigUpdate("esvs", "round_period_s", "0.05"),
        ConfigUpdate("esvs", "allow_fault_injection", "true"),
    ]


def test_bad_arguments_are_refused(rig: Rig) -> None:
    with pytest.raises(ValueError, match="positive"):
        EsvsClient(rig.other, stale_rounds=0)
