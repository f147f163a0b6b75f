"""The vehicle is declared once: a deployment's [vehicle] table reaches the simulator, control, the
planner and the referee, and a mistake in it is named as the table's."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest

from brain.vehicle import VehicleGeometry
from rascal.runtime.deployment import DeploymentError, load_deployment
from rascal.runtime.launch import load_module_config, module_class

HOLDERS = {"sim": "vehicle", "control": "vehicle", "brain": "planner.vehicle", "referee": "vehicle"}


def deployment(tmp_path: Path, vehicle: str, control_set: str = "") -> Path:
    (tmp_path / "course.rddf").write_text("1,35.0,-117.0,30,10\n2,35.0,-116.99,30,10\n")
    path = tmp_path / "deploy.toml"
    modules = "\n".join(f"[modules.{label}]" for label in ("time_service", *HOLDERS))
    path.write_text(
        '[deployment]\nname = "wide"\nbus = "udpm://239.255.1.2:7700?ttl=0"\ncourse = "course.rddf"\n\n'
        f"[vehicle]\n{vehicle}\n\n{modules}\n".replace("[modules.control]", f"[modules.control]\n{control_set}")
    )
    return path


def vehicle_of(label: str, path: Path) -> Any:
    spec = load_deployment(path).spec(label)
    config: Any = load_module_config(module_class(spec.module), None, [f"{k}={v}" for k, v in spec.settings.items()])
    for name in HOLDERS[label].split("."):
        config = getattr(config, name)
    return config


def test_one_vehicle_table_sets_every_module_that_holds_the_vehicle(tmp_path: Path) -> None:
    path = deployment(tmp_path, "width_m = 1.4\nwheelbase_m = 1.5")
    wide = VehicleGeometry(width_m=1.4, wheelbase_m=1.5)
    assert {label: vehicle_of(label, path) for label in HOLDERS} == dict.fromkeys(HOLDERS, wide)
    assert "vehicle.width_m" not in load_deployment(path).spec("time_service").settings


def test_a_modules_own_setting_overrides_the_table(tmp_path: Path) -> None:
    path = deployment(tmp_path, "width_m = 1.4", control_set="set = { vehicle.wheelbase_m = 1.3 }")
    assert vehicle_of("control", path) == VehicleGeometry(width_m=1.4, wheelbase_m=1.3)
    assert vehicle_of("sim", path) == VehicleGeometry(width_m=1.4)


@pytest.mark.parametrize(
    ("vehicle", "message"),
    [
        ("widht_m = 1.4", r"deploy\.toml: vehicle\.widht_m: unknown key"),
        ("rear_overhang_m = 3.0", r"deploy\.toml: vehicle: vehicle\.rear_overhang_m: must be shorter than length_m"),
        ('width_m = "wide"', r"deploy\.toml: vehicle\.width_m: expected a number"),
    ],
)
def test_a_mistake_in_the_table_is_named_as_the_tables(tmp_path: Path, vehicle: str, message: str) -> None:
    with pytest.raises(DeploymentError, match=message):
        load_deployment(deployment(tmp_path, vehicle))


def test_the_geometry_refuses_what_no_vehicle_has() -> None:
    for changes in ({"width_m": 0.0}, {"max_steering_rad": 1.6}, {"wheelbase_m": float("nan")}):
        with pytest.raises(ValueError, match="vehicle"):
            dataclasses.replace(VehicleGeometry(), **changes)
    vehicle = VehicleGeometry()
    assert vehicle.front_m == pytest.approx(1.7) and vehicle.half_width_m == pytest.approx(0.6)
