"""Generated courses and cut stretches: valid RDDFs, the same for a seed, within their bounds."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from brain.corridor import Course
from brain.course_gen import (
    CHORD_TURN_DEG,
    NARROW_WIDTH_M,
    CourseSpec,
    corridor_widths_m,
    cut_course,
    generate_course,
    narrow_length_m,
    rddf_text,
)
from brain.rddf import Waypoint, load_rddf, parse_rddf
from modules.sim.generate import Options, generate
from modules.sim.scenario import load_scenario
from tests.brain.rddf_samples import real_rddf_params, waypoints_at
from tests.rascal.test_rddf_cli import rascal

SEEDS = range(2005, 2013)


def test_the_same_seed_gives_the_same_course() -> None:
    first = rddf_text(generate_course(CourseSpec(7, 1500.0)))
    assert rddf_text(generate_course(CourseSpec(7, 1500.0))) == first
    assert rddf_text(generate_course(CourseSpec(8, 1500.0))) != first


@pytest.mark.parametrize("length_m", [300.0, 2000.0, 20000.0])
def test_the_length_is_the_one_asked_for(length_m: float) -> None:
    # The RDDF has no heights: the last waypoints of a long course sink onto the ellipsoid, a few cm.
    for seed in SEEDS:
        assert Course(generate_course(CourseSpec(seed, length_m))).length_m == pytest.approx(length_m, abs=0.1)


@pytest.mark.parametrize(("low", "high"), [(3.7, 18.0), (3.7, 6.0), (8.0, 12.0), (5.0, 5.01)])
def test_widths_stay_within_their_bounds(low: float, high: float) -> None:
    for seed in SEEDS:
        widths = corridor_widths_m(generate_course(CourseSpec(seed, 2000.0, low, high)))
        assert low <= widths.min() and widths.max() <= high


def test_widths_and_limits_vary_and_every_course_has_a_narrow_stretch() -> None:
    for seed in SEEDS:
        waypoints = generate_course(CourseSpec(seed, 2000.0))
        widths = corridor_widths_m(waypoints)
        limits = {w.speed_limit_mph for w in waypoints}
        assert narrow_length_m(waypoints) >= 50.0, seed
        assert widths.max() > NARROW_WIDTH_M and len(set(widths)) >= 3
        assert limits <= {10.0, 15.0, 20.0, 25.0, 30.0, 35.0} and len(limits) >= 2
        narrow_limits = {w.speed_limit_mph for w, width in zip(waypoints, widths, strict=False) if width <= 6.0}
        assert max(narrow_limits) <= 20.0  # narrow stretches are slow ones


def test_bends_are_smooth_and_the_course_never_comes_back_across_itself() -> None:
    for seed in SEEDS:
        course = Course(generate_course(CourseSpec(seed, 3000.0)))
        heading = np.arctan2(np.diff(course.north_m), np.diff(course.east_m))
        turns = np.degrees(np.abs(np.angle(np.exp(1j * np.diff(heading)))))
        assert turns.max() <= CHORD_TURN_DEG + 0.1  # waypoints are written to about a millimetre
        points = np.column_stack([course.east_m, course.north_m])
        s = np.concatenate([[0.0], np.cumsum(course.segment_length_m)])
        far_along = np.abs(s[:, None] - s[None, :]) > 200.0
        apart = np.hypot(*(points[:, None, :] - points[None, :, :]).transpose(2, 0, 1))
        assert apart[far_along].min() > 60.0  # more than three of the widest corridors


def test_a_written_course_loads_as_it_was_made(tmp_path: Path) -> None:
    waypoints = generate_course(CourseSpec(2009, 800.0))
    path = tmp_path / "course.rddf"
    path.write_text(rddf_text(waypoints, ["a comment"]))
    assert load_rddf(path) == waypoints


def test_scenarios_generated_on_courses_are_fair_and_place_less_where_nothing_fits(tmp_path: Path) -> None:
    for seed, (low, high) in ((2005, (3.7, 18.0)), (2006, (3.7, 6.0)), (2007, (2.0, 2.2))):
        rddf, scenario = tmp_path / f"{seed}.rddf", tmp_path / f"{seed}.toml"
        rddf.write_text(rddf_text(generate_course(CourseSpec(seed, 2000.0, low, high))))
        made = generate(rddf, scenario, Options(seed))
        scenario.write_text(made.text)
        loaded = load_scenario(scenario)  # the loader checks fairness again
        if high < 2.2 + 0.1:  # narrower than a fair lane: nothing fits
            assert made.obstacles == made.washes == made.berms == 0 and not loaded.world.obstacles
        else:
            assert made.obstacles > 0


def test_a_spec_out_of_bounds_is_refused() -> None:
    for length, low, high in ((0.0, 3.7, 18.0), (1000.0, 0.0, 5.0), (1000.0, 8.0, 6.0), (1000.0, 5.001, 5.002)):
        with pytest.raises(ValueError):
            CourseSpec(1, length, low, high)


GRID = waypoints_at([(100.0 * k, 0.0) for k in range(8)], offset_ft=[10.0 + k for k in range(8)])


def test_a_cut_keeps_whole_waypoints_numbered_from_one() -> None:
    cut = cut_course(GRID, 240.0, 290.0)  # from 200 m (nearest 240 m) to 500 m (nearest 200 + 290 m)
    assert [w.number for w in cut] == [1, 2, 3, 4]
    assert [(w.lat_deg, w.lon_deg, w.lateral_offset_ft, w.speed_limit_mph) for w in cut] == [
        (w.lat_deg, w.lon_deg, w.lateral_offset_ft, w.speed_limit_mph) for w in GRID[2:6]
    ]
    assert Course(cut).length_m == pytest.approx(300.0, abs=0.01)


def test_a_cut_is_at_least_one_segment_and_stops_at_the_end() -> None:
    assert len(cut_course(GRID, 0.0, 1.0)) == 2
    assert [w.lateral_offset_ft for w in cut_course(GRID, 650.0, 5000.0)] == [16.0, 17.0]


def test_a_cut_outside_the_course_is_refused() -> None:
    for start, length in ((700.0, 100.0), (-1.0, 100.0), (0.0, 0.0)):
        with pytest.raises(ValueError):
            cut_course(GRID, start, length)


def test_phase_lines_survive_the_round_trip() -> None:
    waypoints = [
        Waypoint(1, 38.2228914, -110.4790771, 20.0, 55.0),
        Waypoint(2, 38.2224215, -110.4793187, 20.0, 55.0, (9, 45, 0)),
    ]
    assert parse_rddf(rddf_text(waypoints), "test") == waypoints


@pytest.mark.parametrize("path", real_rddf_params())
def test_a_cut_of_a_real_file_keeps_its_geometry(path: Path) -> None:
    original = load_rddf(path)
    course = Course(original)
    cut = cut_course(original, course.length_m / 3, course.length_m / 2)
    first = next(i for i, w in enumerate(original) if (w.lat_deg, w.lon_deg) == (cut[0].lat_deg, cut[0].lon_deg))
    kept = original[first : first + len(cut)]
    assert [(w.lat_deg, w.lon_deg, w.lateral_offset_ft, w.speed_limit_mph, w.phase_line) for w in kept] == [
        (w.lat_deg, w.lon_deg, w.lateral_offset_ft, w.speed_limit_mph, w.phase_line) for w in cut
    ]
    assert parse_rddf(rddf_text(cut), "cut") == cut
    assert math.isclose(sum(Course(cut).segment_length_m), Course(cut).length_m)


def test_the_commands_write_courses_that_load(tmp_path: Path) -> None:
    generated, cut = tmp_path / "generated.rddf", tmp_path / "cut.rddf"
    made = rascal("rddf", "generate", "--seed", "4", "--length-km", "1.2", "--max-width-m", "9", "-o", generated)
    assert made.returncode == 0, made.stderr
    assert "1200.0 m" in made.stdout
    assert load_rddf(generated) == generate_course(CourseSpec(4, 1200.0, 3.7, 9.0))
    done = rascal("rddf", "cut", generated, "--from-m", "300", "--length-m", "400", "-o", cut)
    assert done.returncode == 0, done.stderr
    assert Course(load_rddf(cut)).length_m == pytest.approx(400.0, abs=40.0)  # bends have waypoints ~10-25 m apart
    refused = rascal("rddf", "cut", generated, "--from-m", "5000", "--length-m", "400", "-o", cut)
    assert refused.returncode == 2 and "not within" in refused.stderr
    refused = rascal("rddf", "generate", "--seed", "4", "--length-km", "1", "--min-width-m", "9", "--max-width-m", "4",
                     "-o", generated)  # fmt: skip
    assert refused.returncode == 2 and "min <= max" in refused.stderr
