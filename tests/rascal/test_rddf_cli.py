"""`rascal rddf info` and `rascal rddf plot` as commands, run the way a user runs them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.brain.rddf_samples import rddf_text, real_rddf_params, waypoints_at
from tests.conftest import ROOT
from tests.rascal.plot_checks import assert_png, assert_svg, svg_texts

COURSE = waypoints_at([(0.0, 0.0), (120.0, 0.0), (120.0, 80.0), (40.0, 80.0)], speed_mph=[25.0, 15.0, 25.0, 0.0])


def rascal(*args: str | Path) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "rascal.cli", *map(str, args)]
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=60, check=False)


@pytest.fixture
def course_file(tmp_path: Path) -> Path:
    path = tmp_path / "course.rddf"
    path.write_text(rddf_text(COURSE))
    return path


def test_info_reports_the_course(course_file: Path) -> None:
    result = rascal("rddf", "info", course_file)
    assert result.returncode == 0, result.stderr
    report = {label: value.strip() for label, value in (line.split("  ", 1) for line in result.stdout.splitlines())}
    assert report["waypoints"].startswith("4 (numbers 1-4), 3 segments")
    assert "280.0 m (0.280 km)" in report["length"]
    assert "min 7.32 m, median 7.32 m, max 7.32 m" in report["corridor width"]
    assert "min 6.71 m/s (15.0 mph)" in report["speed limit"] and "max 11.18 m/s (25.0 mph)" in report["speed limit"]
    assert report["path"].startswith("281 points every 1.000 m")
    for label in ("desired speed", "min drive time"):
        assert label in report


@pytest.mark.parametrize("path", real_rddf_params()[:1])
def test_info_reads_a_real_file(path: Path) -> None:
    result = rascal("rddf", "info", path)
    assert result.returncode == 0, result.stderr
    assert "waypoints" in result.stdout


def test_info_on_a_bad_file_exits_2_naming_line_and_field(tmp_path: Path) -> None:
    path = tmp_path / "bad.rddf"
    path.write_text(rddf_text(COURSE) + "5, 37.5, -122.0, wide, 5\n")
    result = rascal("rddf", "info", path)
    assert result.returncode == 2
    assert f"{path} line 5, field 'lateral_offset_ft': 'wide' is not a number" in result.stderr
    assert result.stdout == ""


def test_info_on_a_missing_file_exits_2(tmp_path: Path) -> None:
    result = rascal("rddf", "info", tmp_path / "nowhere.rddf")
    assert result.returncode == 2
    assert "nowhere.rddf" in result.stderr


def test_plot_writes_png_or_svg_that_fits_the_size(course_file: Path, tmp_path: Path) -> None:
    for name in ("course.png", "course.svg"):
        output = tmp_path / name
        result = rascal("rddf", "plot", course_file, "-o", output, "--size-px", "900")
        assert result.returncode == 0, result.stderr
        assert result.stdout.startswith(f"wrote {output} (") and result.stderr == ""
    image = assert_png(tmp_path / "course.png")
    assert max(image.shape[:2]) <= 900
    assert "START" in svg_texts(assert_svg(tmp_path / "course.svg"))


def test_plot_to_an_unknown_format_or_place_exits_2(course_file: Path, tmp_path: Path) -> None:
    for output, reason in (
        (tmp_path / "course.bmpx", "name it .png, .svg or .pdf"),
        (tmp_path / "no" / "c.png", "c.png"),
    ):
        result = rascal("rddf", "plot", course_file, "-o", output)
        assert result.returncode == 2 and reason in result.stderr and "Traceback" not in result.stderr
