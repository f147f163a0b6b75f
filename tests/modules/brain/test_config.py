"""Every planner, fusion and cost setting can be set from a deployment file, shows in
--print-config, and is the one the running brain plans with."""

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
from rascal.runtime.launch import load_module_config
from rascal.runtime.module import Runtime

SECTIONS = [f for f in dataclasses.fields(BrainConfig) if is_section(typing.get_type_hints(BrainConfig)[f.name])]


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


def section_fields() -> list[tuple[str, Any]]:
    defaults = BrainConfig()
    return [leaf for section in SECTIONS for leaf in leaves(f"{section.name}.", getattr(defaults, section.name))]


def toml_value(value: Any) -> str:
    """A setting's value as TOML: JSON's numbers, strings, booleans and arrays are TOML's, and
    TOML spells infinity inf."""
    if isinstance(value, float) and math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return json.dumps(list(value) if isinstance(value, tuple) else value)


def test_the_brain_has_the_three_sections() -> None:
    assert sorted(section.name for section in SECTIONS) == ["cost", "fusion", "planner"]
    assert len(section_fields()) > 100


def test_every_section_setting_is_listed_by_print_config() -> None:
    listed = {line.split()[0] for line in describe(BrainConfig, BrainConfig()).splitlines()}
    assert [name for name, _ in section_fields() if name not in listed] == []


def test_every_section_setting_can_be_set_from_a_deployment_file(tmp_path: Path) -> None:
    """A deployment with every planner, fusion and cost setting written out at its default value:
    it loads, the brain is launched with each as a dotted --set, and those build the default
    config back."""
    (tmp_path / "course.rddf").write_text("1,35.0,-117.0,30,10\n2,35.0,-116.99,30,10\n")
    settings = "\n".join(f"{name} = {toml_value(value)}" for name, value in section_fields())
    path = tmp_path / "deploy.toml"
    path.write_text(
        '[deployment]\nname = "tuned"\nbus = "udpm://239.255.1.2:7700?ttl=0"\ncourse = "course.rddf"\n\n'
        f"[modules.time_service]\n\n[modules.brain]\n\n[modules.brain.set]\n{settings}\n"
    )
    spec = load_deployment(path).spec("brain")
    for name, _ in section_fields():
        assert name in spec.settings
    config = load_module_config(Brain, None, [f"{key}={text}" for key, text in spec.settings.items()])
    defaults = BrainConfig()
    for section in SECTIONS:
        assert getattr(config, section.name) == getattr(defaults, section.name)


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
