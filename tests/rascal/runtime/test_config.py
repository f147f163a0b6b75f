"""Module configuration: typed, strict, self-describing."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from rascal.runtime.config import ConfigError, build_config, describe, parse_assignments, setting


@dataclass(frozen=True)
class ExampleConfig:
    rate_hz: float = setting(10.0, "publication rate")
    count: int = setting(3, "how many")
    enabled: bool = setting(True, "on or off")
    channels: tuple[str, ...] = setting(("A",), "channels")


def test_defaults_apply_when_nothing_is_given() -> None:
    assert build_config(ExampleConfig, {}) == ExampleConfig()


def test_unknown_key_is_rejected_by_name() -> None:
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['rate'\]"):
        build_config(ExampleConfig, {"rate": 5.0}, "beacon.toml")


def test_wrong_type_is_rejected_naming_the_field() -> None:
    with pytest.raises(ConfigError, match=r"beacon\.toml\.count: expected int"):
        build_config(ExampleConfig, {"count": "three"}, "beacon.toml")


def test_integers_are_accepted_for_float_fields() -> None:
    assert build_config(ExampleConfig, {"rate_hz": 20}).rate_hz == 20.0


def test_assignments_are_parsed_by_declared_type() -> None:
    values = parse_assignments(ExampleConfig, ["rate_hz=2.5", "count=7", "enabled=off", "channels=A,B"])
    assert values == {"rate_hz": 2.5, "count": 7, "enabled": False, "channels": ("A", "B")}


def test_unparseable_assignment_names_the_key() -> None:
    with pytest.raises(ConfigError, match="count"):
        parse_assignments(ExampleConfig, ["count=many"])


def test_description_lists_every_field_with_help() -> None:
    text = describe(ExampleConfig)
    for name in ("rate_hz", "count", "enabled", "channels", "publication rate"):
        assert name in text
