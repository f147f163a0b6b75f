"""The course settings every ENU module shares: RDDF path and origin."""

from __future__ import annotations

from pathlib import Path

import pytest

from brain.corridor import GeodeticOrigin
from brain.course_config import DEFAULT_COURSE, load_course, parse_origin
from modules.sim.scenario import DEFAULT_SCENARIO, load_scenario


def test_origin_text() -> None:
    assert parse_origin("") is None
    assert parse_origin(" 34.5, -116.25 ") == GeodeticOrigin(34.5, -116.25)
    assert parse_origin("34.5,-116.25,700") == GeodeticOrigin(34.5, -116.25, 700.0)
    for bad in ("34.5", "north,west", "1,2,3,4", "91,0", "0,181", "nan,0"):
        with pytest.raises(ValueError, match="origin"):
            parse_origin(bad)


def test_default_course_is_the_default_scenarios_frame() -> None:
    course = load_course(DEFAULT_COURSE)
    scenario = load_scenario(DEFAULT_SCENARIO)
    assert course.origin == scenario.origin
    assert course.length_m == pytest.approx(scenario.course.length_m)


def test_an_explicit_origin_moves_the_frame(tmp_path: Path) -> None:
    rddf = tmp_path / "c.rddf"
    rddf.write_text("1,35.0,-117.0,30,10\n2,35.0,-116.99,30,10\n")
    shifted = load_course(rddf, "34.999,-117.0")
    east, north = shifted.to_enu(35.0, -117.0)
    assert abs(float(east)) < 1e-6 and float(north) == pytest.approx(111.0, abs=0.5)
