"""No truth leaks: only the simulator (its simulated sensors included) and the referee may read
the simulator's truth.

Estimation, planning and control must work from sensors alone, or the simulated drive proves
nothing. This scans every source file outside the allowed packages for any reference to the
truth channel or message type (names, attributes and string literals alike).
"""

from __future__ import annotations

import ast
from pathlib import Path

from tests.conftest import ROOT

TRUTH_NAMES = {"SIM_TRUTH", "SimTruth"}
ALLOWED = {
    Path("protocol"),  # where the channel and type are declared
    Path("modules/sim"),  # the simulator publishes the truth, and its simulated sensors measure it
    Path("modules/referee"),  # judges the drive against the truth
    Path("rascal/report_data.py"),  # the run report draws the true track beside the estimate, after the drive
}
CHECKED = ("brain", "esvs_client", "modules", "rascal")


def truth_references(path: Path, root: Path = ROOT) -> list[str]:
    return [
        f"{path.relative_to(root)}:{getattr(node, 'lineno', '?')} {_name_of(node)}"
        for node in ast.walk(ast.parse(path.read_text(), str(path)))
        if _name_of(node) in TRUTH_NAMES
    ]


def _name_of(node: ast.AST) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    if isinstance(node, ast.alias):
        return node.name.rsplit(".", 1)[-1]
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    return None


def test_only_the_simulator_and_simulated_sensors_touch_the_truth() -> None:
    leaks = []
    for top in CHECKED:
        for path in sorted((ROOT / top).rglob("*.py")):
            relative = path.relative_to(ROOT)
            if not any(relative.is_relative_to(allowed) for allowed in ALLOWED):
                leaks += truth_references(path)
    assert leaks == [], "truth read outside the simulator and simulated sensors:\n" + "\n".join(leaks)


def test_the_scan_would_see_a_subscription(tmp_path: Path) -> None:
    planted = tmp_path / "planner.py"
    planted.write_text(
        "from protocol import channels\n\ndef peek(bus):\n    bus.subscribe(channels.SIM_TRUTH, print)\n"
    )
    assert truth_references(planted, tmp_path) == ["planner.py:4 SIM_TRUTH"]
