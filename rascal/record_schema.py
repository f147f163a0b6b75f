"""What a recording says about each message type: a JSON Schema for the decoded JSON channel
(Foxglove reads ``jsonschema``) and channel metadata naming the wire layout of the raw channel.

Both are generated from the NamedTuple declarations in ``protocol.messages``, so they cannot
drift from the wire. The JSON form: records as objects, sequences as arrays, ``bytes`` as base64
(``contentEncoding`` ``base64``, which Foxglove decodes), and the integer fields that carry an
enum (:data:`ENUM_FIELDS`) as the member's name, or the number as text for a value this build
does not name. :func:`json_converter` compiles it per type because the twins convert every message.
"""

from __future__ import annotations

import base64
import enum
import inspect
import json
import typing
from collections.abc import Callable
from typing import Any

import protocol.messages  # noqa: F401  (registers every message type this build knows)
from protocol.errors import ProtocolError
from protocol.messages import (
    Frame,
    GpsFix,
    GroundSweep,
    HealthEvent,
    LaneBorders,
    ModuleState,
    ModuleStatus,
    NavQuality,
    ObstacleList,
    Sensor,
    Severity,
    StopCommand,
    StopMode,
    SurfaceProfile,
    TimeSync,
    TimeSyncKind,
    VehicleState,
)
from protocol.schema import describe_type, info_for_id
from rascal.runtime.timesync import SyncState

RAW_ENCODING = "rascal-v1"  # message_encoding of the raw channels: whole signed messages (SPEC.md)
JSON_ENCODING = "json"
JSON_SCHEMA_ENCODING = "jsonschema"
JSON_TOPIC_SUFFIX = ".json"
SCHEMA_PREFIX = "rascal."

_SCALAR_SCHEMAS: dict[type, dict[str, Any]] = {
    float: {"type": "number"},
    int: {"type": "integer"},
    bool: {"type": "boolean"},
    str: {"type": "string"},
    bytes: {"type": "string", "contentEncoding": "base64"},
}
# The wire declares these as int (protocol/messages.py names the enum in a comment).
ENUM_FIELDS: dict[tuple[type, str], type[enum.IntEnum]] = {
    (TimeSync, "kind"): TimeSyncKind,
    (ModuleStatus, "state"): ModuleState,
    (ModuleStatus, "clock_state"): SyncState,
    (HealthEvent, "severity"): Severity,
    (GpsFix, "quality"): NavQuality,
    (VehicleState, "quality"): NavQuality,
    (ObstacleList, "sensor"): Sensor,
    (ObstacleList, "frame"): Frame,
    (SurfaceProfile, "sensor"): Sensor,
    (GroundSweep, "sensor"): Sensor,
    (LaneBorders, "sensor"): Sensor,
    (StopCommand, "mode"): StopMode,
}


def enum_schema(kind: type[enum.IntEnum]) -> dict[str, Any]:
    """A member's name, or an unnamed value as decimal text (a peer may be newer than us)."""
    names = "|".join(member.name for member in kind)
    return {"type": "string", "title": kind.__name__, "pattern": f"^({names}|-?[0-9]+)$"}


def enum_converter(kind: type[enum.IntEnum]) -> Callable[[int], str]:
    names = {member.value: member.name for member in kind}
    return lambda value: names.get(value) or str(value)


def _b64(value: bytes) -> str:
    return base64.b64encode(value).decode("ascii")


def _field_schema(tp: type, name: str, hint: Any) -> dict[str, Any]:
    kind = ENUM_FIELDS.get((tp, name))
    return enum_schema(kind) if kind is not None else json_schema(hint)


def _field_converter(tp: type, name: str, hint: Any) -> Callable[[Any], Any] | None:
    kind = ENUM_FIELDS.get((tp, name))
    return enum_converter(kind) if kind is not None else json_converter(hint)


def json_schema(tp: Any) -> dict[str, Any]:
    """JSON Schema (draft 2020-12 vocabulary) of the JSON form of a wire type."""
    if tp in _SCALAR_SCHEMAS:
        return dict(_SCALAR_SCHEMAS[tp])
    if typing.get_origin(tp) is tuple:
        (item, _ellipsis) = typing.get_args(tp)
        return {"type": "array", "items": json_schema(item)}
    if isinstance(tp, type) and issubclass(tp, tuple) and hasattr(tp, "_fields"):
        hints = typing.get_type_hints(tp)
        defaults = tp._field_defaults  # type: ignore[attr-defined]
        schema: dict[str, Any] = {
            "title": tp.__name__,
            "type": "object",
            "properties": {name: _field_schema(tp, name, hints[name]) for name in tp._fields},  # type: ignore[attr-defined]
            "required": [name for name in tp._fields if name not in defaults],  # type: ignore[attr-defined]
            "additionalProperties": False,
        }
        doc = inspect.getdoc(tp)
        if doc and not doc.startswith(f"{tp.__name__}("):  # NamedTuple's generated docstring says nothing
            schema["description"] = doc
        return schema
    raise TypeError(f"unsupported wire type {tp!r}")


def json_converter(tp: Any) -> Callable[[Any], Any] | None:
    """A function turning a decoded value of wire type ``tp`` into its JSON form, or None where
    ``json.dumps`` takes the value as it is (numbers, strings, sequences of them)."""
    if tp in (float, int, bool, str):
        return None
    if tp is bytes:
        return _b64
    if typing.get_origin(tp) is tuple:
        (item, _ellipsis) = typing.get_args(tp)
        convert_item = json_converter(item)
        if convert_item is None:
            return None
        return lambda values: [convert_item(value) for value in values]
    if isinstance(tp, type) and issubclass(tp, tuple) and hasattr(tp, "_fields"):
        hints = typing.get_type_hints(tp)
        names: tuple[str, ...] = tp._fields  # type: ignore[attr-defined]
        converters = [_field_converter(tp, name, hints[name]) for name in names]
        if not any(converters):
            return lambda record: dict(zip(names, record, strict=True))
        pairs = list(zip(names, converters, strict=True))
        return lambda record: {
            name: value if convert is None else convert(value)
            for (name, convert), value in zip(pairs, record, strict=True)
        }
    raise TypeError(f"unsupported wire type {tp!r}")


def message_schema_bytes(type_id: int) -> tuple[str, bytes]:
    """(schema name, schema document) of a registered message type, for ``register_schema``."""
    cls = info_for_id(type_id).cls
    document = {"$schema": "https://json-schema.org/draft/2020-12/schema", **json_schema(cls)}
    return SCHEMA_PREFIX + cls.__name__, json.dumps(document, indent=1).encode()


def raw_channel_metadata(type_id: int) -> dict[str, str]:
    """Metadata of a raw channel: the type id and, when this build knows it, the layout and its
    fingerprint, so a reader can tell which declaration the recorded bodies follow."""
    metadata = {"type_id": str(type_id)}
    try:
        info = info_for_id(type_id)
    except ProtocolError:
        metadata["type"] = "unknown"  # a type newer than this recorder: kept raw, not decoded
        return metadata
    metadata.update(type=info.cls.__name__, fingerprint=info.fingerprint, layout=describe_type(info.cls))
    return metadata


def known_type(type_id: int) -> bool:
    try:
        info_for_id(type_id)
    except ProtocolError:
        return False
    return True
