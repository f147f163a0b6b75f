"""The tree's layers and what each may import (an import-rules test, as the truth-leak test is):

- ``protocol/``: the wire. Nothing else of ours.
- ``rascal/runtime/``: the bus, shared time, the module loop and launcher, configuration and
  deployments. The protocol.
- ``brain/``: fusion and planning, a library. The protocol and the runtime.
- ``modules/`` and ``esvs_client/``: the processes and the ESVS client. Those, brain, and each other.
- the rest of ``rascal/``: the tools on top (cli, run, supervisor, recording, report, view...).
  Anything; and nothing but tools imports them.

Imports are read from the syntax tree, so those inside functions count too. tests/ and
benchmarks/ may import anything.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

from tests.conftest import ROOT

MAY_IMPORT = {
    "protocol": {"protocol"},
    "runtime": {"protocol", "runtime"},
    "brain": {"protocol", "runtime", "brain"},
    "modules": {"protocol", "runtime", "brain", "modules"},
    "tools": {"protocol", "runtime", "brain", "modules", "tools"},
}
CHECKED = ("protocol", "rascal", "brain", "modules", "esvs_client")


def layer_of(dotted: str) -> str | None:
    """The layer a module (dotted name) belongs to; None for anything not ours."""
    parts = dotted.split(".")
    if parts[0] == "rascal":
        return "runtime" if parts[1:2] == ["runtime"] else "tools"
    return {"protocol": "protocol", "brain": "brain", "modules": "modules", "esvs_client": "modules"}.get(parts[0])


def imported(source: str, package: str) -> Iterator[tuple[int, str]]:
    """(line, dotted name) of every import in a module of ``package``; ``from a import b``
    names ``a.b``, which is the module b when b is one (and a's layer either way)."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            for alias in node.names:
                yield node.lineno, f"{base}.{alias.name}"


def violations(root: Path) -> list[str]:
    found = []
    for top in CHECKED:
        for path in sorted((root / top).rglob("*.py")):
            relative = path.relative_to(root)
            module = ".".join(relative.with_suffix("").parts)
            package = module if path.name == "__init__.py" else module.rpartition(".")[0]
            layer = layer_of(module)
            assert layer is not None
            for line, name in imported(path.read_text(encoding="utf-8"), package.removesuffix(".__init__")):
                target = layer_of(name)
                if target is not None and target not in MAY_IMPORT[layer]:
                    found.append(f"{relative}:{line}: {layer} imports {name} ({target})")
    return found


def test_every_layer_imports_only_what_it_may() -> None:
    assert violations(ROOT) == []


def test_brain_and_modules_use_rascal_only_through_the_runtime() -> None:
    for top in ("brain", "modules", "esvs_client"):
        for path in (ROOT / top).rglob("*.py"):
            names = [name for _, name in imported(path.read_text(encoding="utf-8"), top)]
            assert all(name.startswith("rascal.runtime") for name in names if name.split(".")[0] == "rascal"), path


def test_a_planted_import_against_the_layers_is_found(tmp_path: Path) -> None:
    planted = {
        "protocol/wire.py": "from rascal.runtime.bus import Bus\n",
        "rascal/runtime/loop.py": "def late():\n    import brain.grid\n",
        "brain/plan.py": "from rascal import recording\n",
        "modules/sim/world.py": "from rascal.report import draw\n",
        "esvs_client/client.py": "from ..rascal import view\n",  # relative: resolves to rascal.view
        # Allowed: a module on brain and the runtime, a tool on a module, relative within a layer.
        "modules/brain/module.py": "from brain.grid import GridWindow\nfrom rascal.runtime import config\n",
        "rascal/run.py": "import modules.sim\nfrom .runtime import bus\n",
        "brain/fusion/cost.py": "from ..grid import GridWindow\n",
    }
    for name, source in planted.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(source, encoding="utf-8")
    assert violations(tmp_path) == [
        "protocol/wire.py:1: protocol imports rascal.runtime.bus.Bus (runtime)",
        "rascal/runtime/loop.py:2: runtime imports brain.grid (brain)",
        "brain/plan.py:1: brain imports rascal.recording (tools)",
        "modules/sim/world.py:1: modules imports rascal.report.draw (tools)",
        "esvs_client/client.py:1: modules imports rascal.view (tools)",
    ]
