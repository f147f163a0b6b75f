"""Typed module configuration: dataclasses with defaults and units, strict loading.

Every module declares a frozen dataclass; each field has a default and a ``help`` metadata
string. A field whose type is itself such a dataclass is a section (the brain's ``planner``,
``fusion`` and ``cost``): a TOML sub-table, or dotted keys (``--set planner.margin_m=0.2``).
Loading rejects unknown keys and wrong types by name, a section's own checks (``__post_init__``)
report as configuration errors too, and ``--print-config`` is generated from the same declaration,
sections included, so it cannot drift.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, TypeGuard, TypeVar

C = TypeVar("C")


class ConfigError(ValueError):
    """A configuration value or key that cannot be used; the message names it."""


def setting(default: Any, help: str) -> Any:
    """A config field with its default and a one-line description (units in the field name)."""
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata={"help": help})
    return dataclasses.field(default=default, metadata={"help": help})


def section(cls: type, help: str) -> Any:
    """A config field that is a nested config dataclass, at its defaults unless set."""
    if not is_section(cls):
        raise TypeError(f"a section is a config dataclass, not {cls!r}")
    return dataclasses.field(default_factory=cls, metadata={"help": help})


def is_section(tp: Any) -> TypeGuard[type]:
    """Whether a field's type is a nested config dataclass."""
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def build_config(cls: type[C], values: dict[str, Any], where: str = "config") -> C:
    """Instantiate ``cls`` from a mapping (sections from nested mappings), checking every key
    and type; a value the class's own checks refuse is a ConfigError naming where it was set."""
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; known: {sorted(fields)}")
    hints = typing.get_type_hints(cls)
    checked = {name: _coerce(hints[name], value, f"{where}.{name}") for name, value in values.items()}
    try:
        return cls(**checked)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


def parse_assignments(cls: type, assignments: list[str], where: str = "--set") -> dict[str, Any]:
    """``["rate_hz=20", "planner.margin_m=0.2"]`` -> typed values, parsed by each field's declared
    type; a dotted key sets a field of a section (nested mappings, as TOML sub-tables give)."""
    values: dict[str, Any] = {}
    for assignment in assignments:
        key, sep, text = assignment.partition("=")
        if not sep:
            raise ConfigError(f"{where} {assignment!r}: expected KEY=VALUE")
        *sections, name = key.split(".")
        section_cls, target = cls, values
        for section in sections:
            hint = typing.get_type_hints(section_cls).get(section)
            if not is_section(hint):
                raise ConfigError(f"{where} {key}: {section!r} is not a section; sections: {_sections(section_cls)}")
            section_cls, target = hint, target.setdefault(section, {})
        hints = typing.get_type_hints(section_cls)
        if name not in hints or is_section(hints[name]):
            known = sorted(n for n, tp in hints.items() if not is_section(tp))
            raise ConfigError(f"{where} {key}: unknown key; known: {known}, sections: {_sections(section_cls)}")
        target[name] = _parse_text(hints[name], text, f"{where} {key}")
    return values


def merge_values(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """``overrides`` over ``base``, section by section (a --set of one planner field keeps the
    file's other planner settings)."""
    merged = dict(base)
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = merge_values(merged[key], value)
        else:
            merged[key] = value
    return merged


def flatten_values(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mappings as dotted keys: ``{"planner": {"margin_m": 0.2}}`` -> ``{"planner.margin_m": 0.2}``."""
    flat: dict[str, Any] = {}
    for key, value in values.items():
        if isinstance(value, dict):
            flat |= flatten_values(value, f"{prefix}{key}.")
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def describe(cls: type, instance: Any | None = None) -> str:
    """Human-readable listing of a config class: name, type, value, help (for --print-config);
    a section's fields follow under their dotted names."""
    rows = _rows(cls, instance, "")
    width = [max(len(row[i]) for row in rows) for i in range(3)] if rows else [0, 0, 0]
    return "\n".join(
        f"{name:<{width[0]}}  {tname:<{width[1]}}  {value:<{width[2]}}  # {help_text}"
        for name, tname, value, help_text in rows
    )


def _rows(cls: type, instance: Any | None, prefix: str) -> list[tuple[str, str, str, str]]:
    hints = typing.get_type_hints(cls)
    rows = []
    for f in dataclasses.fields(cls):
        value = getattr(instance, f.name) if instance is not None else _default_of(f)
        if is_section(hints[f.name]):
            rows += _rows(hints[f.name], value, f"{prefix}{f.name}.")
        else:
            rows.append((prefix + f.name, _type_name(hints[f.name]), repr(value), f.metadata.get("help", "")))
    return rows


def shared_sections(cls: type, table: str) -> dict[str, type]:
    """The sections of ``cls``, at any depth, whose class is set from the deployment's ``table``
    (its ``deployment_table`` class attribute): dotted path -> section class."""
    found: dict[str, type] = {}
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if not is_section(tp):
            continue
        if getattr(tp, "deployment_table", None) == table:
            found[f.name] = tp
        found |= {f"{f.name}.{path}": inner for path, inner in shared_sections(tp, table).items()}
    return found


def nest(path: str, values: dict[str, Any]) -> dict[str, Any]:
    """``values`` under a dotted section path: ``nest("planner.vehicle", v)`` -> ``{"planner": {"vehicle": v}}``."""
    for name in reversed(path.split(".")):
        values = {name: values}
    return values


def _sections(cls: type) -> list[str]:
    return sorted(name for name, tp in typing.get_type_hints(cls).items() if is_section(tp))


def _default_of(f: dataclasses.Field[Any]) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def _type_name(tp: Any) -> str:
    if typing.get_origin(tp) is not None:
        return str(tp).replace("typing.", "")
    return getattr(tp, "__name__", str(tp))


def _coerce(tp: Any, value: Any, where: str) -> Any:
    if is_section(tp):
        if isinstance(value, tp):
            return value
        if isinstance(value, dict):
            return build_config(tp, value, where)
        raise ConfigError(f"{where}: expected a table of {tp.__name__} settings, got {value!r}")
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(tp)
        if value is None and type(None) in options:
            return None
        tp = next(option for option in options if option is not type(None))
        origin = typing.get_origin(tp)
    if tp is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if tp in (int, str, bool):
        if type(value) is tp:
            return value
        raise ConfigError(f"{where}: expected {tp.__name__}, got {value!r}")
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        (item, *_rest) = typing.get_args(tp) or (Any,)
        coerced = [value_ if item is Any else _coerce(item, value_, f"{where}[{i}]") for i, value_ in enumerate(value)]
        return tuple(coerced) if origin is tuple else coerced
    if tp is float:
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    return value


def _parse_text(tp: Any, text: str, where: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        if text.lower() in ("none", "null", ""):
            return None
        tp = next(option for option in typing.get_args(tp) if option is not type(None))
    try:
        if tp is bool:
            if text.lower() in ("1", "true", "yes", "on"):
                return True
            if text.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(text)
        if tp in (int, float):
            return tp(text)
        if typing.get_origin(tp) in (list, tuple):
            (item, *_rest) = typing.get_args(tp)
            parsed = [_parse_text(item, part.strip(), where) for part in text.split(",") if part.strip()]
            return tuple(parsed) if typing.get_origin(tp) is tuple else parsed
    except ValueError:
        raise ConfigError(f"{where}: cannot read {text!r} as {_type_name(tp)}") from None
    return text
