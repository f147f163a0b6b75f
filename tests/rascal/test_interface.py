"""`rascal interface list | show`: a type's fields with wire types, units, enums, fingerprint and channels."""

from __future__ import annotations

import json

import pytest

from protocol.schema import registered
from rascal.cli import main
from rascal.interface import unit_of


def test_show_gives_fields_units_enums_fingerprint_and_channels(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["interface", "show", "ObstacleList"]) == 0
    out = capsys.readouterr().out
    assert "fingerprint 85175bc0e15949c0" in out and "OBSTACLES_LIDAR, OBSTACLES_ESVS, OBSTACLES_BEACON" in out
    assert "enum Sensor: UNKNOWN=0" in out and "LIDAR_SWEEP=8" in out and "enum Frame: VEHICLE=0, ENU=1" in out
    assert "[Obstacle]  obstacles" in out and "    float64  yaw_rad     # rad" in out


def test_show_json_by_channel_name(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["interface", "show", "path", "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["type"] == "Path" and shown["channels"] == ["PATH"]
    fields = {field["name"]: field for field in shown["fields"]}
    assert fields["t_input_ns"]["unit"] == "ns" and fields["t_input_ns"]["default"] == 0
    assert "default" not in fields["path_id"]
    assert [point["unit"] for point in fields["points"]["fields"]] == ["m", "m", "m/s"]


def test_list_names_every_registered_type(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["interface", "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[1] for line in lines] == [info.cls.__name__ for info in registered()]
    assert any(line.split()[-1] == "MAP_SNAPSHOT" for line in lines)


@pytest.mark.parametrize(
    "field, unit",
    [
        ("accel_x_mps2", "m/s²"),
        ("gyro_z_radps", "rad/s"),
        ("speed_mps", "m/s"),
        ("c2_per_m", "1/m"),
        ("lat_deg", "deg"),
        ("cpu_pct", "%"),
        ("uptime_s", "s"),
        ("x_m", "m"),
        ("confidence", ""),
    ],
)
def test_units_come_from_the_field_names(field: str, unit: str) -> None:
    assert unit_of(field) == unit
