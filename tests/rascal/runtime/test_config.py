"""Module configuration: typed, strict, self-describing."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import pytest

from rascal.runtime.config import (
    FINITE,
    ConfigError,
    build_config,
    describe,
    flatten_values,
    merge_values,
    parse_assignments,
    required,
    section,
    setting,
)


@dataclass(frozen=True)
class FilterSection:
    gain: float = setting(0.5, "how much a sample moves the estimate")
    taps: int = setting(4, "samples averaged")

    def __post_init__(self) -> None:
        if not 0 < self.gain <= 1:
            raise ValueError(f"gain must be in (0, 1], got {self.gain}")


@dataclass(frozen=True)
class ExampleConfig:
    rate_hz: float = setting(10.0, "publication rate")
    count: int = setting(3, "how many")
    enabled: bool = setting(True, "on or off")
    channels: tuple[str, ...] = setting(("A",), "channels")
    filter: FilterSection = section(FilterSection, "the smoothing filter")


def test_defaults_apply_when_nothing_is_given() -> None:
    assert build_config(ExampleConfig, {}) == ExampleConfig()


def test_unknown_key_is_rejected_by_name() -> None:
    with pytest.raises(ConfigError, match=r"beacon\.toml\.rate: unknown key; known: \['channels'"):
        build_config(ExampleConfig, {"rate": 5.0}, "beacon.toml")


def test_wrong_type_is_rejected_naming_the_field() -> None:
    with pytest.raises(ConfigError, match=r"beacon\.toml\.count: expected an integer, got 'three'"):
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


def test_a_section_is_a_sub_table_or_dotted_keys_and_keeps_what_is_not_overridden() -> None:
    from_file = {"rate_hz": 5.0, "filter": {"gain": 0.25, "taps": 8}}
    overrides = parse_assignments(ExampleConfig, ["filter.taps=2", "count=1"])
    assert overrides == {"filter": {"taps": 2}, "count": 1}
    config = build_config(ExampleConfig, merge_values(from_file, overrides))
    assert config.filter == FilterSection(gain=0.25, taps=2) and config.rate_hz == 5.0 and config.count == 1
    assert build_config(ExampleConfig, {}).filter == FilterSection()
    assert flatten_values(from_file) == {"rate_hz": 5.0, "filter.gain": 0.25, "filter.taps": 8}


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"filter": {"gains": 1.0}}, r"beacon\.toml\.filter\.gains: unknown key"),
        ({"filter": {"taps": "four"}}, r"beacon\.toml\.filter\.taps: expected an integer"),
        ({"filter": 3}, r"beacon\.toml\.filter: expected a table of FilterSection settings"),
        ({"filter": {"gain": 2.0}}, r"beacon\.toml\.filter: gain must be in \(0, 1\], got 2\.0"),
    ],
)
def test_a_sections_mistakes_name_the_section_and_key(values: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        build_config(ExampleConfig, values, "beacon.toml")


@pytest.mark.parametrize(
    ("assignment", "message"),
    [
        ("filter.gains=1", r"--set filter\.gains: unknown key; known: \['gain', 'taps'\]"),
        ("rate.hz=1", r"--set rate\.hz: 'rate' is not a section; sections: \['filter'\]"),
        ("filter=1", r"--set filter: unknown key"),
    ],
)
def test_dotted_assignments_name_what_is_wrong(assignment: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_assignments(ExampleConfig, [assignment])


def test_description_lists_a_sections_fields_under_dotted_names() -> None:
    lines = describe(ExampleConfig, build_config(ExampleConfig, {"filter": {"taps": 6}})).splitlines()
    assert [line.split()[0] for line in lines][-2:] == ["filter.gain", "filter.taps"]
    assert "6" in lines[-1].split()[2] and "samples averaged" in lines[-1]


class Direction(enum.Enum):
    NORTH = "north"
    SOUTH = "south"


@dataclass(frozen=True, kw_only=True)
class PlacedTable:
    """A hand-written file's table (deployments, scenarios): required, ranged, a choice, named tables."""

    heading: Direction = setting(Direction.NORTH, "which way it faces")
    height_m: float = required("how tall", within=(0.0, 50.0))
    offset_m: float = setting(0.0, "sideways", within=FINITE)
    filters: dict[str, FilterSection] = setting({}, "named filters")


def test_a_hand_written_tables_fields_are_read_by_their_declaration() -> None:
    values = {"height_m": 2, "heading": "south", "filters": {"a": {"taps": 2}}}
    placed = PlacedTable(height_m=2.0, heading=Direction.SOUTH, filters={"a": FilterSection(taps=2)})
    assert build_config(PlacedTable, values, "") == placed


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({}, r"^height_m: missing$"),
        ({"height_m": 60}, r"^height_m: expected 0\.\.50, got 60$"),
        ({"height_m": 1, "offset_m": math.nan}, r"^offset_m: expected a finite number, got nan$"),
        ({"height_m": 1, "heading": "up"}, r"^heading: 'up' is not one of \['north', 'south'\]$"),
        ({"height_m": 1, "filters": {"a": {"taps": "x"}}}, r"^filters\.a\.taps: expected an integer, got 'x'$"),
    ],
)
def test_a_hand_written_tables_mistakes_name_the_key(values: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        build_config(PlacedTable, values, "")
