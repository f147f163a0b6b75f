"""EsvsClient against a real ESVS process on the signed loopback bus, the test standing in for
the camera by writing frames into the ring: reports, status, configuration both accepted and
refused, vehicle state, and staleness when the frames stop and recovery when they resume."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from esvs_client import EsvsClient, LaneReport, ObstacleReport
from modules.esvs.frames import RingWriter
from protocol.messages import HealthEvent, NavQuality, VehicleState
from tests.conftest import Processes
from tests.modules.esvs.framework.rings import HEIGHT, WIDTH, ring_name_fixture
from tests.modules.esvs.framework.workers import SCENE, scene_pair

pytestmark = pytest.mark.slow

STATE = VehicleState(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, tuple([0.0] * 25), int(NavQuality.DGPS))


@pytest.fixture
def ring_name() -> Iterator[str]:
    yield from ring_name_fixture()


class Camera:
    """Frames of the test scene at 15 Hz, stamped with the client's shared time, while on."""

    def __init__(self, writer: RingWriter, client: EsvsClient) -> None:
        self.writer, self.client = writer, client
        self.left, self.right = scene_pair()
        self.on = True
        self.next_s = 0.0

    def wait_until(self, done: Callable[[], bool], timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not done():
            now = time.monotonic()
            if now >= deadline:
                return False
            if self.on and now >= self.next_s:
                self.writer.write(self.left, self.right, self.client.bus.clock.now_ns())
                self.next_s = now + 1 / 15
            self.client.poll(0.005)
        return True


def test_client_hears_reports_status_and_staleness_of_a_real_esvs(
    bus_url: str, key_file: Path, processes: Processes, ring_name: str
) -> None:
    obstacles: list[ObstacleReport] = []
    lanes: list[LaneReport] = []
    health: list[HealthEvent] = []
    stale: list[bool] = []
    client = EsvsClient.open(
        bus_url,
        key_file=key_file,
        source_id=930,
        on_obstacles=obstacles.append,
        on_lanes=lanes.append,
        on_health=health.append,
        on_stale=stale.append,
    )
    writer = RingWriter(ring_name, HEIGHT, WIDTH)
    camera = Camera(writer, client)
    processes.module("time_service")
    esvs = processes.module("esvs", "--set", f"ring_name={ring_name}", "--set", "sched=none")
    try:
        assert camera.wait_until(lambda: len(obstacles) >= 5 and client.status is not None, 60.0), processes.log("esvs")
        assert all(len(report.obstacles) == len(SCENE.boxes) for report in obstacles)
        assert lanes and all(len(report.borders) == len(SCENE.stripes) for report in lanes)
        assert client.status is not None and client.status.loop_period_ns == 100_000_000
        assert obstacles[-1].frame_time_ns <= obstacles[-1].received_ns

        client.send_vehicle_state(STATE)
        client.configure("round_period_s", 0.05)
        client.configure("mode", "cambada")

        def answered() -> bool:
            return {"config", "config_rejected"} <= {event.code for event in health}

        assert camera.wait_until(answered, 10.0)
        assert camera.wait_until(lambda: client.status.loop_period_ns == 50_000_000, 5.0)  # type: ignore[union-attr]
        assert camera.wait_until(lambda: "vehicle state" in client.status.detail, 3.0)  # type: ignore[union-attr]
        assert "no vehicle state" not in client.status.detail  # type: ignore[union-attr]

        before = len(stale)  # the client went stale once already, waiting for the ESVS to start
        camera.on = False  # the camera stops: reports stop, the client says so
        assert camera.wait_until(lambda: client.stale, 5.0)
        camera.on = True
        assert camera.wait_until(lambda: not client.stale, 10.0)
        assert stale[before:] == [True, False]
        assert client.gaps == 0, "nothing is lost on loopback"
        assert esvs.poll() is None
    finally:
        client.close()
        writer.close()
