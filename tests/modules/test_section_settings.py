"""Every setting of a module's sections (the brain's planner, fusion and cost; control's
controller, guard and vehicle; the simulator's and referee's vehicle) can be set from a
deployment file, shows in --print-config, and is the one the running module uses."""

from __future__ import annotations

import dataclasses
import json
import math
import typing
import uuid
from pathlib import Path
from typing import Any

import pytest

from modules.brain.module import Brain, BrainConfig
from protocol.auth import Keyring
from protocol.transport import MemTransport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from rascal.runtime.config import describe, is_section
from rascal.runtime.deployment import load_deployment
from rascal.runtime.launch import load_module_config, module_class
from rascal.runtime.module import Runtime

SECTIONED = {"brain": ["cost", "fusion", "planner"], "control": ["controller", "guard", "vehicle"]}
SECTIONED |= {"sim": ["vehicle"], "referee": ["vehicle"]}


def sections(config_class: type) -> list[str]:
    hints = typing.get_type_hints(config_class)
    return sorted(f.name for f in dataclasses.fields(config_class) if is_section(hints[f.name]))


def leaves(prefix: str, config: Any) -> list[tuple[str, Any]]:
    """Every setting under a section, at any depth: (dotted name, default value)."""
    found: list[tuple[str, Any]] = []
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if dataclasses.is_dataclass(value):
            found += leaves(f"{prefix}{field.name}.", value)
        else:
            found.append((f"{prefix}{field.name}", value))
    return found


def section_settings(label: str) -> list[tuple[str, Any]]:
    defaults = module_class(label).Config()
    return [leaf for name in sections(type(defaults)) for leaf in leaves(f"{name}.", getattr(defaults, name))]


def toml_value(value: Any) -> str:
    """A setting's value as TOML: JSON's numbers, strings, booleans and arrays are TOML's, and
    TOML spells infinity inf."""
    if isinstance(value, float) and math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return json.dumps(list(value) if isinstance(value, tuple) else value)


def test_the_modules_with_sections_are_these() -> None:
    assert {label: sections(module_class(label).Config) for label in SECTIONED} == SECTIONED
    for label in ("ins", "lidar", "nav_sensors", "esvs", "health", "time_service"):
        assert sections(module_class(label).Config) == [], label
    assert len(section_settings("brain")) > 100 and len(section_settings("control")) > 25


@pytest.mark.parametrize("label", sorted(SECTIONED))
def test_every_section_setting_is_listed_by_print_config(label: str) -> None:
    config_class = module_class(label).Config
    listed = {line.split()[0] for line in describe(config_class, config_class()).splitlines()}
    assert [name for name, _ in section_settings(label) if name not in listed] == []


@pytest.mark.parametrize("label", sorted(SECTIONED))
def test_every_section_setting_can_be_set_from_a_deployment_file(tmp_path: Path, label: str) -> None:
    """A deployment with every section setting written out at its default value: it loads, the
    module is launched with each as a dotted --set, and those build the default config back."""
    (tmp_path / "course.rddf").write_text("1,35.0,-117.0,30,10\n2,35.0,-116.99,30,10\n")
    settings = "\n".join(f"{name} = {toml_value(value)}" for name, value in section_settings(label))
    path = tmp_path / "deploy.toml"
    path.write_text(
        '[deployment]\nname = "tuned"\nbus = "udpm://239.255.1.2:7700?ttl=0"\ncourse = "course.rddf"\n\n'
        f"[modules.time_service]\n\n[modules.{label}]\n\n[modules.{label}.set]\n{settings}\n"
    )
    spec = load_deployment(path).spec(label)
    assert [name for name, _ in section_settings(label) if name not in spec.settings] == []
    config_class = module_class(label).Config
    config = load_module_config(module_class(label), None, [f"{key}={text}" for key, text in spec.settings.items()])
    for name in sections(config_class):
        assert getattr(config, name) == getattr(config_class(), name)


@pytest.mark.parametrize(
    ("assignment", "section", "name", "value"),
    [
        ("planner.margin_m=0.25", "planner", "margin_m", 0.25),
        ("fusion.sweep_half_life_s=120", "fusion", "sweep_half_life_s", 120.0),
        ("cost.hazard_threshold=0.85", "cost", "hazard_threshold", 0.85),
    ],
)
def test_the_running_brain_plans_with_the_settings_given(assignment: str, section: str, name: str, value: Any) -> None:
    config = load_module_config(Brain, None, [assignment])
    clock = MasterClock()
    brain = Brain(config, Runtime(Bus(MemTransport(uuid.uuid4().hex), 30, Keyring.generate(), clock), clock))
    brain.on_start()
    used = {"planner": brain.planner.config, "fusion": brain.fusion.config, "cost": brain.fusion.cost_config}
    assert getattr(used[section], name) == value
    assert used[section] == dataclasses.replace(getattr(BrainConfig(), section), **{name: value})
