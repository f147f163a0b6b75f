"""Each module declares its interface once: its README carries the generated table, and the bus
channels its code names are the ones it declares."""

from __future__ import annotations

import inspect
import re
import subprocess
import sys
from pathlib import Path

import pytest

from protocol import channels
from rascal.runtime.launch import module_class
from rascal.runtime.ports import Port, interface_table

ROOT = Path(__file__).resolve().parents[3]
MODULES = sorted(path.parent.name for path in (ROOT / "modules").glob("*/__main__.py"))
# What the runtime sends for every module (heartbeats, report()) and for the time master.
RUNTIME_CHANNELS = {channels.MODULE_STATUS, channels.HEALTH, channels.TIME_SYNC}
CHANNEL_NAMES = {name for name in dir(channels) if name.isupper() and isinstance(getattr(channels, name), str)}


def channels_named_in_code(name: str) -> set[str]:
    """The channels named in the module class's own folder (a simulated sensor's process lives
    in the simulator's: modules/sim/lidar/process.py for ``lidar``)."""
    folder = Path(inspect.getsourcefile(module_class(name)) or "").parent
    found: set[str] = set()
    for source in folder.glob("*.py"):
        found |= set(re.findall(r"\bchannels\.([A-Z][A-Z0-9_]*)\b", source.read_text()))
    return {getattr(channels, constant) for constant in found & CHANNEL_NAMES}


def test_every_process_has_an_interface_and_a_readme() -> None:
    assert len(MODULES) >= 12
    for name in MODULES:
        assert module_class(name).interface, f"modules.{name} declares no interface"
        assert (ROOT / "modules" / name / "README.md").exists(), f"modules/{name} has no README"


@pytest.mark.parametrize("name", MODULES)
def test_the_readme_carries_the_declared_table(name: str) -> None:
    table = interface_table(module_class(name).interface)
    readme = (ROOT / "modules" / name / "README.md").read_text()
    assert table in readme, f"modules/{name}/README.md: replace its table with `rascal module {name} --interface`"


@pytest.mark.parametrize("name", MODULES)
def test_the_code_names_the_channels_declared(name: str) -> None:
    declared = {channel for port in module_class(name).interface for channel in port.bus_channels}
    unknown = declared - set(channels.CHANNEL_TYPES)
    assert not unknown, f"not bus channels: {sorted(unknown)}"
    in_code = channels_named_in_code(name)
    assert in_code - declared == set(), "named in the code but not declared"
    assert declared - in_code <= RUNTIME_CHANNELS, "declared but not named in the code"


def test_the_interface_is_printed_by_the_command_line() -> None:
    printed = subprocess.run(
        [sys.executable, "-m", "modules.ins", "--interface"], capture_output=True, text=True, check=True, cwd=ROOT
    ).stdout
    assert printed.strip() == interface_table(module_class("ins").interface)


def test_a_port_is_one_table_row() -> None:
    port = Port("in", "`PATH` (the planner's)", "Path", "10 Hz")
    assert port.bus_channels == ("PATH",) and port.max_age == "—"
    assert interface_table([port]).splitlines()[-1] == "| in | `PATH` (the planner's) | Path | 10 Hz | — |"
    for bad in ({"direction": "both"}, {"carries": "a | b"}, {"rate": ""}):
        with pytest.raises(ValueError):
            Port(**({"direction": "in", "channel": "`PATH`", "carries": "Path", "rate": "10 Hz"} | bad))  # type: ignore[arg-type]


SIMULATED_PROCESSES = ["modules.sim.lidar.process", "modules.sim.camera.process", "modules.sim.nav.process"]


@pytest.mark.parametrize("process", SIMULATED_PROCESSES)
def test_a_simulated_process_imports_first_without_a_cycle(process: str) -> None:
    """The integration stack imports the lidar's process before its package: a fresh interpreter
    importing each process module first, then its package's MODULE, must not meet a cycle."""
    package = {"lidar": "modules.lidar", "camera": "modules.stereo_camera", "nav": "modules.nav_sensors"}
    name = package[process.split(".")[2]]
    code = f"import {process}; from {name} import MODULE; print(MODULE.name)"
    subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
