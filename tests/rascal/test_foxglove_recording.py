"""Foxglove-native recordings: the recorder, fed real encoded messages over the loopback bus,
writes foxglove-schema channels that the mcap reader decodes and their schemas accept; the
twins rewrite regenerates them; their rate is bounded; the shipped layout names what exists."""

from __future__ import annotations

import base64
import itertools
import json
import math
import subprocess
import sys
import typing
import zlib
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from brain.course_config import DEFAULT_COURSE, load_course
from protocol import channels
from protocol.auth import Keyring, load_keyring
from protocol.codec import Codec
from protocol.messages import (
    Frame,
    GpsFix,
    MapSnapshot,
    NavQuality,
    Obstacle,
    ObstacleList,
    PathPoint,
    Sensor,
    VehicleState,
)
from protocol.messages import Path as PlannedPath
from rascal import foxglove_schemas as fx
from rascal.record_foxglove import FoxgloveOptions
from rascal.record_schema import JSON_ENCODING, JSON_SCHEMA_ENCODING, RAW_ENCODING
from rascal.record_twins import add_json_twins
from rascal.recording import RecordingWriter, course_info
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from tests.conftest import ROOT
from tests.rascal.test_recording import _wait_for_recorder, validate

LAYOUT = ROOT / "deploy" / "foxglove" / "rascal_layout.json"
MS = 1_000_000
T0 = 1_700_000_000_000_000_000
CELLS = bytes(range(200)) * 3  # a 20 x 30 map


def drive(step: int) -> list[tuple[str, Any]]:
    """What the stack sends in 20 ms of a drive along the first leg of the course."""
    east, yaw = step * 0.2, 0.1
    messages: list[tuple[str, Any]] = [
        (
            channels.VEHICLE_STATE,
            VehicleState(east, 1.0, 0.0, yaw, 10.0, 10.0, 0.0, 0.0, (0.0,) * 25, int(NavQuality.DGPS)),
        )
    ]
    if step % 5 == 0:
        lidar = ObstacleList(
            int(Sensor.LIDAR_H_LEFT), int(Frame.VEHICLE), (Obstacle(12.0, 1.5, 1.0, 0.8, 1.0, 0.0, 0.9, 12.1),)
        )
        points = tuple(PathPoint(east + k, 1.0, 8.0) for k in range(20))
        fix = GpsFix(34.86 + step * 1e-6, -116.89, 700.0, 0.5, 0.5, 1.0, int(NavQuality.DGPS), 11)
        messages += [(channels.OBSTACLES_LIDAR, lidar), (channels.PATH, PlannedPath(step, points, False)),
                     (channels.GPS, fix)]  # fmt: skip
    if step % 25 == 0:
        messages.append((channels.MAP_SNAPSHOT, MapSnapshot(-5.0, -5.0, 0.5, 20, 30, zlib.compress(CELLS))))
    return messages


def read_all(path: Path) -> dict[str, list[tuple[int, dict[str, Any]]]]:
    """Every schema'd channel's messages (log time, decoded JSON), each checked against its schema."""
    topics: dict[str, list[tuple[int, dict[str, Any]]]] = {}
    with path.open("rb") as stream:
        for schema, channel, message in make_reader(stream).iter_messages():
            if channel.message_encoding == RAW_ENCODING:
                continue
            assert channel.message_encoding == JSON_ENCODING and schema is not None, channel.topic
            assert schema.encoding == JSON_SCHEMA_ENCODING, channel.topic
            document = json.loads(schema.data)
            if not channel.topic.endswith(".json"):
                assert schema.name == fx.TOPICS[channel.topic] == document["title"]
            value = json.loads(message.data)
            validate(value, document, channel.topic)
            topics.setdefault(channel.topic, []).append((message.log_time, value))
    return topics


def test_a_recorded_drive_has_valid_foxglove_channels(bus_url: str, key_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    log = tmp_path / "recorder.log"
    command = [sys.executable, "-m", "rascal.recording", "--out", str(out), "--set", f"course={DEFAULT_COURSE}"]
    recorder = subprocess.Popen(command, cwd=ROOT, stdout=log.open("wb"), stderr=subprocess.STDOUT)
    try:
        bus = Bus.open(bus_url, source_id=31, clock=MasterClock(), keyring=load_keyring(key_file))
        _wait_for_recorder(bus, recorder)
        for step in range(60):  # 1.2 s
            for channel, message in drive(step):
                bus.publish(channel, message)
            bus.poll(0.02)
        bus.close()
    finally:
        recorder.terminate()
        recorder.wait(timeout=10)
    assert recorder.returncode == 0, log.read_text()

    topics = read_all(out)
    assert set(fx.TOPICS) <= set(topics), sorted(topics)
    assert {"VEHICLE_STATE.json", "OBSTACLES_LIDAR.json", "GPS.json"} <= set(topics)
    _, transform = topics[fx.TF_TOPIC][-1]
    assert (transform["parent_frame_id"], transform["child_frame_id"]) == ("enu", "vehicle")
    assert 59 * 0.2 - 3.0 < transform["translation"]["x"] <= 59 * 0.2  # a pose of the last 0.1 s
    _, scene = topics[fx.OBSTACLES_TOPIC][-1]
    (lidar,) = scene["entities"]
    assert lidar["id"] == "lidar_h_left" and len(lidar["cubes"]) == 1
    cube = lidar["cubes"][0]["pose"]["position"]  # 12 m ahead of the pose of its measurement time
    assert math.isclose(cube["y"], 1.0 + 12.0 * math.sin(0.1) + 1.5 * math.cos(0.1), abs_tol=0.05)
    _, grid = topics[fx.MAP_TOPIC][0]
    assert base64.b64decode(grid["data"]) == CELLS and grid["column_count"] == 30
    _, fix = topics[fx.GPS_TOPIC][0]
    assert fix["latitude"] > 34.8 and fix["position_covariance"][0] == 0.25
    _, corridor = topics[fx.CORRIDOR_TOPIC][0]
    assert len(corridor["entities"][0]["lines"]) > 3
    assert len(topics[fx.PATH_TOPIC][-1][1]["entities"][0]["lines"][0]["points"]) == 20
    assert topics[fx.POSE_TOPIC][-1][1]["frame_id"] == "enu"
    assert topics["GPS.json"][0][1]["quality"] == "DGPS"  # the twins name enums


def _record(path: Path, steps: int, foxglove: FoxgloveOptions | None, json_channels: bool = True) -> Path:
    """``steps`` of :func:`drive`, 20 ms apart, signed and written without a network."""
    codec = Codec(Keyring.generate())
    course = course_info(str(DEFAULT_COURSE), "")
    writer = RecordingWriter(path, course, json_channels=json_channels, foxglove=foxglove)
    seq = 0
    for step in range(steps):
        t = T0 + step * 20 * MS
        for channel, message in drive(step):
            seq += 1
            data = codec.encode(channel.encode(), message, 31, seq, t - 5 * MS, t - MS)
            writer.write(codec.open(data), data, t)
    writer.close({})
    return writer.path


def _foxglove_only(topics: dict[str, list[tuple[int, dict[str, Any]]]]) -> dict[str, Any]:
    return {topic: messages for topic, messages in topics.items() if topic in fx.TOPICS}


def test_the_twins_rewrite_regenerates_the_same_foxglove_channels(tmp_path: Path) -> None:
    options = FoxgloveOptions(course=load_course(DEFAULT_COURSE))
    live = read_all(_record(tmp_path / "live.mcap", 150, options))
    # Raw only, as `rascal run`'s recorder writes it: the rewrite makes what a live tap would have.
    rewritten = _record(tmp_path / "raw.mcap", 150, None, json_channels=False)
    add_json_twins(rewritten)
    again = read_all(rewritten)
    assert _foxglove_only(again) == _foxglove_only(live) and fx.CORRIDOR_TOPIC in again
    assert set(again) == set(live)


def test_the_conversion_rate_is_bounded(tmp_path: Path) -> None:
    """3 s of a 50 Hz pose stream: the scene at 10 Hz, the 2 Hz map every 2 s, nothing without a tap."""
    topics = read_all(_record(tmp_path / "run.mcap", 150, FoxgloveOptions()))
    assert len(topics[fx.TF_TOPIC]) == 30 == len(topics[fx.POSE_TOPIC])
    assert len(topics[fx.MAP_TOPIC]) == 2
    times = [t for t, _ in topics[fx.TF_TOPIC]]
    assert min(b - a for a, b in itertools.pairwise(times)) >= 100 * MS
    assert fx.CORRIDOR_TOPIC not in topics  # no course given
    assert not _foxglove_only(read_all(_record(tmp_path / "off.mcap", 10, None)))


# -- the layout --------------------------------------------------------------------------------


def _plot_topic(path: str) -> tuple[str, str]:
    """``"VEHICLE_STATE.json".speed_mps`` -> (topic, field path): Foxglove quotes topics with dots."""
    assert path.startswith('"'), path
    topic, _, rest = path[1:].partition('"')
    return topic, rest.lstrip(".")


def test_the_layout_opens_the_recorded_topics() -> None:
    layout = json.loads(LAYOUT.read_text())
    panels = layout["configById"]
    kinds = {panel_id.split("!")[0] for panel_id in panels}
    assert {"3D", "map", "Plot"} <= kinds
    three_d = next(config for panel_id, config in panels.items() if panel_id.startswith("3D!"))
    assert set(three_d["topics"]) <= set(fx.TOPICS) and three_d["followTf"] == fx.VEHICLE_FRAME
    map_panel = next(config for panel_id, config in panels.items() if panel_id.startswith("map!"))
    assert map_panel["followTopic"] == fx.GPS_TOPIC
    plotted = [
        series["value"] for pid, config in panels.items() if pid.startswith("Plot!") for series in config["paths"]
    ]
    assert any("speed_mps" in value for value in plotted)
    for value in plotted:
        topic, field_path = _plot_topic(value)
        message_type = channels.CHANNEL_TYPES[topic.removesuffix(".json")]
        _resolve(message_type, field_path)
    referenced = json.dumps(layout["layout"])
    assert all(panel_id in referenced for panel_id in panels)


def _resolve(tp: Any, field_path: str) -> None:
    """Walk ``points[0].speed_mps`` through the message declaration: every name must exist."""
    for part in field_path.split("."):
        name = part.split("[")[0]
        hints = typing.get_type_hints(tp)
        assert name in hints, f"{tp.__name__} has no field {name}"
        tp = hints[name]
        if "[" in part:
            tp = typing.get_args(tp)[0]
