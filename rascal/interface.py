"""`rascal interface list | show TYPE`: the message types of the bus, as `ros2 interface show`.

Everything comes from the declarations in protocol/messages.py (units are the field names'
suffixes) and protocol/channels.py, so it cannot drift from the wire.
"""

from __future__ import annotations

import difflib
import enum
import typing
from typing import Any

from protocol import channels
from protocol.schema import MessageInfo, describe_type, registered
from rascal.record_schema import ENUM_FIELDS

# Longest first: ``_mps2`` before ``_mps``, ``_radps`` before ``_rad``...
UNIT_SUFFIXES = (
    ("_mps2", "m/s²"),
    ("_radps", "rad/s"),
    ("_mps", "m/s"),
    ("_per_m", "1/m"),
    ("_pct", "%"),
    ("_deg", "deg"),
    ("_rad", "rad"),
    ("_ns", "ns"),
    ("_s", "s"),
    ("_m", "m"),
)


def unit_of(field: str) -> str:
    """The unit a field name declares by its suffix, or "" when it declares none."""
    return next((unit for suffix, unit in UNIT_SUFFIXES if field.endswith(suffix)), "")


def channels_of(cls: type) -> list[str]:
    return [name for name, tp in channels.CHANNEL_TYPES.items() if tp is cls]


def find_type(name: str) -> MessageInfo:
    """A registered message type by class name (any case) or by a channel that carries it;
    ValueError naming the nearest ones otherwise."""
    by_name = {info.cls.__name__.lower(): info for info in registered()}
    if name.lower() in by_name:
        return by_name[name.lower()]
    if name.upper() in channels.CHANNEL_TYPES:
        return next(info for info in registered() if info.cls is channels.CHANNEL_TYPES[name.upper()])
    names = [info.cls.__name__ for info in registered()]
    near = difflib.get_close_matches(name, names, n=3, cutoff=0.5)
    hint = f"did you mean {', '.join(near)}?" if near else f"known: {', '.join(names)}"
    raise ValueError(f"unknown message type {name!r}; {hint}")


def _is_record(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, tuple) and hasattr(tp, "_fields")


def fields_of(cls: type) -> list[dict[str, Any]]:
    """Each field: name, wire type, unit, default (absent: required), enum members, and the
    fields of a record it is a sequence of."""
    hints = typing.get_type_hints(cls)
    defaults = cls._field_defaults  # type: ignore[attr-defined]
    described = []
    for name in cls._fields:  # type: ignore[attr-defined]
        hint = hints[name]
        field: dict[str, Any] = {"name": name, "type": describe_type(hint), "unit": unit_of(name)}
        if name in defaults:
            field["default"] = defaults[name]
        kind: type[enum.IntEnum] | None = ENUM_FIELDS.get((cls, name))
        if kind is not None:
            field["enum"] = {"name": kind.__name__, "members": {member.name: member.value for member in kind}}
        item = typing.get_args(hint)[0] if typing.get_origin(hint) is tuple else None
        if _is_record(item):
            field["type"] = f"[{item.__name__}]"
            field["fields"] = fields_of(item)
        described.append(field)
    return described


def describe(info: MessageInfo) -> dict[str, Any]:
    """Everything `interface show` tells about a type, as JSON-ready data."""
    doc = (info.cls.__doc__ or "").strip()
    return {
        "type": info.cls.__name__,
        "type_id": info.type_id,
        "fingerprint": info.fingerprint,
        "channels": channels_of(info.cls),
        "doc": "" if doc.startswith(f"{info.cls.__name__}(") else doc,  # NamedTuple's generated one says nothing
        "fields": fields_of(info.cls),
    }


def show_lines(described: dict[str, Any]) -> list[str]:
    lines = [
        f"{described['type']}  (type id {described['type_id']}, fingerprint {described['fingerprint']})",
        f"channels: {', '.join(described['channels']) or '(none declared)'}",
    ]
    if described["doc"]:
        lines += ["", *described["doc"].splitlines()]
    return [*lines, "", *_field_lines(described["fields"], "")]


def _field_lines(fields: list[dict[str, Any]], indent: str) -> list[str]:
    lines = []
    type_width = max((len(field["type"]) for field in fields), default=0)
    name_width = max((len(field["name"]) for field in fields), default=0)
    for field in fields:
        notes = [field["unit"]] if field["unit"] else []
        if "enum" in field:
            members = ", ".join(f"{name}={value}" for name, value in field["enum"]["members"].items())
            notes.append(f"enum {field['enum']['name']}: {members}")
        if "default" in field:
            notes.append(f"default {field['default']!r}")
        note = f"  # {'; '.join(notes)}" if notes else ""
        lines.append(f"{indent}{field['type']:<{type_width}}  {field['name']:<{name_width}}{note}".rstrip())
        lines += _field_lines(field.get("fields", []), indent + "    ")
    return lines


def list_rows() -> list[dict[str, Any]]:
    return [
        {
            "type": info.cls.__name__,
            "type_id": info.type_id,
            "fingerprint": info.fingerprint,
            "channels": channels_of(info.cls),
        }
        for info in registered()
    ]


def list_lines(rows: list[dict[str, Any]]) -> list[str]:
    return [
        f"{row['type_id']:>5}  {row['type']:<16} {row['fingerprint']}  {', '.join(row['channels'])}".rstrip()
        for row in rows
    ]
