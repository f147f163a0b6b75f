"""A short bent course for control's process tests, as a scenario file."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.modules.control.short_course import RDDF, SCENARIO


@pytest.fixture
def scenario(tmp_path: Path) -> Path:
    (tmp_path / "course.rddf").write_text(RDDF)
    path = tmp_path / "scenario.toml"
    path.write_text(SCENARIO)
    return path
