"""rascal view: the state it draws, the hub that only ever sends the latest frame, the HTTP/SSE
server over a real socket, the viewer process on a real bus, and the replay of a recording."""

from __future__ import annotations

import base64
import contextlib
import http.client
import json
import math
import select
import socket
import subprocess
import sys
import threading
import time
import urllib.request
import uuid
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from brain.corridor import Course
from brain.rddf import Waypoint
from protocol import channels
from protocol.auth import load_keyring
from protocol.messages import (
    Frame,
    HealthEvent,
    LaneBorder,
    LaneBorders,
    MapSnapshot,
    ModuleStatus,
    Obstacle,
    ObstacleList,
    PathPoint,
    Sensor,
    VehicleState,
)
from protocol.messages import (
    Path as PlannedPath,
)
from rascal.recording import RecordingWriter
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from rascal.view.guard import Access
from rascal.view.server import FrameHub, ViewServer
from rascal.view.state import MAX_NAMES, ViewState
from tests.conftest import ROOT

T0 = 1_700_000_000_000_000_000
MS = 1_000_000


def vehicle(east: float, north: float, yaw: float) -> VehicleState:
    return VehicleState(east, north, 0.0, yaw, 2.0, 0.0, 0.0, 0.0, (0.0,) * 25, 3)


def status(name: str, restarts: int = 0, stale: tuple[str, ...] = ()) -> ModuleStatus:
    return ModuleStatus(name, 1, 12.0, 10_000_000, 200_000, 0, restarts, 3, stale, 2, 0, 0, "fine")


def snapshot(rows: int = 3, cols: int = 4) -> MapSnapshot:
    return MapSnapshot(10.0, -5.0, 0.5, rows, cols, zlib.compress(bytes(range(rows * cols))))


def short_course() -> Course:
    return Course([Waypoint(1, 34.865, -116.89, 40.0, 25.0), Waypoint(2, 34.865, -116.888, 30.0, 25.0)])


# -- the state ----------------------------------------------------------------------------------


def test_vehicle_frame_obstacles_are_placed_with_the_pose_of_their_measurement_time() -> None:
    state = ViewState()
    state.handle(channels.VEHICLE_STATE, vehicle(0.0, 0.0, 0.0), T0, T0)
    state.handle(channels.VEHICLE_STATE, vehicle(100.0, 0.0, math.pi / 2), T0 + 100 * MS, T0 + 100 * MS)
    # Measured at T0 (the first pose), 10 m ahead and 2 m left: at (10, 2) whatever came later.
    lidar = ObstacleList(int(Sensor.LIDAR_H_LEFT), int(Frame.VEHICLE), (Obstacle(10.0, 2.0, 1, 0.5, 1, 0.0, 1, 10),))
    state.handle(channels.OBSTACLES_LIDAR, lidar, T0 + 10 * MS, T0 + 120 * MS)
    # Measured at the second pose: facing north, 10 m ahead is north.
    esvs = ObstacleList(int(Sensor.ESVS), int(Frame.VEHICLE), (Obstacle(10.0, 0.0, 1, 1, 1, 0.0, 1, 10),))
    state.handle(channels.OBSTACLES_ESVS, esvs, T0 + 100 * MS, T0 + 130 * MS)
    enu = ObstacleList(int(Sensor.SYNTHETIC), int(Frame.ENU), (Obstacle(-3.0, 4.0, 1, 1, 1, 0.3, 1, 5),))
    state.handle(channels.OBSTACLES_BEACON, enu, T0 + 100 * MS, T0 + 130 * MS)
    scene = state.scene_view()
    (left,) = scene["obstacles"]["lidar_h_left"]
    (stereo,) = scene["obstacles"]["esvs"]
    (beacon,) = scene["obstacles"]["synthetic"]
    assert (left["e"], left["n"], left["yaw"]) == (10.0, 2.0, 0.0)
    assert (stereo["e"], stereo["n"]) == pytest.approx((100.0, 10.0))
    assert stereo["yaw"] == pytest.approx(math.pi / 2, abs=1e-3)
    assert (beacon["e"], beacon["n"], beacon["yaw"]) == (-3.0, 4.0, 0.3)
    assert scene["vehicle"]["e"] == 100.0
    # A sensor silent for over a second has its obstacles taken off.
    state.handle(channels.VEHICLE_STATE, vehicle(101.0, 0.0, 0.0), T0 + 1500 * MS, T0 + 1500 * MS)
    assert state.scene_view()["obstacles"] == {}


def test_lane_borders_trail_and_path_are_in_enu() -> None:
    state = ViewState()
    state.handle(channels.VEHICLE_STATE, vehicle(5.0, 5.0, math.pi), T0, T0)
    border = LaneBorder(1, 2.0, 0.0, 0.0, 0.0, 11.0, 0.9)
    state.handle(channels.LANE_BORDERS, LaneBorders(int(Sensor.ESVS), (border,)), T0, T0)
    (line,) = state.scene_view()["lanes"]["esvs"]
    assert line[0] == pytest.approx([5.0, 3.0]) and line[-1] == pytest.approx([-6.0, 3.0])  # facing west, left is south
    for i in range(20):
        state.handle(channels.VEHICLE_STATE, vehicle(5.0 + i * 0.1, 5.0, 0.0), T0 + (i + 1) * MS, T0 + (i + 1) * MS)
    assert len(state.trail_view()) == 4  # one point per half metre driven
    state.handle(channels.PATH, PlannedPath(3, (PathPoint(1.0, 2.0, 3.0), PathPoint(4.0, 5.0, 3.0)), True), T0, T0)
    assert state.scene_view()["path"] == [[1.0, 2.0], [4.0, 5.0]] and state.scene_view()["slow"] is True


def test_bad_input_is_counted_not_drawn() -> None:
    state = ViewState()
    lidar = ObstacleList(int(Sensor.LIDAR_H_LEFT), int(Frame.VEHICLE), (Obstacle(1, 1, 1, 1, 1, 0, 1, 1),))
    state.handle(channels.OBSTACLES_LIDAR, lidar, T0, T0)  # no pose yet
    state.handle(channels.VEHICLE_STATE, vehicle(math.nan, 0.0, 0.0), T0, T0)
    state.handle(channels.MAP_SNAPSHOT, MapSnapshot(0.0, 0.0, 0.5, 4, 4, b"not zlib"), T0, T0)
    state.handle(channels.MAP_SNAPSHOT, MapSnapshot(0.0, 0.0, 0.5, 4, 4, zlib.compress(bytes(15))), T0, T0)
    state.handle(channels.VEHICLE_STATE, vehicle(1.0, 1.0, 0.0), T0 + MS, T0 + MS)
    state.handle(channels.VEHICLE_STATE, vehicle(9.0, 9.0, 0.0), T0, T0 + 2 * MS)  # late: the newer one stays
    huge = ObstacleList(int(Sensor.ESVS), int(Frame.VEHICLE), (Obstacle(math.inf, 0, 1, 1, 1, 0, 1, 1),))
    state.handle(channels.OBSTACLES_ESVS, huge, T0 + MS, T0 + MS)
    assert state.map_view() is None and state.scene_view()["vehicle"]["e"] == 1.0
    assert state.scene_view()["obstacles"] == {"esvs": []}
    for i in range(MAX_NAMES + 5):  # a key holder inventing module names cannot grow the books without bound
        state.handle(channels.MODULE_STATUS, status(f"m{i}"), T0, T0 + 2 * MS)
    assert len(state.modules) == MAX_NAMES and state.bad.pop("too_many_names") == 5
    late = ObstacleList(int(Sensor.ESVS), int(Frame.VEHICLE), (Obstacle(1, 1, 1, 1, 1, 0, 1, 1),))
    state.handle(channels.OBSTACLES_ESVS, late, T0 + 2000 * MS, T0 + 2000 * MS)  # navigation silent since T0 + 1 ms
    assert state.bad.pop("obstacles_without_a_pose_at_their_time") == 2
    assert state.bad == {"vehicle_state_not_finite": 1, "map_snapshot_undecodable": 2}
    json.dumps(state.scene_view(), allow_nan=False)
    json.dumps(state.health_view({}), allow_nan=False)


def test_health_lists_modules_rates_events_restarts_and_rejects() -> None:
    state = ViewState(short_course())
    state.handle(channels.MODULE_STATUS, status("brain", stale=("VEHICLE_STATE",)), T0, T0)
    state.handle(channels.MODULE_STATUS, status("sim"), T0, T0 + 50 * MS)
    event = HealthEvent("supervisor", 2, "module_restart", "brain exited with signal SIGKILL; restarting")
    state.handle(channels.HEALTH, event, T0, T0 + 100 * MS)
    for i in range(21):
        state.count(channels.IMU, T0 - 100 * MS + i * 10 * MS)
    health = state.health_view({"bad_tag": 2})
    brain, sim = health["modules"]
    assert brain["name"] == "brain" and brain["restarts"] == 1 and brain["stale"] == ["VEHICLE_STATE"]
    assert brain["age_s"] == 0.1 and brain["loop_hz"] == 100.0 and brain["rx_rejected"] == 3
    assert sim["restarts"] == 0
    assert health["rates_hz"]["IMU"] == pytest.approx(100.0)
    assert health["events"][0]["code"] == "module_restart" and health["events"][0]["severity"] == "ERROR"
    assert health["rejected"] == {"bad_tag": 2}
    course = state.course_view()
    assert course["waypoints"][0] == [0.0, 0.0] and course["waypoints"][1][0] == pytest.approx(182.8, abs=0.5)
    assert course["half_widths_m"] == [12.19]


# -- the hub and the server ---------------------------------------------------------------------


def test_a_slow_client_gets_only_the_latest_version_of_each_topic() -> None:
    hub = FrameHub()
    seen: dict[str, int] = {}
    for i in range(100):
        hub.publish("scene", {"i": i})
    hub.publish("map", {"seq": 1})
    fresh = dict(hub.wait_newer(seen, 1.0) or [])
    assert json.loads(fresh["scene"]) == {"i": 99} and json.loads(fresh["map"]) == {"seq": 1}
    assert hub.wait_newer(seen, 0.05) == []  # nothing new: nothing queued behind
    hub.publish("scene", {"i": 100})
    assert [topic for topic, _ in hub.wait_newer(seen, 1.0) or []] == ["scene"]
    with pytest.raises(ValueError):
        hub.publish("scene", {"x": math.nan})
    done: list[Any] = []
    waiter = threading.Thread(target=lambda: done.append(hub.wait_newer(seen, 10.0)))
    waiter.start()
    hub.close()
    waiter.join(timeout=5)
    assert done == [None]


def read_events(url: str, wanted: int, events: list[tuple[str, Any]] | None = None) -> list[tuple[str, Any]]:
    """The first ``wanted`` server-sent events, appended to ``events`` as they come."""
    events = [] if events is None else events
    with urllib.request.urlopen(url + "events", timeout=10) as stream:
        name = ""
        for raw in stream:
            line = raw.decode().rstrip("\n")
            if line.startswith("event: "):
                name = line[7:]
            elif line.startswith("data: "):
                events.append((name, json.loads(line[6:])))
                if len(events) >= wanted:
                    break
    return events


def test_the_server_streams_events_and_serves_the_page() -> None:
    hub = FrameHub()
    server = ViewServer(hub, "127.0.0.1", 0)
    server.start()
    try:
        hub.publish("course", {"waypoints": []})
        hub.publish("scene", {"t": 1})
        got: list[tuple[str, Any]] = []
        reader = threading.Thread(target=read_events, args=(server.url, 3, got))
        reader.start()
        deadline = time.monotonic() + 10
        while len(got) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)  # the client has what there was: now something new
        hub.publish("scene", {"t": 2})
        reader.join(timeout=10)
        assert got == [("course", {"waypoints": []}), ("scene", {"t": 1}), ("scene", {"t": 2})]
        page = urllib.request.urlopen(server.url, timeout=5).read().decode()
        script = urllib.request.urlopen(server.url + "view.js", timeout=5).read().decode()
        assert '<canvas id="map">' in page and "requestAnimationFrame" in script
        state = json.loads(urllib.request.urlopen(server.url + "state.json", timeout=5).read())
        assert state["scene"] == {"t": 2} and state["map"] is None
        with pytest.raises(urllib.error.HTTPError) as missing:
            urllib.request.urlopen(server.url + "../../etc/passwd", timeout=5)
        assert missing.value.code == 404
    finally:
        server.close()


def test_a_client_that_stops_reading_holds_up_neither_the_publisher_nor_other_clients() -> None:
    hub = FrameHub()
    server = ViewServer(hub, "127.0.0.1", 0)
    server.start()
    host, port = server.httpd.server_address[:2]
    stuck = socket.create_connection((host, port), timeout=5)
    stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        stuck.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")  # ...and never reads a byte
        big = "x" * 100_000
        for i in range(300):  # 30 MB offered: far beyond any socket buffer
            hub.publish("map", {"seq": i, "cells": big})
            if i % 50 == 0:
                time.sleep(0.02)  # let the stuck client's thread fill its socket
        got: list[tuple[str, Any]] = []
        reader = threading.Thread(target=lambda: got.extend(read_events(server.url, 1)))
        reader.start()
        reader.join(timeout=10)
        assert [(name, value["seq"]) for name, value in got] == [("map", 299)]  # the newest, nothing queued
    finally:
        stuck.close()
        server.close()


def get(port: int, path: str, *hosts: str) -> tuple[int, bytes]:
    """One GET over a fresh loopback connection with these Host headers: (status, body)."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    try:
        conn.putrequest("GET", path, skip_host=True)
        for host in hosts:
            conn.putheader("Host", host)
        conn.endheaders()
        response = conn.getresponse()
        return response.status, response.read()
    finally:
        conn.close()


def served(port: int, timeout_s: float, between: Callable[[], object] = lambda: None) -> bool:
    """Whether /state.json is served within ``timeout_s``, calling ``between`` before each try
    (a connection over the cap is closed at once: tried again)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        between()
        with contextlib.suppress(ConnectionError):
            if get(port, "/state.json", "127.0.0.1")[0] == 200:
                return True
        time.sleep(0.05)
    return False


def test_a_request_naming_another_host_gets_no_state(capsys: pytest.CaptureFixture[str]) -> None:
    """DNS rebinding: a page on evil.example points its name at 127.0.0.1 and reads /state.json as
    its own. Its requests say Host: evil.example; IP literals, localhost and listed names pass."""
    hub = FrameHub()
    hub.publish("scene", {"secret": 1})
    server = ViewServer(hub, "127.0.0.1", 0, Access.of("127.0.0.1", ["viewer.lan"]))
    server.start()
    port = server.httpd.server_address[1]
    try:
        refused = ["evil.example", f"evil.example:{port}", "localhost.evil.example", "127.0.0.1.evil.example", "",
                   "127.0.0.1@evil.example", f"127.0.0.1:{port}/x", "[::1"]  # fmt: skip
        for host in refused:
            status, body = get(port, "/state.json", host)
            assert (status, body) == (403, b"Host not allowed (see --allow-host)\n"), host
        assert get(port, "/state.json", "127.0.0.1", "evil.example")[0] == 403  # two Hosts: refused
        assert get(port, "/state.json")[0] == 403  # none
        for host in [f"127.0.0.1:{port}", f"LocalHost:{port}", "localhost", "[::1]:9000", "127.0.0.2", "viewer.lan:1"]:
            status, body = get(port, "/state.json", host)
            assert status == 200 and json.loads(body)["scene"] == {"secret": 1}, host
        assert server.refusals.counts == {"host": len(refused) + 2}
    finally:
        server.close()
    assert capsys.readouterr().err.count("refused") == 1  # logged once, then counted


def test_connections_over_the_cap_are_closed_at_once_and_start_no_thread() -> None:
    cap, extra = 4, 6
    server = ViewServer(FrameHub(), "127.0.0.1", 0, max_connections=cap, timeout_s=10.0)
    server.start()
    address = server.httpd.server_address[:2]
    before = threading.active_count()
    clients = [socket.create_connection(address, timeout=5) for _ in range(cap + extra)]
    closed: set[socket.socket] = set()
    try:
        deadline = time.monotonic() + 10
        while len(closed) < extra and time.monotonic() < deadline:
            readable, _, _ = select.select([c for c in clients if c not in closed], [], [], 0.1)
            closed.update(c for c in readable if c.recv(1) == b"")
        assert len(closed) == extra and closed.isdisjoint(clients[:cap])  # the first ones hold the slots
        assert threading.active_count() - before <= cap
        assert server.refusals.counts == {"busy": extra}
        for client in clients:
            client.close()
        assert served(address[1], 5.0)  # the held slots are freed as their clients go
    finally:
        for client in clients:
            client.close()
        server.close()


def test_a_stalled_client_is_dropped_after_the_timeout() -> None:
    """Slowloris: a request head that never ends, or nothing at all, holds a thread only ``timeout_s``."""
    server = ViewServer(FrameHub(), "127.0.0.1", 0, timeout_s=0.5)
    server.start()
    address = server.httpd.server_address[:2]
    try:
        for opening in (b"", b"GET /state.json HTTP/1.1\r\nHost: 127.0.0.1\r\n"):
            with socket.create_connection(address, timeout=5) as client:
                client.sendall(opening)
                started = time.monotonic()
                assert client.recv(1024) == b""  # closed by the server, before our own 5 s timeout
                assert 0.4 < time.monotonic() - started < 3.0
    finally:
        server.close()


def test_an_event_stream_that_stops_reading_frees_its_slot_after_the_timeout() -> None:
    hub = FrameHub()
    server = ViewServer(hub, "127.0.0.1", 0, max_connections=1, timeout_s=0.5)
    server.start()
    address = server.httpd.server_address[:2]
    stuck = socket.create_connection(address, timeout=5)
    stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        stuck.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")  # ...and never reads a byte
        big = "x" * 100_000
        # New frames until the stuck stream's send stalls for the timeout and its thread ends.
        assert served(address[1], 20.0, lambda: hub.publish("map", {"cells": big}))
        assert server.refusals.counts["busy"] >= 1  # it did hold the only slot meanwhile
    finally:
        stuck.close()
        server.close()


# -- the viewer process and replay ----------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def fetch_state(url: str, done: Any, timeout_s: float, child: subprocess.Popen[bytes], log: Path) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    state: dict[str, Any] = {}
    while time.monotonic() < deadline:
        assert child.poll() is None, log.read_text()
        try:
            state = json.loads(urllib.request.urlopen(url + "state.json", timeout=2).read())
        except OSError:
            state = {}
        try:
            if state and done(state):
                return state
        except (KeyError, TypeError):
            pass  # a topic not published yet (null)
        time.sleep(0.2)
    raise AssertionError(f"no such state in {timeout_s} s: {json.dumps(state)[:1500]}\n{log.read_text()[-2000:]}")


def publish_drive(bus: Bus, steps: int, step_s: float) -> None:
    bus.publish(channels.MAP_SNAPSHOT, snapshot())
    for i in range(steps):
        bus.publish(channels.VEHICLE_STATE, vehicle(i * 0.5, 0.0, 0.0))
        bus.publish(channels.MODULE_STATUS, status("sim"))
        lidar = ObstacleList(int(Sensor.LIDAR_H_LEFT), int(Frame.VEHICLE), (Obstacle(8.0, 0.0, 1, 1, 1, 0.0, 1, 8),))
        bus.publish(channels.OBSTACLES_LIDAR, lidar)
        bus.publish(
            channels.PATH, PlannedPath(i, (PathPoint(i * 0.5, 0.0, 2.0), PathPoint(i * 0.5 + 5, 0.0, 2.0)), False)
        )
        bus.poll(step_s)


def start(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, *args], cwd=ROOT, stdout=log.open("wb"), stderr=subprocess.STDOUT)


def stop(child: subprocess.Popen[bytes]) -> None:
    child.terminate()
    try:
        child.wait(timeout=10)
    except subprocess.TimeoutExpired:
        child.kill()
        child.wait()


def test_the_viewer_process_shows_the_live_bus(bus_url: str, key_file: Path, tmp_path: Path) -> None:
    port = free_port()
    log = tmp_path / "viewer.log"
    child = start(["-m", "rascal.view", "--set", f"port={port}", "--set", "course="], log)
    url = f"http://127.0.0.1:{port}/"
    bus = Bus.open(bus_url, source_id=77, clock=MasterClock(), keyring=load_keyring(key_file))
    try:
        fetch_state(url, lambda s: s["health"] is not None, 60.0, child, log)  # the viewer is up
        publish_drive(bus, 20, 0.02)
        bus.transport.send(channels.VEHICLE_STATE, b"\x00" * 40)  # garbage: counted by the viewer, not drawn

        def drawn(s: dict[str, Any]) -> bool:
            names = [m["name"] for m in s["health"]["modules"]]
            last = s["scene"]["vehicle"] is not None and s["scene"]["vehicle"]["e"] == 9.5
            return last and s["map"] is not None and "sim" in names

        state = fetch_state(url, drawn, 10.0, child, log)
        assert zlib.decompress(base64.b64decode(state["map"]["zlib_b64"])) == bytes(range(12))
        (boxes,) = state["scene"]["obstacles"].values()
        assert boxes[0]["e"] == 17.5  # 8 m ahead of the vehicle at 9.5 m
        assert state["scene"]["path"] == [[9.5, 0.0], [14.5, 0.0]]
        assert {m["name"] for m in state["health"]["modules"]} >= {"sim", "viewer"}
        assert state["course"] == {"waypoints": [], "half_widths_m": [], "source": "live"}
        state = fetch_state(url, lambda s: sum(s["health"]["rejected"].values()) >= 1, 5.0, child, log)
        assert state["health"]["rates_hz"]["VEHICLE_STATE"] > 0
    finally:
        bus.close()
        stop(child)
    assert child.returncode == 0, log.read_text()


def recording(path: Path, key_file: Path, messages: list[tuple[str, Any]], end_info: dict[str, str]) -> Path:
    """A recording of ``messages`` (channel, message) sent 10 ms apart over an in-process bus."""
    hub = f"mem://view-{uuid.uuid4().hex}"
    keyring = load_keyring(key_file)
    sender = Bus.open(hub, source_id=50, clock=MasterClock(), keyring=keyring)
    recorder = Bus.open(hub, source_id=51, clock=MasterClock(), keyring=keyring)
    writer = RecordingWriter(path, {"test": "rascal view"})
    recorder.subscribe_raw(writer.write)
    for channel, message in messages:
        sender.publish(channel, message)
        recorder.poll(0.0)
        time.sleep(0.01)
    writer.close(end_info)
    return writer.path


def test_rascal_view_replays_a_recording(tmp_path: Path, key_file: Path) -> None:
    drive: list[tuple[str, Any]] = [(channels.VEHICLE_STATE, vehicle(i * 1.0, 2.0, 0.0)) for i in range(30)]
    drive[10:10] = [(channels.MAP_SNAPSHOT, snapshot()), (channels.MODULE_STATUS, status("brain"))]
    path = recording(tmp_path / "run.mcap", key_file, drive, {"rejected/77/bad_tag": "4"})
    log = tmp_path / "view.log"
    port = free_port()
    child = start(["-m", "rascal.cli", "view", str(path), "--port", str(port), "--speed", "2"], log)
    try:
        url = f"http://127.0.0.1:{port}/"
        state = fetch_state(url, lambda s: s["health"]["rejected"] == {"bad_tag": 4}, 60.0, child, log)
        assert state["scene"]["vehicle"]["e"] == 29.0 and state["map"]["cols"] == 4
        assert [m["name"] for m in state["health"]["modules"]] == ["brain"]
        assert len(state["trail"]) == 30
        assert state["course"]["waypoints"]  # the default deployment's course
        assert state["course"]["source"] == "replaying run.mcap"
    finally:
        stop(child)
    assert "end of" in log.read_text()
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file at all")
    result = subprocess.run(
        [sys.executable, "-m", "rascal.cli", "view", str(bad), "--port", "0"], cwd=ROOT, capture_output=True, text=True
    )
    assert result.returncode == 2 and "bad.mcap" in result.stderr


def test_a_port_already_taken_is_a_clear_error(tmp_path: Path, key_file: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        path = recording(tmp_path / "run.mcap", key_file, [(channels.VEHICLE_STATE, vehicle(0.0, 0.0, 0.0))], {})
        for args in ([], [str(path)]):  # live, and replaying
            command = [sys.executable, "-m", "rascal.cli", "view", *args, "--port", str(port), "--duration", "5"]
            result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=120)
            assert result.returncode in (1, 2) and f"cannot serve the view on 127.0.0.1:{port}" in result.stderr
            assert "Traceback" not in result.stderr


def test_a_course_that_cannot_be_read_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "bad.rddf").write_text("not a route\n")
    for course in (tmp_path / "missing.rddf", tmp_path / "bad.rddf"):
        command = [sys.executable, "-m", "rascal.cli", "view", "--course", str(course), "--duration", "5"]
        result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert result.returncode == 1 and f"viewer: course {course}" in result.stderr
        assert "Traceback" not in result.stderr
