"""The recorder: a live bus session into MCAP, read back with the mcap library; JSON channels
that match their schemas; the sequence check; files cut short or already there."""

from __future__ import annotations

import base64
import json
import random
import re
import subprocess
import sys
import time
import typing
import uuid
from pathlib import Path
from typing import Any

import msgpack
from mcap.reader import make_reader

from protocol import channels
from protocol.auth import Keyring, load_keyring
from protocol.codec import HEADER, Codec, decode_body
from protocol.messages import (
    Frame,
    GpsFix,
    HealthEvent,
    ImuSample,
    MapSnapshot,
    ModuleStatus,
    NavQuality,
    Obstacle,
    ObstacleList,
    Sensor,
)
from protocol.schema import registered
from rascal.logread import END_METADATA, RUN_METADATA, Scan, check_sequences, iter_datagrams, read_metadata
from rascal.record_schema import ENUM_FIELDS, JSON_SCHEMA_ENCODING, RAW_ENCODING, json_converter, json_schema
from rascal.record_twins import add_json_twins
from rascal.recording import RECORDER_SOURCE_ID, RecordingWriter, bus_counts
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from tests.conftest import ROOT

T0_NS = 1_700_000_000_000_000_000


# -- helpers shared with test_logtools ----------------------------------------------------------


def sample(tp: Any, rng: random.Random) -> Any:
    """A valid value of any wire type, for round trips."""
    if tp is float:
        return rng.uniform(-100.0, 100.0)
    if tp is int:
        return rng.randint(-(2**40), 2**40)
    if tp is bool:
        return rng.random() < 0.5
    if tp is str:
        return rng.choice(["", "lidar", "ok ✓", 'quote "x"'])
    if tp is bytes:
        return rng.randbytes(rng.randint(0, 8))
    if typing.get_origin(tp) is tuple:
        (item, _ellipsis) = typing.get_args(tp)
        return tuple(sample(item, rng) for _ in range(rng.randint(0, 3)))
    hints = typing.get_type_hints(tp)
    return tp(*(sample(hints[name], rng) for name in tp._fields))


def make_recording(
    path: Path, messages: list[tuple[str, Any, int]], keyring: Keyring | None = None, source_id: int = 31
) -> list[bytes]:
    """A recording of ``(channel, msg, log_time_ns)`` made without a network: each message is
    signed as a publisher would (with ``keyring``, default a fresh key), and stamped as published
    1 ms before it was logged and measured 2 ms before that. Returns the signed bytes in order."""
    codec = Codec(keyring or Keyring.generate())
    writer = RecordingWriter(path, {"made_by": "test"})
    sent = []
    seqs: dict[str, int] = {}
    for channel, msg, log_ns in messages:
        seq = seqs[channel] = seqs.get(channel, 5_000_000_000) + 1
        data = codec.encode(channel.encode(), msg, source_id, seq, log_ns - 3_000_000, log_ns - 1_000_000)
        writer.write(codec.open(data), data, log_ns)
        sent.append(data)
    counts = {channel: sum(1 for c, _m, _t in messages if c == channel) for channel in seqs}
    writer.close({**{f"received/{c}": str(n) for c, n in counts.items()}, **{f"lost/{c}": "0" for c in counts}})
    return sent


_KINDS = {
    "number": lambda v: isinstance(v, int | float) and not isinstance(v, bool),
    "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "boolean": lambda v: isinstance(v, bool),
    "string": lambda v: isinstance(v, str),
    "array": lambda v: isinstance(v, list),
    "object": lambda v: isinstance(v, dict),
}


def validate(value: Any, schema: dict[str, Any], where: str = "$") -> None:
    """The part of JSON Schema our schemas (rascal's and foxglove's) use: type, properties,
    required, additionalProperties, items, minItems/maxItems, minimum/maximum, pattern, oneOf of
    consts (foxglove's enums) and base64 content. Also what Foxglove's reader needs: a type (or
    oneOf) on every property."""
    if "oneOf" in schema:
        assert value in [alternative["const"] for alternative in schema["oneOf"]], f"{where}: {value!r} not one of"
        return
    kind = schema["type"]
    assert _KINDS[kind](value), f"{where}: {value!r} is not {kind}"
    if kind in ("number", "integer"):
        assert schema.get("minimum", value) <= value <= schema.get("maximum", value), f"{where}: {value} out of range"
    if kind == "string":
        assert re.search(schema.get("pattern", ""), value), f"{where}: {value!r} does not match {schema['pattern']}"
        if schema.get("contentEncoding") == "base64":
            base64.b64decode(value, validate=True)
    if kind == "array":
        assert schema.get("minItems", 0) <= len(value) <= schema.get("maxItems", len(value)), f"{where}: length"
        for index, item in enumerate(value):
            validate(item, schema["items"], f"{where}[{index}]")
    if kind == "object":
        assert set(schema["required"]) <= set(value), f"{where}: missing {set(schema['required']) - set(value)}"
        if schema.get("additionalProperties") is False:
            assert set(value) <= set(schema["properties"]), f"{where}: extra {set(value) - set(schema['properties'])}"
        for name, item in value.items():
            validate(item, schema["properties"][name], f"{where}.{name}")


def from_twin(tp: Any, value: Any, enum: Any = None) -> Any:
    """A JSON twin read back into the typed message (the inverse of ``json_converter``)."""
    if enum is not None:
        return enum[value].value if value in enum.__members__ else int(value)
    if tp is bytes:
        return base64.b64decode(value)
    if typing.get_origin(tp) is tuple:
        return tuple(from_twin(typing.get_args(tp)[0], item) for item in value)
    if hasattr(tp, "_fields"):
        hints = typing.get_type_hints(tp)
        return tp(*(from_twin(hints[name], value[name], ENUM_FIELDS.get((tp, name))) for name in tp._fields))
    return value


# -- the JSON form ------------------------------------------------------------------------------


def test_every_message_type_has_a_schema_its_json_satisfies() -> None:
    rng = random.Random(7)
    for info in registered():
        schema = json_schema(info.cls)
        assert schema["title"] == info.cls.__name__
        assert list(schema["properties"]) == list(info.cls._fields)
        convert = json_converter(info.cls)
        assert convert is not None
        for _ in range(5):
            msg = sample(info.cls, rng)
            as_json = json.loads(json.dumps(convert(msg)))
            assert from_twin(info.cls, as_json) == msg  # nothing lost
            validate(as_json, schema, info.cls.__name__)


def test_enums_are_names_and_bytes_base64_in_the_json() -> None:
    fix = json_converter(GpsFix)(GpsFix(34.9, -116.9, 700.0, 1.0, 1.0, 2.0, NavQuality.DGPS, 9))  # type: ignore[misc]
    assert fix["quality"] == "DGPS"
    lidar = ObstacleList(Sensor.LIDAR_SWEEP, Frame.VEHICLE, ())
    assert json_converter(ObstacleList)(lidar) == {"sensor": "LIDAR_SWEEP", "frame": "VEHICLE", "obstacles": []}  # type: ignore[misc]
    newer = json_converter(ObstacleList)(ObstacleList(42, 1, ()))  # type: ignore[misc]
    assert newer["sensor"] == "42"  # a sensor this build does not name
    validate(newer, json_schema(ObstacleList))
    snapshot = json_converter(MapSnapshot)(MapSnapshot(0.0, 0.0, 0.5, 1, 2, b"\x00\xff"))  # type: ignore[misc]
    assert snapshot["cells"] == "AP8="  # base64, as Foxglove decodes a contentEncoding base64 string


def test_a_wrong_shape_fails_the_schema_check() -> None:
    schema = json_schema(ImuSample)
    good = json_converter(ImuSample)(ImuSample(0.0, 0.0, 9.8, 0.0, 0.0, 0.1))  # type: ignore[misc]
    validate(good, schema)
    for bad in ({**good, "accel_x_mps2": "fast"}, {k: v for k, v in good.items() if k != "gyro_z_radps"}):
        try:
            validate(bad, schema)
        except AssertionError:
            continue
        raise AssertionError(f"{bad} passed")


# -- a live session -----------------------------------------------------------------------------


def _by_channel(datagrams: list[bytes]) -> dict[bytes, list[bytes]]:
    """Each channel's datagrams in the order given (the channel name is in the header)."""
    grouped: dict[bytes, list[bytes]] = {}
    for data in datagrams:
        channel_bytes = HEADER.unpack_from(data)[6]
        grouped.setdefault(data[HEADER.size : HEADER.size + channel_bytes], []).append(data)
    return grouped


def _wait_for_recorder(bus: Bus, child: subprocess.Popen[bytes], timeout_s: float = 15.0) -> None:
    """The recorder subscribes before its first heartbeat: once that is heard it records."""
    heard: list[int] = []
    bus.subscribe(channels.MODULE_STATUS, lambda _msg, env: heard.append(env.source_id))
    deadline = time.monotonic() + timeout_s
    while RECORDER_SOURCE_ID not in heard:
        assert time.monotonic() < deadline and child.poll() is None, "the recorder did not start"
        bus.poll(0.05)


def test_records_a_live_bus_session_exactly(bus_url: str, key_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "runs" / "run.mcap"
    log = (tmp_path / "recorder.log").open("wb")
    recorder = subprocess.Popen(
        [sys.executable, "-m", "rascal.recording", "--out", str(out), "--info", "scenario=unit test"],
        cwd=ROOT,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    try:
        bus = Bus.open(bus_url, source_id=31, clock=MasterClock(), keyring=load_keyring(key_file))
        _wait_for_recorder(bus, recorder)
        sent: list[bytes] = []
        rng = random.Random(3)
        big = ObstacleList(1, 0, tuple(Obstacle(*(rng.uniform(-50, 50) for _ in range(8))) for _ in range(60)))
        for i in range(120):
            _seq, data = bus.encode(channels.IMU, ImuSample(0.0, 0.1, 9.81, 0.0, 0.0, i * 0.01))
            if 50 <= i < 53:
                continue  # lost on the way: the recorder's bus counts it and the file has a gap there
            bus.send_raw(channels.IMU, data)
            sent.append(data)
            if i % 20 == 0:  # 4.4 kB: goes as fragments, recorded whole
                sent.append(bus.encode(channels.OBSTACLES_LIDAR, big)[1])
                bus.send_raw(channels.OBSTACLES_LIDAR, sent[-1])
            bus.poll(0.002)
        for extra in (MapSnapshot(10.0, -5.0, 0.5, 2, 2, bytes([0, 9, 255, 7])), HealthEvent("test", 1, "x", "ok ✓")):
            channel = channels.MAP_SNAPSHOT if isinstance(extra, MapSnapshot) else channels.HEALTH
            sent.append(bus.encode(channel, extra)[1])
            bus.send_raw(channel, sent[-1])
        forger = Codec(Keyring.generate())
        bus.transport.send(channels.IMU, forger.encode(b"IMU", ImuSample(0, 0, 0, 0, 0, 0), 31, 1, T0_NS, T0_NS))
        bus.transport.send(channels.IMU, sent[0])  # a replay
        bus.poll(0.3)
        bus.close()
    finally:
        recorder.terminate()  # SIGTERM: the recorder finishes the file
        try:
            recorder.wait(timeout=10)
        except subprocess.TimeoutExpired:
            recorder.kill()
            recorder.wait()
        log.close()
    assert recorder.returncode == 0, (tmp_path / "recorder.log").read_text()

    # Read back with the mcap library itself.
    raw: list[bytes] = []
    json_count = 0
    with out.open("rb") as stream:
        reader = make_reader(stream)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if channel.message_encoding == RAW_ENCODING:
                assert channel.schema_id == 0 and int(channel.metadata["type_id"]) > 0
                opened_source = HEADER.unpack_from(message.data)[4]
                if opened_source == 31:
                    raw.append(message.data)
                    assert message.publish_time == HEADER.unpack_from(message.data)[10]
                    assert message.sequence == HEADER.unpack_from(message.data)[8] & 0xFFFFFFFF
            else:
                assert channel.message_encoding == "json" and channel.topic.endswith(".json")
                assert schema is not None and schema.encoding == JSON_SCHEMA_ENCODING
                validate(json.loads(message.data), json.loads(schema.data), channel.topic)
                json_count += 1
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
    # Every message, byte for byte, in order on each channel. Across channels the order is the
    # order the recorder read its sockets in: each port is its own socket, drained in turn.
    assert sorted(raw) == sorted(sent)
    assert _by_channel(raw) == _by_channel(sent)
    assert json_count * 2 == summary.statistics.message_count  # one JSON message beside each raw one

    metadata = read_metadata(out)
    assert metadata[RUN_METADATA]["scenario"] == "unit test"
    end = metadata[END_METADATA]
    assert end["lost/IMU"] == "3"
    assert end["rejected/31/bad_mac"] == "1" and end["rejected/31/replay"] == "1"

    report = check_sequences(out)
    assert report.problems() == []
    assert report.streams[(31, channels.IMU)].gaps == 3
    assert report.streams[(31, channels.IMU)].messages == 117
    assert report.streams[(31, channels.OBSTACLES_LIDAR)].gaps == 0


# -- files the recorder must cope with -------------------------------------------------------------


def _stream_of(
    path: Path, count: int, drop: int | None = None, json_channels: bool = True
) -> tuple[Bus, RecordingWriter]:
    """``count`` IMU messages through an in-process bus into a recording, skipping message
    ``drop`` on its way into the file (a recorder that lost one)."""
    hub = f"mem://rec-{uuid.uuid4().hex}"
    keyring = Keyring.generate()
    publisher = Bus.open(hub, source_id=12, clock=MasterClock(), keyring=keyring)
    listener = Bus.open(hub, source_id=RECORDER_SOURCE_ID, clock=MasterClock(), keyring=keyring)
    writer = RecordingWriter(path, {}, json_channels=json_channels)
    written = 0

    def record(opened: Any, data: bytes, recv_ns: int) -> None:
        nonlocal written
        written += 1
        if written - 1 != drop:
            writer.write(opened, data, recv_ns)

    listener.subscribe_raw(record)
    for i in range(count):
        publisher.publish(channels.IMU, ImuSample(0.0, 0.0, 9.8, 0.0, 0.0, float(i)))
    listener.poll(0.0)
    return listener, writer


def test_json_twins_added_after_the_run_are_those_the_recorder_would_write(tmp_path: Path) -> None:
    bus, raw = _stream_of(tmp_path / "raw.mcap", 20, json_channels=False)
    raw.close(bus_counts(bus, raw))
    bus, live = _stream_of(tmp_path / "live.mcap", 20)
    live.close(bus_counts(bus, live))
    assert add_json_twins(tmp_path / "raw.mcap") == 20
    assert not list(tmp_path.glob("*partial*"))

    def contents(path: Path) -> dict[str, list[bytes]]:
        topics: dict[str, list[bytes]] = {}
        with path.open("rb") as stream:
            for _schema, channel, message in make_reader(stream).iter_messages():
                topics.setdefault(channel.topic, []).append(message.data if channel.topic.endswith(".json") else b"")
        return topics

    twinned, recorded = contents(tmp_path / "raw.mcap"), contents(tmp_path / "live.mcap")
    assert set(twinned) == {channels.IMU, channels.IMU + ".json"} == set(recorded)
    # The same JSON as the recorder's own (the IMU values are the same; the streams differ only in keys).
    assert [json.loads(m) for m in twinned[channels.IMU + ".json"]] == [
        json.loads(m) for m in recorded[channels.IMU + ".json"]
    ]
    metadata = read_metadata(tmp_path / "raw.mcap")
    assert metadata[RUN_METADATA] == {} and metadata[END_METADATA]["received/IMU"] == "20"
    assert check_sequences(tmp_path / "raw.mcap").problems() == []


def test_the_check_sees_a_message_the_recorder_missed(tmp_path: Path) -> None:
    bus, writer = _stream_of(tmp_path / "run.mcap", 10, drop=4)
    writer.close(bus_counts(bus, writer))
    report = check_sequences(tmp_path / "run.mcap")
    assert report.streams[(12, channels.IMU)].gaps == 1
    assert report.problems() == [
        "IMU: 9 recorded, 10 received",
        "IMU: 1 missing sequence number(s), the bus lost 0",
    ]


def test_a_file_cut_short_reads_up_to_its_last_whole_chunk(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    bus, writer = _stream_of(path, 30)
    writer.flush()  # what the recorder does every flush_period_s
    first_chunk_end = path.stat().st_size
    for i in range(10):
        bus.publish(channels.IMU, ImuSample(0.0, 0.0, 9.8, 0.0, 0.0, float(i)))  # heard by itself
    bus.poll(0.0)
    writer.flush()
    killed = tmp_path / "killed.mcap"
    killed.write_bytes(path.read_bytes()[: first_chunk_end + 40])  # the kill cut the second chunk
    writer.close(bus_counts(bus, writer))
    scan = Scan()
    assert len(list(iter_datagrams(killed, scan=scan))) == 30
    assert scan.truncated
    assert read_metadata(killed)[RUN_METADATA] == {}
    assert check_sequences(killed).problems() == ["no end-of-recording counts: the recorder did not finish the file"]
    assert len(list(iter_datagrams(path))) == 40 and check_sequences(path).ok


def test_an_existing_recording_is_never_overwritten(tmp_path: Path) -> None:
    first = RecordingWriter(tmp_path / "run.mcap", {"life": "1"})
    first.close({})
    second = RecordingWriter(tmp_path / "run.mcap", {"life": "2"})
    second.close({})
    assert second.path == tmp_path / "run.1.mcap"
    assert read_metadata(tmp_path / "run.mcap")[RUN_METADATA] == {"life": "1"}
    assert read_metadata(tmp_path / "run.1.mcap")[RUN_METADATA] == {"life": "2"}


def test_unknown_types_and_bad_bodies_are_kept_raw_only(tmp_path: Path) -> None:
    keyring = Keyring.generate()
    codec = Codec(keyring)

    def forge(type_id: int, channel: bytes, body: bytes) -> bytes:
        head = HEADER.pack(b"RB", 1, 1, type_id, 44, keyring.active, len(channel), 0, 1, T0_NS, T0_NS)
        return head + channel + body + keyring.sign(head + channel + body)

    newer = forge(777, b"FUTURE_THING", msgpack.packb([1, 2, 3]))
    broken = forge(10, b"IMU", msgpack.packb([1.0, "not a number"]))
    good = codec.encode(b"MODULE_STATUS", sample(ModuleStatus, random.Random(1)), 44, 1, T0_NS, T0_NS)
    writer = RecordingWriter(tmp_path / "run.mcap", {})
    for data in (newer, broken, good):
        writer.write(codec.open(data), data, T0_NS + 1)
    assert writer.undecodable == 1  # the broken IMU: a newer type is not counted, it has no JSON channel at all
    writer.close({})
    with (tmp_path / "run.mcap").open("rb") as stream:
        topics = sorted(channel.topic for channel in make_reader(stream).get_summary().channels.values())  # type: ignore[union-attr]
    assert topics == ["FUTURE_THING", "IMU", "IMU.json", "MODULE_STATUS", "MODULE_STATUS.json"]
    assert [d.data for d in iter_datagrams(tmp_path / "run.mcap")] == [newer, broken, good]
    assert decode_body(2, codec.open(good).body) == sample(ModuleStatus, random.Random(1))
