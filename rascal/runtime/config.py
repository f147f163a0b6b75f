"""Typed module configuration: dataclasses with defaults and units, strict loading.

Every module declares a frozen dataclass; each field has a default and a ``help`` metadata
string. A field whose type is itself such a dataclass is a section (the brain's ``planner``,
``fusion`` and ``cost``): a TOML sub-table, or dotted keys (``--set planner.margin_m=0.2``).
Loading rejects unknown keys, wrong types, missing required fields and values outside a field's
declared range by name, a section's own checks (``__post_init__``) report as configuration errors
too, and ``--print-config`` is generated from the same declaration, sections included, so it cannot
drift. Hand-written files (deployments, scenarios) declare their tables the same way and are
checked by the same code, so a mistake reads the same wherever it is made: ``where.key: problem``
(their loaders put the file's name in front).
"""

from __future__ import annotations

import dataclasses
import enum
import math
import types
import typing
from typing import Any, TypeGuard, TypeVar

C = TypeVar("C")
T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value or key that cannot be used; the message names it."""


# A ``within`` for numbers that have no bounds but must be finite (no nan or inf from a file).
FINITE = (-math.inf, math.inf)


def setting(default: Any, help: str, within: tuple[float, float] | None = None) -> Any:
    """A config field with its default and a one-line description (units in the field name);
    ``within``: the inclusive range a given number must be in (finite, too)."""
    metadata = _metadata(help, within)
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def required(help: str, within: tuple[float, float] | None = None) -> Any:
    """A config field with no default: loading fails naming it when it is not given (its class
    needs ``kw_only=True`` when fields with defaults come before it)."""
    return dataclasses.field(metadata=_metadata(help, within))


def _metadata(help: str, within: tuple[float, float] | None) -> dict[str, Any]:
    return {"help": help} if within is None else {"help": help, "within": within}


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
        raise ConfigError(f"{_key(where, unknown[0])}: unknown key; known: {sorted(fields)}")
    for f in fields.values():
        if f.name not in values and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{_key(where, f.name)}: missing")
    hints = typing.get_type_hints(cls)
    checked = {}
    for name, value in values.items():
        checked[name] = _coerce(hints[name], value, _key(where, name))
        if "within" in fields[name].metadata and value is not None:
            low, high = fields[name].metadata["within"]
            check_range(value, low, high, _key(where, name))  # the value as written: "got 60", not 60.0
    try:
        return cls(**checked)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


def check_range(value: float, low: float, high: float, where: str) -> None:
    """``value`` finite and in ``low..high``, else a ConfigError naming ``where``; for a field's
    declared ``within`` and for ranges known only while loading (a place along the course)."""
    if not (math.isfinite(value) and low <= value <= high):
        bounds = f">= {low:g}" if high == math.inf else f"<= {high:g}" if low == -math.inf else f"{low:g}..{high:g}"
        raise ConfigError(f"{where}: expected {'a finite number' if (low, high) == FINITE else bounds}, got {value!r}")


def given(value: T | None, where: str) -> T:
    """An optional field that this case requires (a cylinder's radius): a ConfigError if it is absent."""
    if value is None:
        raise ConfigError(f"{where}: missing")
    return value


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


def _key(where: str, name: str) -> str:
    """``name`` under ``where``, dotted; an empty ``where`` is a document's top level."""
    return f"{where}.{name}" if where else name


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


# What a value of each plain type is called in an error ("expected an integer, got 'a'").
_TYPE_WORDS = {int: "an integer", str: "a string", bool: "true or false"}


def _coerce(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(tp)
        if value is None and type(None) in options:
            return None
        tp = next(option for option in options if option is not type(None))
        origin = typing.get_origin(tp)
    if is_section(tp):
        if isinstance(value, tp):
            return value
        if isinstance(value, dict):
            return build_config(tp, value, where)
        raise ConfigError(f"{where}: expected a table of {tp.__name__} settings, got {value!r}")
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        try:
            return tp(value)
        except ValueError:
            raise ConfigError(f"{where}: {value!r} is not one of {[e.value for e in tp]}") from None
    if tp is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if tp in _TYPE_WORDS:
        if type(value) is tp:
            return value
        raise ConfigError(f"{where}: expected {_TYPE_WORDS[tp]}, got {value!r}")
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        (item, *_rest) = typing.get_args(tp) or (Any,)
        coerced = [value_ if item is Any else _coerce(item, value_, f"{where}[{i}]") for i, value_ in enumerate(value)]
        return tuple(coerced) if origin is tuple else coerced
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a table, got {value!r}")
        item = typing.get_args(tp)[1]
        return {k: v if item is Any else _coerce(item, v, _key(where, k)) for k, v in value.items()}
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
