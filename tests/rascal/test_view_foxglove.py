"""rascal view --foxglove: a client speaking Foxglove's WebSocket protocol connects to the viewer
process, sees the channels advertised with their Foxglove JSON schemas (the recordings' own,
rascal/foxglove_schemas.py), subscribes, and receives each, valid by its schema (the map's cells
inside the Grid). And the recordings' JSON channels are in Foxglove's terms."""

from __future__ import annotations

import base64
import json
import socket
import struct
import time
import zlib
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from brain.course_config import DEFAULT_COURSE
from protocol import channels
from protocol.auth import load_keyring
from rascal.record_schema import JSON_ENCODING, JSON_SCHEMA_ENCODING
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from tests.rascal.test_recording import validate
from tests.rascal.test_view import free_port, publish_drive, recording, snapshot, start, stop, vehicle

websocket = pytest.importorskip("websocket", reason="websocket-client (a dev dependency) is not installed")
pytest.importorskip("foxglove", reason="foxglove-sdk (the optional 'foxglove' extra) is not installed")

from rascal.view.foxglove_bridge import TOPICS, FoxgloveBridge  # noqa: E402  (needs foxglove-sdk)

MESSAGE_DATA_OPCODE = 1


def test_a_foxglove_client_receives_map_scene_path_and_vehicle(bus_url: str, key_file: Path, tmp_path: Path) -> None:
    port, fox_port = free_port(), free_port()
    log = tmp_path / "viewer.log"
    command = ["-m", "rascal.cli", "view", "--port", str(port), "--foxglove", "--foxglove-port", str(fox_port)]
    child = start([*command, "--course", str(DEFAULT_COURSE)], log)
    bus = Bus.open(bus_url, source_id=78, clock=MasterClock(), keyring=load_keyring(key_file))
    client = None
    try:
        deadline = time.monotonic() + 60
        while client is None:
            assert child.poll() is None and time.monotonic() < deadline, log.read_text()
            try:
                client = websocket.create_connection(
                    f"ws://127.0.0.1:{fox_port}", subprotocols=["foxglove.sdk.v1"], timeout=5, suppress_origin=True
                )
            except OSError:
                time.sleep(0.3)
        advertised: dict[int, dict[str, str]] = {}
        while len(advertised) < len(TOPICS):
            message = json.loads(client.recv())
            if message["op"] == "advertise":
                advertised.update({channel["id"]: channel for channel in message["channels"]})
        assert {c["topic"]: c["schemaName"] for c in advertised.values()} == TOPICS
        assert {(c["encoding"], c["schemaEncoding"]) for c in advertised.values()} == {("json", "jsonschema")}
        topic_of = dict(enumerate((c["topic"] for c in advertised.values()), start=1))
        subscriptions = [{"id": i, "channelId": cid} for i, cid in enumerate(advertised, start=1)]
        client.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
        received: dict[str, bytes] = {}
        client.settimeout(0.05)
        deadline = time.monotonic() + 30
        while set(received) != set(TOPICS) and time.monotonic() < deadline:
            bus.publish(channels.MAP_SNAPSHOT, snapshot())  # every frame: one lands after the subscription
            publish_drive(bus, 3, 0.02)
            try:
                frame = client.recv()
            except websocket.WebSocketTimeoutException:
                continue
            if isinstance(frame, bytes) and frame[0] == MESSAGE_DATA_OPCODE:
                (subscription,) = struct.unpack_from("<I", frame, 1)
                received[topic_of[subscription]] = frame[13:]  # opcode, subscription id, log time
        assert set(received) == set(TOPICS), (sorted(received), log.read_text()[-2000:])
        schemas = {c["topic"]: json.loads(c["schema"]) for c in advertised.values()}
        for topic, data in received.items():
            validate(json.loads(data), schemas[topic], topic)
        grid = json.loads(received["/rascal/map"])
        assert base64.b64decode(grid["data"]) == zlib.decompress(snapshot().cells)  # the cells, as Grid data
        assert b"vehicle" in received["/tf"] and b"lidar_h_left" in received["/rascal/obstacles"]
    finally:
        if client is not None:
            client.close()
        bus.close()
        stop(child)
    assert child.returncode == 0, log.read_text()


def test_the_foxglove_socket_refuses_other_sites_and_relays_the_rest() -> None:
    """Any web page may open a WebSocket to loopback: the guard in front of foxglove-sdk's server
    (which checks nothing, and listens at an unguessable loopback address) checks Host and Origin."""
    bridge = FoxgloveBridge("127.0.0.1", 0)
    url = f"ws://127.0.0.1:{bridge.guard.port}"
    refused: list[dict[str, Any]] = [
        {"origin": "https://evil.example"},
        {"origin": "null"},  # a sandboxed frame of any site
        {"host": "evil.example", "suppress_origin": True},  # DNS rebinding
    ]
    accepted: list[dict[str, Any]] = [
        {"suppress_origin": True},  # not a browser
        {"origin": "https://app.foxglove.dev"},
        {"origin": f"http://localhost:{bridge.guard.port}", "host": "localhost"},
    ]
    try:
        assert bridge.url == url
        with pytest.raises(ConnectionRefusedError):  # foxglove-sdk's own port is not on 127.0.0.1
            socket.create_connection(("127.0.0.1", bridge.server.port), timeout=5).close()
        for options in refused:
            with pytest.raises(websocket.WebSocketBadStatusException) as refusal:
                websocket.create_connection(url, subprotocols=["foxglove.sdk.v1"], timeout=5, **options)
            assert refusal.value.status_code == 403, options
        for options in accepted:
            client = websocket.create_connection(url, subprotocols=["foxglove.sdk.v1"], timeout=5, **options)
            try:
                assert json.loads(client.recv())["op"] == "serverInfo", options
            finally:
                client.close()
        assert bridge.guard.refusals.counts == {"origin": 2, "host": 1}
    finally:
        bridge.close()


def test_recorded_json_channels_are_what_foxglove_opens(tmp_path: Path, key_file: Path) -> None:
    """Foxglove decodes a channel with message encoding ``json`` by the ``jsonschema`` schema
    registered with it; both must be set on every non-raw channel, and the schema must be a JSON
    object schema naming the message type."""
    messages = [(channels.VEHICLE_STATE, vehicle(1.0, 2.0, 0.5)), (channels.MAP_SNAPSHOT, snapshot())]
    path = recording(tmp_path / "run.mcap", key_file, messages, {})
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        json_channels = [c for c in summary.channels.values() if c.topic.endswith(".json")]
        assert {c.topic for c in json_channels} == {"VEHICLE_STATE.json", "MAP_SNAPSHOT.json"}
        for channel in json_channels:
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == JSON_ENCODING == "json"
            assert schema.encoding == JSON_SCHEMA_ENCODING == "jsonschema"
            document = json.loads(schema.data)
            assert document["type"] == "object" and schema.name.endswith(document["title"])
        for _schema, channel, message in reader.iter_messages(topics=["VEHICLE_STATE.json"]):
            assert json.loads(message.data)["yaw_rad"] == 0.5 and channel.topic == "VEHICLE_STATE.json"
