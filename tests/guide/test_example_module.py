"""The module guide's example runs as a real process on a loopback bus; `rascal bus echo` hears it.
And every python block of docs/MODULE_GUIDE.md is quoted verbatim from the example file."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

from protocol import channels
from tests.conftest import ROOT

EXAMPLE = Path(__file__).with_name("example_module.py")
GUIDE = ROOT / "docs" / "MODULE_GUIDE.md"


def test_the_example_module_publishes_and_bus_echo_receives(bus_url: str, key_file: Path) -> None:
    module = subprocess.Popen(
        [sys.executable, str(EXAMPLE), "--set", "distance_m=8", "--set", "rate_hz=20"],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    echo_command = ["bus", "echo", channels.OBSTACLES_BEACON, "--count", "2", "--duration", "6"]
    try:
        echo = subprocess.run(
            [sys.executable, "-m", "rascal.cli", *echo_command], cwd=ROOT, capture_output=True, text=True, timeout=15
        )
    finally:
        module.terminate()
        _, err = module.communicate(timeout=5)
    assert echo.returncode == 0, (echo.stderr, err)
    lines = [json.loads(line) for line in echo.stdout.splitlines()]
    assert len(lines) == 2, lines
    for line in lines:
        assert line["channel"] == channels.OBSTACLES_BEACON and line["source"] == 60
        assert [obstacle["x_m"] for obstacle in line["msg"]["obstacles"]] == [8.0]


def test_the_guide_quotes_the_example_verbatim() -> None:
    source = EXAMPLE.read_text()
    blocks = re.findall(r"```python\n(.*?)```", GUIDE.read_text(), re.S)
    assert len(blocks) >= 3
    for block in blocks:
        assert block in source, f"docs/MODULE_GUIDE.md block not in {EXAMPLE.name}:\n{block}"
