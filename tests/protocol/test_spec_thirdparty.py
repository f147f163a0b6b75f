"""protocol/SPEC.md is enough to talk to the bus: a third-party implementation, written from the
document with only the standard library and msgpack, decodes real captured traffic and forges
messages the project accepts.

Layout of this module:

* ``tp_*``: the third-party implementation. It imports nothing from the project (checked by
  :func:`test_third_party_code_imports_nothing_from_the_project`); even the message layouts,
  field defaults and channel table it uses are parsed out of SPEC.md.
* Fixtures and tests: they may use the project, to produce captured datagrams and to check that
  forged ones are accepted.
* ``render_*``: generators for the tables in SPEC.md between ``<!-- generated:NAME -->`` markers.
  The drift test fails when SPEC.md no longer matches the code; refresh it with
  ``python tests/protocol/test_spec_thirdparty.py --write``.
"""

from __future__ import annotations

import ast
import hashlib
import hmac
import json
import math
import random
import re
import struct
import sys
import time
import tomllib
import zlib
from pathlib import Path
from typing import Any, NamedTuple

import msgpack
import pytest

ROOT = Path(__file__).resolve().parents[2]
SPEC_PATH = ROOT / "protocol" / "SPEC.md"

# =================================================================================================
# Third-party implementation: stdlib + msgpack, from SPEC.md only.
# =================================================================================================

TP_HEADER = struct.Struct("<2sBBHHHBBQqq")  # SPEC "Fixed header": 36 bytes
TP_FRAGMENT_HEADER = struct.Struct("<2sBBHHHHII")  # SPEC "Fragmentation": 20 bytes
TP_MAGIC = b"RB"
TP_VERSION = 1
TP_SIGNED = 0x01
TP_FRAGMENT = 0x02
TP_SIGNATURE = 0x04
TP_TAG_BYTES = 16
TP_SIGNATURE_BYTES = 64
TP_FRAGMENT_TAG_BYTES = 8
TP_MAX_MESSAGE = 256 * 1024
TP_MAX_DATAGRAM = 1400
TP_CHANNEL = re.compile(r"[A-Za-z0-9_./-]{1,64}")


class TpError(Exception):
    """The third-party decoder rejects the bytes; ``reason`` is the SPEC's reason name."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


# -- message layouts, parsed from SPEC.md ---------------------------------------------------------


class TpLayout(NamedTuple):
    """A record layout from its canonical string: name and [(field, type)], where a type is a
    scalar name ("float64", "int64", "bool", "str", "bin"), ("array", type) or a TpLayout."""

    name: str
    fields: tuple[tuple[str, Any], ...]


def tp_parse_layout(text: str) -> TpLayout:
    """Parse a canonical layout string (SPEC "Fingerprints") such as ``A(x:float64,p:[B(y:str)])``."""
    pos = 0

    def ident() -> str:
        nonlocal pos
        match = re.compile(r"[A-Za-z_][A-Za-z0-9_]*").match(text, pos)
        if not match:
            raise ValueError(f"identifier expected at {pos} in {text!r}")
        pos = match.end()
        return match.group()

    def expect(char: str) -> None:
        nonlocal pos
        if text[pos : pos + 1] != char:
            raise ValueError(f"{char!r} expected at {pos} in {text!r}")
        pos += 1

    def wire_type() -> Any:
        nonlocal pos
        if text.startswith("[", pos):
            pos += 1
            item = wire_type()
            expect("]")
            return ("array", item)
        name = ident()
        if text.startswith("(", pos):
            return record(name)
        if name not in ("float64", "int64", "bool", "str", "bin"):
            raise ValueError(f"unknown scalar {name!r}")
        return name

    def record(name: str) -> TpLayout:
        expect("(")
        fields = []
        while True:
            field_name = ident()
            expect(":")
            fields.append((field_name, wire_type()))
            if text.startswith(")", pos):
                break
            expect(",")
        expect(")")
        return TpLayout(name, tuple(fields))

    layout = record(ident())
    if pos != len(text):
        raise ValueError(f"trailing text in {text!r}")
    return layout


class TpSchema(NamedTuple):
    layouts: dict[int, TpLayout]  # type_id -> layout
    names: dict[str, int]  # message name -> type_id
    fingerprints: dict[int, str]
    canonical: dict[int, str]
    defaults: dict[tuple[str, str], Any]  # (record name, field) -> default value
    channels: dict[str, int]  # channel -> type_id


def tp_schema_from_spec(spec: str) -> TpSchema:
    """Everything the third party knows about message types comes from the SPEC's tables."""
    layouts: dict[int, TpLayout] = {}
    names: dict[str, int] = {}
    fingerprints: dict[int, str] = {}
    canonical: dict[int, str] = {}
    defaults: dict[tuple[str, str], Any] = {}
    tables = spec.split("<!-- generated:message-types -->")[1].split("<!-- /generated:message-types -->")[0]
    for section in re.split(r"^#### ", tables, flags=re.M)[1:]:
        heading = section.splitlines()[0]
        message = re.fullmatch(r"(\d+) (\w+)", heading)
        record = re.fullmatch(r"Record (\w+)", heading)
        if not (message or record):
            continue
        name = (message or record).group(2 if message else 1)  # type: ignore[union-attr]
        layout_text = re.search(r"^Layout: `([^`]+)`", section, re.M).group(1)  # type: ignore[union-attr]
        rows = re.findall(r"^\| \d+ \| `(\w+)` \|[^|]*\|[^|]*\| (?:`([^`]*)`|required) \|$", section, re.M)
        for field, default in rows:
            if default:
                defaults[(name, field)] = json.loads(default)
        if message:
            type_id = int(message.group(1))
            layouts[type_id] = tp_parse_layout(layout_text)
            names[name] = type_id
            canonical[type_id] = layout_text
            fingerprints[type_id] = re.search(r"^Fingerprint: `([0-9a-f]{16})`", section, re.M).group(1)  # type: ignore[union-attr]
    channels = {
        channel: names[type_name]
        for channel, type_name in re.findall(r"^\| `([A-Za-z0-9_./-]+)` \| \d+ \| (\w+) \|", spec, re.M)
    }
    return TpSchema(layouts, names, fingerprints, canonical, defaults, channels)


def tp_fingerprint(canonical: str) -> str:
    return hashlib.sha256(canonical.encode("ascii")).hexdigest()[:16]


# -- keys and MAC ---------------------------------------------------------------------------------


def tp_load_keys(path: Path) -> tuple[dict[int, bytes], int]:
    """Key file (SPEC "Keys"): TOML, ``active = ID`` and ``[keys]`` of ID = "64 hex digits"."""
    doc = tomllib.loads(path.read_text())
    keys = {int(key_id): bytes.fromhex(value) for key_id, value in doc["keys"].items()}
    assert all(len(key) == 32 for key in keys.values())
    return keys, doc.get("active", min(keys))


def tp_mac(key: bytes, signed_part: bytes) -> bytes:
    return hashlib.blake2b(signed_part, key=key, digest_size=TP_TAG_BYTES).digest()


def tp_fragment_mac(key: bytes, signed_part: bytes) -> bytes:
    return hashlib.blake2b(signed_part, key=key, digest_size=TP_FRAGMENT_TAG_BYTES).digest()


def tp_signing_seed(signing_master: bytes, source_id: int) -> bytes:
    """SPEC "Signatures": the Ed25519 seed of a source (an Ed25519 library does the rest)."""
    return hashlib.blake2b(
        struct.pack("<H", source_id), key=signing_master, person=b"rascal-ed25519", digest_size=32
    ).digest()


# -- messages -------------------------------------------------------------------------------------


class TpMessage(NamedTuple):
    flags: int
    type_id: int
    source_id: int
    key_id: int
    seq: int
    t_meas_ns: int
    t_pub_ns: int
    channel: str
    body: bytes
    signature: bytes  # empty without SIGNATURE
    signed_part: bytes  # what the signature covers


def tp_open(data: bytes, keys: dict[int, bytes] | None) -> TpMessage:
    """Header, channel and tag of one whole message. ``keys=None``: unsigned deployment."""
    if len(data) < TP_HEADER.size:
        raise TpError("truncated")
    if len(data) > TP_MAX_MESSAGE:
        raise TpError("oversized")
    magic, version, flags, type_id, source_id, key_id, channel_len, _reserved, seq, t_meas, t_pub = (
        TP_HEADER.unpack_from(data)
    )
    if magic != TP_MAGIC:
        raise TpError("bad_magic")
    if version != TP_VERSION:
        raise TpError("bad_version")
    if flags & ~(TP_SIGNED | TP_SIGNATURE) or (flags & TP_SIGNATURE and not flags & TP_SIGNED):
        raise TpError("bad_header", f"flags {flags:#x}")
    end = tag_start = len(data)
    if flags & TP_SIGNED:
        tag_start -= TP_TAG_BYTES
        end = tag_start - (TP_SIGNATURE_BYTES if flags & TP_SIGNATURE else 0)
        if end < TP_HEADER.size + channel_len:
            raise TpError("truncated")
        if keys is not None:
            if key_id not in keys:
                raise TpError("unknown_key")
            if not hmac.compare_digest(tp_mac(keys[key_id], data[:tag_start]), data[tag_start:]):
                raise TpError("bad_mac")
    elif keys is not None:
        raise TpError("unsigned")
    body_start = TP_HEADER.size + channel_len
    if not 1 <= channel_len <= 64 or body_start >= end:
        raise TpError("bad_header", "channel length or empty body")
    channel = data[TP_HEADER.size : body_start].decode("ascii")
    if not TP_CHANNEL.fullmatch(channel):
        raise TpError("bad_header", f"channel {channel!r}")
    return TpMessage(
        flags,
        type_id,
        source_id,
        key_id,
        seq,
        t_meas,
        t_pub,
        channel,
        data[body_start:end],
        data[end:tag_start],
        data[:end],
    )


def tp_decode_body(schema: TpSchema, type_id: int, body: bytes) -> dict[str, Any]:
    """msgpack array -> {field: value} by the SPEC's layout and evolution rules."""
    if type_id not in schema.layouts:
        raise TpError("unknown_type")
    try:
        raw = msgpack.unpackb(body, raw=False, use_list=True, strict_map_key=True)
    except Exception as exc:  # any msgpack failure is a bad body
        raise TpError("bad_body", repr(exc)) from None
    return tp_decode_record(schema, schema.layouts[type_id], raw)


def tp_decode_record(schema: TpSchema, layout: TpLayout, raw: Any) -> dict[str, Any]:
    if not isinstance(raw, list):
        raise TpError("bad_body", f"{layout.name} is not an array")
    values: dict[str, Any] = {}
    for index, (name, wire_type) in enumerate(layout.fields):
        if index < len(raw):
            values[name] = tp_decode_value(schema, wire_type, raw[index])
        elif (layout.name, name) in schema.defaults:
            values[name] = schema.defaults[(layout.name, name)]
        else:
            raise TpError("bad_body", f"{layout.name}.{name} missing and has no default")
    return values  # extra trailing fields (a newer layout) are ignored


def tp_decode_value(schema: TpSchema, wire_type: Any, value: Any) -> Any:
    if isinstance(wire_type, TpLayout):
        return tp_decode_record(schema, wire_type, value)
    if isinstance(wire_type, tuple):
        if not isinstance(value, list):
            raise TpError("bad_body", "array expected")
        return [tp_decode_value(schema, wire_type[1], item) for item in value]
    if wire_type == "float64":
        if isinstance(value, bool) or not isinstance(value, (float, int)) or not math.isfinite(value):
            raise TpError("bad_body", f"finite float64 expected, got {value!r}")
        return float(value)
    expected = {"int64": int, "bool": bool, "str": str, "bin": bytes}[wire_type]
    if not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
        raise TpError("bad_body", f"{wire_type} expected, got {value!r}")
    return value


def tp_encode_value(schema: TpSchema, wire_type: Any, value: Any) -> Any:
    """{field: value} (nested records as dicts) -> msgpack-ready lists, floats as float."""
    if isinstance(wire_type, TpLayout):
        return [tp_encode_value(schema, t, value[name]) for name, t in wire_type.fields]
    if isinstance(wire_type, tuple):
        return [tp_encode_value(schema, wire_type[1], item) for item in value]
    if wire_type == "float64":
        value = float(value)
        assert math.isfinite(value)
    return value


def tp_encode(
    schema: TpSchema,
    channel: str,
    fields: dict[str, Any],
    *,
    source_id: int,
    seq: int,
    t_meas_ns: int,
    t_pub_ns: int,
    key: bytes | None,
    key_id: int = 0,
    type_name: str | None = None,
    sign: Any = None,
) -> bytes:
    """Forge one whole message; signed iff ``key`` is given, with a signature iff ``sign`` (an
    Ed25519 signing function of the source's seed) is also given."""
    assert TP_CHANNEL.fullmatch(channel)
    type_id = schema.names[type_name] if type_name else schema.channels[channel]
    body = msgpack.packb(tp_encode_value(schema, schema.layouts[type_id], fields), use_bin_type=True)
    head = TP_HEADER.pack(
        TP_MAGIC,
        TP_VERSION,
        (TP_SIGNED | (TP_SIGNATURE if sign else 0)) if key else 0,
        type_id,
        source_id,
        key_id if key else 0,
        len(channel),
        0,
        seq,
        t_meas_ns,
        t_pub_ns,
    )
    data = head + channel.encode("ascii") + body
    if key and sign:
        data += sign(data)
    if key:
        data += tp_mac(key, data)
    assert len(data) <= TP_MAX_MESSAGE
    return data


# -- fragments ------------------------------------------------------------------------------------


def tp_is_fragment(datagram: bytes) -> bool:
    return len(datagram) >= 4 and datagram[3] & TP_FRAGMENT != 0


def tp_fragment(
    message: bytes,
    source_id: int,
    message_id: int,
    key: bytes | None,
    key_id: int = 0,
    max_datagram: int = TP_MAX_DATAGRAM,
) -> list[bytes]:
    """Fragments of ``message``, each tagged with ``key`` (``None``: unsigned deployment)."""
    if len(message) <= max_datagram:
        return [message]
    tag_bytes = 0 if key is None else TP_FRAGMENT_TAG_BYTES
    flags = TP_FRAGMENT if key is None else TP_FRAGMENT | TP_SIGNED
    chunk = max_datagram - TP_FRAGMENT_HEADER.size - tag_bytes
    count = -(-len(message) // chunk)
    parts = []
    for i in range(count):
        header = TP_FRAGMENT_HEADER.pack(
            TP_MAGIC, TP_VERSION, flags, source_id, i, count, key_id, message_id, len(message)
        )
        part = header + message[i * chunk : (i + 1) * chunk]
        parts.append(part if key is None else part + tp_fragment_mac(key, part))
    return parts


def tp_fragment_data(datagram: bytes, keys: dict[int, bytes] | None) -> bytes:
    """The data of one fragment whose flags and tag SPEC section 8 accepts; TpError otherwise."""
    _magic, _version, flags, _source, _index, _count, key_id, _mid, _total = TP_FRAGMENT_HEADER.unpack_from(datagram)
    if flags == TP_FRAGMENT:
        if keys is not None:
            raise TpError("unsigned", "fragment")
        return datagram[TP_FRAGMENT_HEADER.size :]
    if flags != TP_FRAGMENT | TP_SIGNED:
        raise TpError("bad_fragment", f"flags {flags:#x}")
    end = len(datagram) - TP_FRAGMENT_TAG_BYTES
    if end <= TP_FRAGMENT_HEADER.size:
        raise TpError("truncated")
    if keys is not None:
        if key_id not in keys:
            raise TpError("unknown_key")
        if not hmac.compare_digest(tp_fragment_mac(keys[key_id], datagram[:end]), datagram[end:]):
            raise TpError("bad_mac", "fragment")
    return datagram[TP_FRAGMENT_HEADER.size : end]


def tp_reassemble(datagrams: list[bytes], keys: dict[int, bytes] | None) -> list[bytes]:
    """Whole messages from a capture: unfragmented datagrams as they are, authentic fragments
    joined per (source_id, message_id) in index order once every index is present (duplicates
    ignored)."""
    out: list[bytes] = []
    partial: dict[tuple[int, int], dict[int, bytes]] = {}
    for datagram in datagrams:
        if not tp_is_fragment(datagram):
            out.append(datagram)
            continue
        magic, version, _flags, source_id, index, count, _key_id, message_id, total_len = (
            TP_FRAGMENT_HEADER.unpack_from(datagram)
        )
        assert (magic, version) == (TP_MAGIC, TP_VERSION) and count >= 2 and index < count
        data = tp_fragment_data(datagram, keys)
        parts = partial.setdefault((source_id, message_id), {})
        parts.setdefault(index, data)
        if len(parts) == count:
            whole = b"".join(parts[i] for i in range(count))
            assert len(whole) == total_len
            out.append(whole)
            del partial[(source_id, message_id)]
    return out


def tp_port(channel: str, base_port: int = 7667, span: int = 67) -> int:
    return base_port + zlib.crc32(channel.encode("ascii")) % span


# =================================================================================================
# Generated SPEC.md tables (these use the project: they document it).
# =================================================================================================

UNIT_SUFFIXES = (
    ("_mps2", "m/s²"),
    ("_radps", "rad/s"),
    ("_mps", "m/s"),
    ("_per_m", "1/m"),
    ("_deg", "deg"),
    ("_rad", "rad"),
    ("_ns", "ns"),
    ("_s", "s"),
    ("_m", "m"),
)
ENUM_FIELDS = {
    ("TimeSync", "kind"): "TimeSyncKind",
    ("ModuleStatus", "state"): "ModuleState",
    ("ModuleStatus", "clock_state"): "SyncState",
    ("HealthEvent", "severity"): "Severity",
    ("GpsFix", "quality"): "NavQuality",
    ("VehicleState", "quality"): "NavQuality",
    ("ObstacleList", "sensor"): "Sensor",
    ("ObstacleList", "frame"): "Frame",
    ("SurfaceProfile", "sensor"): "Sensor",
    ("GroundSweep", "sensor"): "Sensor",
    ("LaneBorders", "sensor"): "Sensor",
}
NOTES = {
    ("TimeSync", "client_source_id"): "source id of the requesting client",
    ("TimeSync", "t1_local_ns"): "ns, client's local clock",
    ("TimeSync", "t2_master_ns"): "ns, shared time",
    ("TimeSync", "t3_master_ns"): "ns, shared time",
    ("ModuleStatus", "module"): "module name",
    ("ModuleStatus", "detail"): "free text",
    ("ModuleStatus", "clock_offset_ns"): "ns, shared − local",
    ("ModuleStatus", "stale_inputs"): "channel names",
    ("ModuleStatus", "overruns"): "count",
    ("ModuleStatus", "restarts"): "count",
    ("ModuleStatus", "rx_rejected"): "count",
    ("ModuleStatus", "cpu_pct"): "% of one core over the last heartbeat period, children included; −1 unknown",
    ("HealthEvent", "module"): "module name",
    ("HealthEvent", "code"): "short machine-readable code",
    ("HealthEvent", "text"): "human-readable text",
    ("GpsFix", "satellites"): "count",
    ("MagHeading", "magnetometer"): "index",
    ("MagHeading", "heading_from_north_rad"): "rad, clockwise from north",
    ("VehicleState", "covariance"): "25 values: row-major 5×5 of [east_m, north_m, yaw_rad, speed_mps, yaw_rate_radps]",
    ("Obstacle", "confidence"): "0..1",
    ("LaneBorder", "side"): "+1 left, −1 right",
    ("LaneBorder", "c1"): "1 (slope)",
    ("LaneBorder", "confidence"): "0..1",
    ("Path", "path_id"): "changes when the planner re-plans",
    ("Path", "t_input_ns"): "ns, shared time: the oldest of the newest obstacle inputs planned from; 0 unknown",
    ("Path", "reverse"): "drive the path backwards (points in the order of travel, speeds as magnitudes)",
    ("ActuatorCommand", "throttle"): "fraction 0..1",
    ("ActuatorCommand", "brake"): "fraction 0..1",
    ("ActuatorCommand", "steering_rad"): "rad, front wheels, left positive",
    ("ActuatorCommand", "reverse"): "reverse gear; changed only at a standstill",
    ("SimTruth", "collisions"): "count",
}


def _unit(owner: str, field: str) -> str:
    if (owner, field) in NOTES:
        return NOTES[(owner, field)]
    if (owner, field) in ENUM_FIELDS:
        return f"enum {ENUM_FIELDS[(owner, field)]}"
    for suffix, unit in UNIT_SUFFIXES:
        if field.endswith(suffix):
            return unit
    return "—"


def _record_table(cls: type) -> list[str]:
    import typing

    from protocol.schema import describe_type

    hints = typing.get_type_hints(cls)
    lines = ["| # | field | wire type | unit / meaning | default |", "|--:|---|---|---|---|"]
    for index, name in enumerate(cls._fields):  # type: ignore[attr-defined]
        tp = hints[name]
        wire = describe_type(tp)
        if typing.get_origin(tp) is tuple and hasattr(typing.get_args(tp)[0], "_fields"):
            wire = f"[{typing.get_args(tp)[0].__name__}]"
        defaults = cls._field_defaults  # type: ignore[attr-defined]
        default = f"`{json.dumps(defaults[name])}`" if name in defaults else "required"
        lines.append(f"| {index} | `{name}` | {wire} | {_unit(cls.__name__, name)} | {default} |")
    return lines


def _nested_records(cls: type, seen: dict[str, type]) -> None:
    import typing

    for tp in typing.get_type_hints(cls).values():
        if typing.get_origin(tp) is tuple:
            item = typing.get_args(tp)[0]
            if hasattr(item, "_fields") and item.__name__ not in seen:
                seen[item.__name__] = item
                _nested_records(item, seen)


def render_message_types() -> str:
    from protocol import channels
    from protocol.schema import describe_type, registered

    carried: dict[type, list[str]] = {}
    for channel, cls in channels.CHANNEL_TYPES.items():
        carried.setdefault(cls, []).append(channel)
    infos = registered()
    lines = ["| type_id | message | fingerprint | channels |", "|--:|---|---|---|"]
    for info in infos:
        chans = ", ".join(f"`{c}`" for c in carried.get(info.cls, [])) or "—"
        lines.append(f"| {info.type_id} | {info.cls.__name__} | `{info.fingerprint}` | {chans} |")
    records: dict[str, type] = {}
    for info in infos:
        lines += [
            "",
            f"#### {info.type_id} {info.cls.__name__}",
            "",
            f"Layout: `{describe_type(info.cls)}`",
            f"Fingerprint: `{info.fingerprint}`",
            "",
            *_record_table(info.cls),
        ]
        _nested_records(info.cls, records)
    for name, cls in records.items():
        lines += ["", f"#### Record {name}", "", f"Layout: `{describe_type(cls)}`", "", *_record_table(cls)]
    return "\n".join(lines)


def render_enums() -> str:
    import enum

    from protocol import messages
    from rascal.runtime.timesync import SyncState

    enums = [
        value
        for value in vars(messages).values()
        if isinstance(value, type) and issubclass(value, enum.IntEnum) and value.__module__ == messages.__name__
    ]
    lines = ["| enum | values |", "|---|---|"]
    for cls in [*enums, SyncState]:
        lines.append(f"| {cls.__name__} | " + ", ".join(f"{int(v)} = {v.name}" for v in cls) + " |")
    return "\n".join(lines)


def render_channels() -> str:
    from urllib.parse import urlsplit

    from protocol import channels
    from protocol.schema import info_for_class
    from protocol.transport import DEFAULT_URL
    from rascal.runtime.bus import REPLAY_EXEMPT

    base = urlsplit(DEFAULT_URL).port
    assert base is not None
    lines = [
        f"| channel | type_id | message | port offset (span {channels.DEFAULT_PORT_SPAN}) | default port "
        "| replay and freshness checked |",
        "|---|--:|---|--:|--:|---|",
    ]
    for channel, cls in channels.CHANNEL_TYPES.items():
        offset = channels.port_offset(channel)
        fresh = "no (section 13)" if channel in REPLAY_EXEMPT else "yes"
        lines.append(
            f"| `{channel}` | {info_for_class(cls).type_id} | {cls.__name__} | {offset} | {base + offset} | {fresh} |"
        )
    return "\n".join(lines)


RENDERERS = {"message-types": render_message_types, "enums": render_enums, "channels": render_channels}


def generated_block(spec: str, name: str) -> str | None:
    match = re.search(rf"<!-- generated:{name} -->\n(.*?)\n<!-- /generated:{name} -->", spec, re.S)
    return match.group(1) if match else None


def write_generated(spec: str) -> str:
    for name, render in RENDERERS.items():
        pattern = re.compile(rf"(<!-- generated:{name} -->\n)(?:.*?\n)?(<!-- /generated:{name} -->)", re.S)
        spec, found = pattern.subn(lambda m, text=render(): m.group(1) + text + "\n" + m.group(2), spec)  # noqa: B008
        if not found:
            raise SystemExit(f"SPEC.md has no <!-- generated:{name} --> block")
    return spec


# =================================================================================================
# Fixtures: real traffic from the project's Bus (the project is used here, not in tp_*).
# =================================================================================================


class Capture(NamedTuple):
    directory: Path  # NNN.dgram files in send order, and bus.key
    expected: list[tuple[str, int, dict[str, Any]]]  # (channel, type_id, fields) per message
    source_id: int


def _plain(value: Any) -> Any:
    """A project message as the third party sees it: records as dicts, arrays as lists."""
    if hasattr(value, "_asdict"):
        return {k: _plain(v) for k, v in value._asdict().items()}
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    if isinstance(value, int) and not isinstance(value, bool):
        return int(value)  # IntEnum -> int
    return value


@pytest.fixture
def capture(tmp_path: Path) -> Capture:
    from protocol import channels as ch
    from protocol import messages as m
    from protocol.auth import Keyring, write_keyring
    from protocol.schema import info_for_class
    from protocol.transport import MemTransport
    from rascal.runtime.bus import Bus
    from rascal.runtime.clock import ManualClock

    keyring = Keyring({3: bytes(range(32)), 9: random.randbytes(32)}, active=9)
    write_keyring(tmp_path / "bus.key", keyring)
    hub = f"spec-thirdparty-{random.getrandbits(64):x}"
    recorder = MemTransport(hub)
    recorder.listen_all()
    bus = Bus(MemTransport(hub), 77, keyring, ManualClock())
    rng = random.Random(5)
    obstacles = tuple(
        m.Obstacle(*(rng.uniform(-50, 50) for _ in range(6)), rng.random(), rng.uniform(0, 80)) for _ in range(60)
    )
    sent = [
        (ch.ACTUATOR_COMMAND, m.ActuatorCommand(0.3, 0.0, -0.05, "")),
        (ch.IMU, m.ImuSample(0.1, -0.2, 9.81, 0.001, 0.0, -0.03)),
        (ch.TIME_SYNC, m.TimeSync(m.TimeSyncKind.REQUEST, 77, 1_699_999_999_123_456_789)),
        (
            ch.MODULE_STATUS,
            m.ModuleStatus("planner", 1, 12.5, 50_000_000, 1200, 0, 1, 3, ("GPS", "IMU"), 1, -4, 9, "ok"),
        ),
        (ch.PATH, m.Path(7, tuple(m.PathPoint(float(i), 2.0 * i, 5.5) for i in range(5)), True)),
        (ch.OBSTACLES_LIDAR, m.ObstacleList(m.Sensor.LIDAR_H_LEFT, m.Frame.VEHICLE, obstacles)),  # > 1400 B
        (ch.LANE_BORDERS, m.LaneBorders(m.Sensor.ESVS, (m.LaneBorder(1, 1.8, 0.01, -0.001, 0.0, 30.0, 0.9),))),
    ]
    for channel, msg in sent:
        bus.publish(channel, msg, t_meas_ns=bus.clock.now_ns() - 3_000_000)
        bus.clock.advance(1_000_000)  # type: ignore[attr-defined]
    datagrams: list[bytes] = []
    recorder.receive(datagrams.append, 0.0, 1000)
    for index, datagram in enumerate(datagrams):
        (tmp_path / f"{index:03d}.dgram").write_bytes(datagram)
    expected = [(c, info_for_class(type(msg)).type_id, _plain(msg)) for c, msg in sent]
    return Capture(tmp_path, expected, 77)


@pytest.fixture(scope="module")
def spec() -> str:
    return SPEC_PATH.read_text()


@pytest.fixture(scope="module")
def schema(spec: str) -> TpSchema:
    return tp_schema_from_spec(spec)


def _section(spec: str, title: str) -> str:
    """The text of the SPEC.md section ``## N. title``."""
    return re.split(rf"^## (?:\d+\. )?{title}\n", spec, flags=re.M)[1].split("\n## ", 1)[0]


def _read_capture(directory: Path) -> list[bytes]:
    return [path.read_bytes() for path in sorted(directory.glob("*.dgram"))]


# =================================================================================================
# Tests
# =================================================================================================


def test_spec_tables_match_the_code(spec: str) -> None:
    for name, render in RENDERERS.items():
        block = generated_block(spec, name)
        assert block is not None, f"SPEC.md lacks the generated:{name} block"
        assert block == render(), (
            f"SPEC.md's {name} table is out of date: run python tests/protocol/test_spec_thirdparty.py --write"
        )


def test_unit_annotations_name_existing_fields() -> None:
    import typing

    from protocol.schema import registered

    records: dict[str, type] = {}
    for info in registered():
        records[info.cls.__name__] = info.cls
        _nested_records(info.cls, records)
    known = {(name, field) for name, cls in records.items() for field in typing.get_type_hints(cls)}
    assert set(ENUM_FIELDS) | set(NOTES) <= known


def test_spec_lists_every_rejection_reason(spec: str) -> None:
    from protocol.errors import Reason

    listed = set(re.findall(r"^\| `([a-z_]+)` \|", _section(spec, "Rejection reasons"), re.M))
    assert listed == {reason.value for reason in Reason}


def test_fingerprints_follow_from_the_canonical_layouts(schema: TpSchema) -> None:
    assert schema.layouts, "no message types parsed from SPEC.md"
    for type_id, canonical in schema.canonical.items():
        assert tp_fingerprint(canonical) == schema.fingerprints[type_id]


def test_third_party_decodes_captured_traffic(capture: Capture, schema: TpSchema) -> None:
    keys, _active = tp_load_keys(capture.directory / "bus.key")
    datagrams = _read_capture(capture.directory)
    assert all(len(d) <= TP_MAX_DATAGRAM for d in datagrams)
    fragments = [d for d in datagrams if tp_is_fragment(d)]
    assert len(fragments) >= 2, "the capture should include a fragmented message"
    assert all(TP_FRAGMENT_HEADER.unpack_from(d)[2] == TP_FRAGMENT | TP_SIGNED for d in fragments)
    messages = tp_reassemble(datagrams, keys)
    assert len(messages) == len(capture.expected)
    decoded = {}
    for data in messages:
        msg = tp_open(data, keys)
        assert msg.flags == TP_SIGNED and msg.key_id == 9 and msg.source_id == capture.source_id
        assert msg.t_meas_ns == msg.t_pub_ns - 3_000_000
        assert schema.channels[msg.channel] == msg.type_id
        decoded[msg.channel] = (msg.type_id, tp_decode_body(schema, msg.type_id, msg.body), msg.seq)
    for channel, type_id, fields in capture.expected:
        got_type, got_fields, _seq = decoded[channel]
        assert got_type == type_id
        assert got_fields == fields
    # Sequence numbers start at the publisher's wall clock in microseconds, one series per channel.
    seqs = {seq for _t, _f, seq in decoded.values()}
    assert len(seqs) == 1 and abs(seqs.pop() - time.time_ns() // 1000) < 60_000_000


def test_third_party_rejects_tampering(capture: Capture, schema: TpSchema) -> None:
    keys, _ = tp_load_keys(capture.directory / "bus.key")
    datagrams = _read_capture(capture.directory)
    data = tp_reassemble(datagrams, keys)[0]
    for position in (0, 5, 12, TP_HEADER.size + 2, len(data) - 20, len(data) - 1):
        forged = bytearray(data)
        forged[position] ^= 0x40
        with pytest.raises(TpError) as error:
            tp_open(bytes(forged), keys)
        assert error.value.reason in ("bad_magic", "bad_mac")
    with pytest.raises(TpError, match="unknown_key"):
        tp_open(data, {1: bytes(32)})
    fragment = next(d for d in datagrams if tp_is_fragment(d))
    for position in (4, 6, 12, 16, TP_FRAGMENT_HEADER.size + 3, len(fragment) - 1):
        forged = bytearray(fragment)
        forged[position] ^= 0x01
        with pytest.raises(TpError, match="bad_mac"):
            tp_fragment_data(bytes(forged), keys)


def _project_opens(data: bytes, key_file: Path) -> tuple[Any, Any]:
    from protocol.auth import load_keyring
    from protocol.codec import Codec, decode_body

    opened = Codec(load_keyring(key_file)).open(data)
    return opened, decode_body(opened.type_id, opened.body, opened.source_id)


def test_project_accepts_a_forged_actuator_command(capture: Capture, schema: TpSchema) -> None:
    from protocol.messages import ActuatorCommand

    keys, active = tp_load_keys(capture.directory / "bus.key")
    data = tp_encode(
        schema,
        "ACTUATOR_COMMAND",
        {"throttle": 0.42, "brake": 0.0, "steering_rad": -0.21, "stop_reason": "forged", "reverse": False},
        source_id=4242,
        seq=123_456,
        t_meas_ns=1_700_000_000_000_000_000,
        t_pub_ns=1_700_000_000_001_000_000,
        key=keys[active],
        key_id=active,
    )
    opened, msg = _project_opens(data, capture.directory / "bus.key")
    assert (opened.channel, opened.source_id, opened.seq) == ("ACTUATOR_COMMAND", 4242, 123_456)
    assert (opened.t_meas_ns, opened.t_pub_ns) == (1_700_000_000_000_000_000, 1_700_000_000_001_000_000)
    assert msg == ActuatorCommand(0.42, 0.0, -0.21, "forged")
    assert type(msg) is ActuatorCommand
    # Signed with the other listed key (rotation): still accepted.
    other = tp_encode(
        schema,
        "ACTUATOR_COMMAND",
        {"throttle": 0.1, "brake": 0.2, "steering_rad": 0.3, "stop_reason": "", "reverse": True},
        source_id=4242,
        seq=1,
        t_meas_ns=0,
        t_pub_ns=0,
        key=keys[3],
        key_id=3,
    )
    assert _project_opens(other, capture.directory / "bus.key")[1] == ActuatorCommand(0.1, 0.2, 0.3, reverse=True)


def test_project_applies_the_evolution_rules_to_forged_bodies(capture: Capture, schema: TpSchema) -> None:
    from protocol.messages import ActuatorCommand

    keys, active = tp_load_keys(capture.directory / "bus.key")
    header_fields = {"source_id": 5, "seq": 1, "t_meas_ns": 0, "t_pub_ns": 0, "key": keys[active], "key_id": active}

    def forge(body: list[Any]) -> bytes:
        data = tp_encode(
            schema,
            "ACTUATOR_COMMAND",
            {"throttle": 0.0, "brake": 0.0, "steering_rad": 0.0, "stop_reason": "", "reverse": False},
            **header_fields,
        )
        # Re-sign with a hand-made body: an older (3 fields) and a newer (7 fields) layout.
        message = tp_open(data, keys)
        unsigned = data[: TP_HEADER.size + len(message.channel)] + msgpack.packb(body, use_bin_type=True)
        return unsigned + tp_mac(keys[active], unsigned)

    older = forge([0.5, 0.25, 0.125])
    assert _project_opens(older, capture.directory / "bus.key")[1] == ActuatorCommand(0.5, 0.25, 0.125, "")
    newer = forge([0.5, 0.25, 0.125, "why", True, 17, {"future": b"x"}])
    assert _project_opens(newer, capture.directory / "bus.key")[1] == ActuatorCommand(0.5, 0.25, 0.125, "why", True)
    assert tp_decode_body(schema, 31, tp_open(newer, keys).body)["stop_reason"] == "why"

    from protocol.errors import ProtocolError, Reason

    for bad in ([0.5, 0.25], [0.5, float("nan"), 0.0], [0.5, "x", 0.0], {"throttle": 0.5}):
        with pytest.raises(ProtocolError) as error:
            _project_opens(forge(bad), capture.directory / "bus.key")  # type: ignore[arg-type]
        assert error.value.reason is Reason.BAD_BODY


def test_project_reassembles_a_forged_fragmented_message(capture: Capture, schema: TpSchema) -> None:
    from protocol.auth import load_keyring
    from protocol.framing import Reassembler
    from protocol.messages import ObstacleList

    keys, active = tp_load_keys(capture.directory / "bus.key")
    rng = random.Random(11)
    obstacles = [
        {
            "x_m": rng.uniform(0, 60),
            "y_m": rng.uniform(-20, 20),
            "length_m": 4.5,
            "width_m": 1.8,
            "height_m": 1.5,
            "yaw_rad": rng.uniform(-3, 3),
            "confidence": rng.random(),
            "range_m": rng.uniform(0, 60),
        }
        for _ in range(100)
    ]
    message = tp_encode(
        schema,
        "OBSTACLES_ESVS",
        {"sensor": 5, "frame": 1, "obstacles": obstacles},
        source_id=31337,
        seq=99,
        t_meas_ns=1,
        t_pub_ns=2,
        key=keys[active],
        key_id=active,
    )
    parts = tp_fragment(message, 31337, 0xDEADBEEF, keys[active], active)
    assert len(parts) >= 4 and all(len(p) <= TP_MAX_DATAGRAM for p in parts)
    shuffled = [*parts[:0:-1], parts[2], parts[0]]  # reversed, with a duplicate before completion
    reassembler = Reassembler(keyring=load_keyring(capture.directory / "bus.key"))
    results = [reassembler.feed(part, now_ns=1_000) for part in shuffled]
    whole = [r for r in results if r is not None]
    assert len(whole) == 1 and whole[0] == message
    opened, msg = _project_opens(whole[0], capture.directory / "bus.key")
    assert opened.channel == "OBSTACLES_ESVS" and opened.source_id == 31337
    assert isinstance(msg, ObstacleList) and _plain(msg) == {"sensor": 5, "frame": 1, "obstacles": obstacles}
    assert reassembler.pending() == 0 and not reassembler.dropped


def test_forged_traffic_passes_a_live_bus(capture: Capture, schema: TpSchema) -> None:
    """End to end through Bus.poll: framing, MAC, replay window and freshness as SPEC.md states."""
    from protocol.auth import load_keyring
    from protocol.transport import MemTransport
    from rascal.runtime.bus import Bus
    from rascal.runtime.clock import ManualClock

    keys, active = tp_load_keys(capture.directory / "bus.key")
    hub = f"spec-thirdparty-live-{random.getrandbits(64):x}"
    clock = ManualClock()
    bus = Bus(MemTransport(hub), 2, load_keyring(capture.directory / "bus.key"), clock)
    received: list[tuple[Any, Any]] = []
    bus.subscribe("ACTUATOR_COMMAND", lambda msg, env: received.append((msg, env)))
    bus.subscribe("OBSTACLES_BEACON", lambda msg, env: received.append((msg, env)))
    wire = MemTransport(hub)
    now = clock.now_ns()

    def send(channel: str, fields: dict[str, Any], seq: int, t_pub_ns: int) -> None:
        data = tp_encode(
            schema,
            channel,
            fields,
            source_id=600,
            seq=seq,
            t_meas_ns=t_pub_ns,
            t_pub_ns=t_pub_ns,
            key=keys[active],
            key_id=active,
        )
        for part in tp_fragment(data, 600, random.getrandbits(32), keys[active], active):
            wire.send(channel, part)
        bus.poll()

    command = {"throttle": 0.5, "brake": 0.0, "steering_rad": 0.1, "stop_reason": "", "reverse": False}
    send("ACTUATOR_COMMAND", command, 1_000, now)
    send("ACTUATOR_COMMAND", command, 1_000, now)  # replay
    send("ACTUATOR_COMMAND", command, 1_002, now + 2_000_000_000)  # edge of the freshness window
    send("ACTUATOR_COMMAND", command, 1_001, now)  # late but inside the 64-entry window
    send("ACTUATOR_COMMAND", command, 1_003, now - 2_000_000_001)  # stale
    send("ACTUATOR_COMMAND", command, 1_004, now + 2_000_000_001)  # future
    send("ACTUATOR_COMMAND", command, 1_002 - 64, now)  # behind the window
    big = {
        "sensor": 7,
        "frame": 0,
        "obstacles": [
            {
                "x_m": i,
                "y_m": 0,
                "length_m": 1,
                "width_m": 1,
                "height_m": 1,
                "yaw_rad": 0,
                "confidence": 1,
                "range_m": i,
            }
            for i in range(40)
        ],
    }
    send("OBSTACLES_BEACON", big, 5, now)
    assert [env.seq for _msg, env in received] == [1_000, 1_002, 1_001, 5]
    assert _plain(received[-1][0]) == big
    assert dict(bus.rejects) == {(600, "replay"): 2, (600, "stale"): 1, (600, "future"): 1}


def test_spec_test_vector(spec: str, schema: TpSchema) -> None:
    """The worked example in SPEC.md is what the project's codec emits, and decodes as stated."""
    from protocol.auth import Keyring
    from protocol.codec import Codec
    from protocol.messages import ActuatorCommand

    section = _section(spec, "Test vector")
    hex_block = re.search(r"```text\n(.*?)```", section, re.S).group(1)  # type: ignore[union-attr]
    vector = bytes.fromhex("".join(line.split("|")[0][6:] for line in hex_block.splitlines()))
    key = bytes(range(32))
    command = ActuatorCommand(0.25, 0.0, -0.125, "")
    seq, t_meas_ns, t_pub_ns = _VECTOR_HEADER
    ours = Codec(Keyring({1: key}, 1)).encode(b"ACTUATOR_COMMAND", command, 7, seq, t_meas_ns, t_pub_ns)
    assert vector == ours
    msg = tp_open(vector, {1: key})
    assert (msg.type_id, msg.source_id, msg.key_id, msg.seq) == (31, 7, 1, 1_700_000_000_000_000)
    assert tp_decode_body(schema, msg.type_id, msg.body) == {
        "throttle": 0.25,
        "brake": 0.0,
        "steering_rad": -0.125,
        "stop_reason": "",
        "reverse": False,
    }
    assert f"`{vector[-16:].hex()}`" in section
    _check_signed_test_vector(section, vector, schema)


def _check_signed_test_vector(section: str, vector: bytes, schema: TpSchema) -> None:
    """The example's signed twin: the seed and public key the SPEC states, and the bytes."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

    from protocol.auth import Keyring
    from protocol.codec import Codec
    from protocol.messages import ActuatorCommand
    from protocol.signing import Signer

    seed = tp_signing_seed(bytes(range(32, 64)), 7)
    public = Ed25519PrivateKey.from_private_bytes(seed).public_key().public_bytes_raw()
    assert f"`{seed.hex()}`" in section and f"`{public.hex()}`" in section
    blocks = re.findall(r"```text\n(.*?)```", section, re.S)
    tail = bytes.fromhex("".join(line.split("|")[0][6:] for line in blocks[1].splitlines()))
    signed = vector[:3] + bytes([TP_SIGNED | TP_SIGNATURE]) + vector[4:-16] + tail
    ours = Codec(Keyring({1: bytes(range(32))}, 1)).encode(
        b"ACTUATOR_COMMAND", ActuatorCommand(0.25, 0.0, -0.125, ""), 7, *_VECTOR_HEADER, Signer(7, seed)
    )
    assert signed == ours and len(signed) == 162
    msg = tp_open(signed, {1: bytes(range(32))})
    Ed25519PublicKey.from_public_bytes(public).verify(msg.signature, msg.signed_part)
    assert tp_decode_body(schema, msg.type_id, msg.body)["steering_rad"] == -0.125


_VECTOR_HEADER = (1_700_000_000_000_000, 1_700_000_000_000_000_000, 1_700_000_000_002_000_000)


def test_a_third_party_command_signature_passes_an_enforcing_node(capture: Capture, schema: TpSchema) -> None:
    """Signed as SPEC.md says (seed by the KDF, Ed25519 over header, channel and body), a command
    from the source with authority is accepted by a node holding a module key file; the same
    command unsigned, or signed by a source without authority, is rejected as unauthorized."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    from protocol.auth import Keyring
    from protocol.authority import Authority
    from protocol.transport import MemTransport
    from rascal.runtime.bus import Bus
    from rascal.runtime.clock import ManualClock

    keys, active = tp_load_keys(capture.directory / "bus.key")
    master = Keyring(keys, active, random.randbytes(32))
    table = {"ACTUATOR_COMMAND": [40], "STOP": [], "PATH": [], "CONFIG": [], "TIME_SYNC": [1]}
    hub = f"spec-thirdparty-authority-{random.getrandbits(64):x}"
    clock = ManualClock()
    bus = Bus(MemTransport(hub), 5, master.for_module(5, Authority.derive(table, master.signing_master)), clock)
    received: list[Any] = []
    bus.subscribe("ACTUATOR_COMMAND", lambda msg, env: received.append((msg, env.source_id)))
    wire = MemTransport(hub)
    command = {"throttle": 0.5, "brake": 0.0, "steering_rad": 0.1, "stop_reason": "", "reverse": False}
    for seq, (source_id, signer) in enumerate([(40, 40), (40, None), (41, 41), (40, 41)], start=1):
        sign = (
            Ed25519PrivateKey.from_private_bytes(tp_signing_seed(master.signing_master, signer)).sign
            if signer
            else None
        )
        header = {"source_id": source_id, "seq": seq, "t_meas_ns": clock.now_ns(), "t_pub_ns": clock.now_ns()}
        wire.send(
            "ACTUATOR_COMMAND",
            tp_encode(schema, "ACTUATOR_COMMAND", command, **header, key=keys[active], key_id=active, sign=sign),
        )
        bus.poll()
    assert [source for _msg, source in received] == [40]
    assert dict(bus.rejects) == {(40, "unauthorized"): 2, (41, "unauthorized"): 1}


def test_port_mapping_matches_the_transport(schema: TpSchema) -> None:
    from protocol.transport import UdpConfig

    config = UdpConfig("239.255.76.67", 7667)
    assert schema.channels
    for channel in schema.channels:
        assert tp_port(channel) == config.port(channel)


def test_third_party_code_imports_nothing_from_the_project() -> None:
    """Module-level imports are stdlib, msgpack and pytest; tp_* code has no imports of its own."""
    tree = ast.parse(Path(__file__).read_text())
    allowed = set(sys.stdlib_module_names) | {"msgpack", "pytest", "__future__"}
    for node in tree.body:
        if isinstance(node, ast.Import):
            assert {alias.name.split(".")[0] for alias in node.names} <= allowed
        elif isinstance(node, ast.ImportFrom):
            assert (node.module or "").split(".")[0] in allowed
    third_party = [
        n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.ClassDef)) and n.name.lower().startswith("tp")
    ]
    assert len(third_party) > 10
    for node in third_party:
        assert not [n for n in ast.walk(node) if isinstance(n, (ast.Import, ast.ImportFrom))], node.name
        names = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}
        assert not names & {"protocol", "rascal", "render_message_types", "_plain", "Capture"}, node.name


if __name__ == "__main__":
    if sys.argv[1:] == ["--write"]:
        SPEC_PATH.write_text(write_generated(SPEC_PATH.read_text()))
    else:
        for name, render in RENDERERS.items():
            print(f"<!-- generated:{name} -->\n{render()}\n<!-- /generated:{name} -->\n")
