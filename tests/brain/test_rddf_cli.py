"""`rascal rddf info` and `rascal rddf plot` as commands, run the way a user runs them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from tests.brain.rddf_samples import rddf_text, real_rddf_params, waypoints_at
from tests.conftest import ROOT

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


def test_plot_writes_a_png_that_fits_the_size(course_file: Path, tmp_path: Path) -> None:
    output = tmp_path / "course.png"
    result = rascal("rddf", "plot", course_file, "-o", output, "--size-px", "900")
    assert result.returncode == 0, result.stderr
    assert output.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = cv2.imread(str(output))
    assert image is not None and max(image.shape[:2]) <= 900 and min(image.shape[:2]) > 100
    assert len({tuple(pixel) for pixel in image.reshape(-1, 3)[::97]}) > 10  # drawn, not blank
