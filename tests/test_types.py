"""The type check `make lint` runs: mypy, as configured in pyproject.toml (strict on protocol/)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_the_type_check_passes() -> None:
    # No cache: nothing written into the tree, and a cold check of protocol/ takes about a second.
    done = subprocess.run(
        [sys.executable, "-m", "mypy", "--cache-dir", "/dev/null"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
