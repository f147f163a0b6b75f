"""Course geometry: the ENU frame, the 1 m path and its speeds, the corridor as a union of capsules."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pymap3d
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from brain.corridor import FT_TO_M, MPH_TO_MPS, Corridor, Course, CoursePath, GeodeticOrigin
from brain.rddf import load_rddf
from tests.brain.rddf_samples import rddf_text, real_rddf_params, waypoints_at

RIGHT_ANGLE = waypoints_at([(0.0, 0.0), (100.0, 0.0), (100.0, 100.0)])
SLOW_AFTER_FAST = waypoints_at([(0.0, 0.0), (200.0, 0.0), (300.0, 0.0)], speed_mph=[40.0, 10.0, 10.0])
LIMITS = {"max_lateral_accel_mps2": 2.0, "max_decel_mps2": 2.0, "max_accel_mps2": 1.5}


def metres_between(lat1: np.ndarray, lon1: np.ndarray, lat2: np.ndarray, lon2: np.ndarray) -> np.ndarray:
    east, north, _ = pymap3d.geodetic2enu(lat1, lon1, 0.0, lat2, lon2, 0.0)
    return np.hypot(east, north)


def check_speed_invariants(course: Course, path: CoursePath) -> None:
    """Desired speeds respect the RDDF limits, the turn limit and the acceleration limits."""
    tolerance = 1e-9
    assert np.all(path.speed_mps >= 0.0)
    assert np.all(path.speed_mps <= course.speed_limit_mps[path.segment] + tolerance)
    assert np.all(path.speed_mps <= path.speed_limit_mps + tolerance)
    with np.errstate(divide="ignore"):
        turn_limit = np.sqrt(LIMITS["max_lateral_accel_mps2"] / path.curvature_1pm)
    assert np.all(path.speed_mps <= turn_limit + tolerance)
    change = np.diff(path.speed_mps**2) / (2.0 * np.diff(path.s_m))
    assert change.min() >= -LIMITS["max_decel_mps2"] - tolerance
    assert change.max() <= LIMITS["max_accel_mps2"] + tolerance


@pytest.mark.parametrize("path", real_rddf_params())
def test_real_course_path_and_corridor_hold_together(path: Path) -> None:
    course = Course.from_file(path)
    resampled = course.interpolate(**LIMITS)
    assert abs(resampled.length_m - course.length_m) < 1e-6
    assert np.all(course.corridor.contains(course.east_m, course.north_m))
    assert np.all(course.corridor.contains(resampled.east_m, resampled.north_m))
    check_speed_invariants(course, resampled)


@pytest.mark.parametrize("path", real_rddf_params())
def test_enu_round_trips_through_pymap3d_within_a_millimetre(path: Path) -> None:
    course = Course.from_file(path)
    lat = np.array([w.lat_deg for w in course.waypoints])
    lon = np.array([w.lon_deg for w in course.waypoints])
    origin = course.origin
    back_lat, back_lon, _ = pymap3d.enu2geodetic(
        course.east_m, course.north_m, course.up_m, origin.lat_deg, origin.lon_deg, origin.alt_m
    )
    assert metres_between(back_lat, back_lon, lat, lon).max() < 1e-3
    again_lat, again_lon = course.to_geodetic(*course.to_enu(lat, lon), course.up_m)
    assert metres_between(again_lat, again_lon, lat, lon).max() < 1e-3


def test_the_first_waypoint_is_the_origin_unless_one_is_given() -> None:
    course = Course(RIGHT_ANGLE)
    assert (course.east_m[0], course.north_m[0]) == (0.0, 0.0)
    np.testing.assert_allclose(course.east_m, [0.0, 100.0, 100.0], atol=1e-6)
    np.testing.assert_allclose(course.north_m, [0.0, 0.0, 100.0], atol=1e-6)
    first = RIGHT_ANGLE[0]
    moved = Course(RIGHT_ANGLE, GeodeticOrigin(first.lat_deg - 0.001, first.lon_deg, 12.0))
    assert moved.north_m[0] == pytest.approx(110.99, abs=0.05)  # 0.001 deg of latitude at 37.5 deg
    np.testing.assert_allclose(moved.segment_length_m, course.segment_length_m, atol=1e-3)


def test_units_are_metres_and_metres_per_second() -> None:
    course = Course(waypoints_at([(0.0, 0.0), (50.0, 0.0)], offset_ft=10.0, speed_mph=30.0))
    assert course.half_width_m[0] == pytest.approx(3.048)
    assert course.speed_limit_mps[0] == pytest.approx(13.4112)
    assert course.length_m == pytest.approx(50.0, abs=1e-6)


def test_path_points_are_one_metre_apart_and_end_on_the_waypoints() -> None:
    course = Course(RIGHT_ANGLE)
    path = course.interpolate(spacing_m=1.0)
    steps = np.diff(path.s_m)
    assert np.allclose(steps, steps[0]) and abs(path.spacing_m - 1.0) <= 0.5 / len(steps)
    chords = np.hypot(np.diff(path.east_m), np.diff(path.north_m))
    assert np.all(chords <= path.spacing_m + 1e-9)
    same_segment = path.segment[:-1] == path.segment[1:]
    np.testing.assert_allclose(chords[same_segment], path.spacing_m, atol=1e-6)
    assert (path.east_m[0], path.north_m[0]) == (course.east_m[0], course.north_m[0])
    assert path.east_m[-1] == pytest.approx(course.east_m[-1]) and path.north_m[-1] == pytest.approx(course.north_m[-1])


def test_path_starts_and_ends_at_standstill_and_slows_for_a_corner() -> None:
    course = Course(RIGHT_ANGLE)
    path = course.interpolate(**LIMITS)
    assert path.speed_mps[0] == 0.0 and path.speed_mps[-1] == 0.0
    corner = int(np.argmin(np.hypot(path.east_m - 100.0, path.north_m)))
    straight = int(np.argmin(np.hypot(path.east_m - 50.0, path.north_m)))
    assert path.speed_mps[corner] < 0.5 * path.speed_mps[straight]
    assert path.speed_mps[straight] == pytest.approx(25.0 * MPH_TO_MPS)
    check_speed_invariants(course, path)


def test_path_slows_down_before_a_slower_segment_not_in_it() -> None:
    course = Course(SLOW_AFTER_FAST)
    path = course.interpolate(**LIMITS)
    boundary = int(np.argmin(np.abs(path.s_m - 200.0)))
    slow = 10.0 * MPH_TO_MPS
    assert path.speed_mps[boundary] <= slow + 1e-9
    assert path.speed_mps[boundary - 20] > slow + 1.0  # still braking 20 m ahead of the boundary
    assert path.speed_mps[120] == pytest.approx(40.0 * MPH_TO_MPS)
    check_speed_invariants(course, path)


def test_repeated_waypoints_are_skipped_by_the_path_but_kept_in_the_corridor() -> None:
    course = Course(waypoints_at([(0.0, 0.0), (30.0, 0.0), (30.0, 0.0), (30.0, 40.0)]))
    path = course.interpolate()
    assert path.length_m == pytest.approx(70.0, abs=1e-6)
    assert 1 not in set(path.segment.tolist())
    assert len(course.corridor.half_width_m) == 3


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.floats(-300.0, 300.0),
            st.floats(-300.0, 300.0),
            st.floats(3.0, 60.0),
            st.floats(2.0, 60.0),
        ),
        min_size=2,
        max_size=12,
    )
)
def test_any_course_keeps_the_speed_invariants_and_its_path_inside(rows: list[tuple[float, ...]]) -> None:
    points = [(0.0, 0.0)] + [(east, north) for east, north, _, _ in rows[1:]]
    assume(sum(math.dist(a, b) for a, b in itertools.pairwise(points)) >= 1.0)
    course = Course(waypoints_at(points, [row[2] for row in rows], [row[3] for row in rows]))
    path = course.interpolate(**LIMITS)
    check_speed_invariants(course, path)
    assert np.all(course.corridor.contains(path.east_m, path.north_m))


STRAIGHT = Corridor([[0.0, 0.0]], [[100.0, 0.0]], [5.0])


def test_straight_band_edges_are_exact() -> None:
    assert STRAIGHT.contains(50.0, 4.9) and STRAIGHT.contains(50.0, -4.9)
    assert not STRAIGHT.contains(50.0, 5.1) and not STRAIGHT.contains(50.0, -5.1)
    assert STRAIGHT.contains(50.0, 5.0)  # the edge itself belongs to the corridor
    assert STRAIGHT.distance_to_edge(50.0, 5.1) == pytest.approx(-0.1)
    assert STRAIGHT.distance_to_edge(50.0, 1.0) == pytest.approx(4.0)
    # Round caps beyond the ends.
    assert STRAIGHT.contains(104.9, 0.0) and not STRAIGHT.contains(105.1, 0.0)
    assert STRAIGHT.contains(103.0, 3.9) and not STRAIGHT.contains(103.0, 4.1)


def test_queries_answer_in_the_shape_they_are_asked() -> None:
    east = np.linspace(-10.0, 110.0, 12).reshape(3, 4)
    inside = STRAIGHT.contains(east, 0.0)
    assert inside.shape == (3, 4) and inside.dtype == bool
    assert STRAIGHT.distance_to_edge(east, np.zeros((3, 4))).shape == (3, 4)
    assert isinstance(STRAIGHT.contains(1.0, 1.0), bool)
    assert isinstance(STRAIGHT.distance_to_edge(1.0, 1.0), float)


def test_course_corridor_excludes_points_just_outside_a_straight_segment() -> None:
    course = Course(RIGHT_ANGLE)
    half_width = 12.0 * FT_TO_M
    assert course.corridor.contains(50.0, half_width - 0.1)
    assert not course.corridor.contains(50.0, half_width + 0.1)
    assert not course.corridor.contains(50.0, -half_width - 0.1)


def test_corner_is_the_union_of_both_bands_each_with_its_start_waypoints_offset() -> None:
    # Segment 0 is 10 ft (3.05 m) to each side, segment 1 is 40 ft (12.19 m); the last offset is unused.
    course = Course(waypoints_at([(0.0, 0.0), (100.0, 0.0), (100.0, 100.0)], offset_ft=[10.0, 40.0, 1.0]))
    corridor = course.corridor
    assert corridor.contains(50.0, 3.0) and not corridor.contains(50.0, 3.2)
    assert corridor.contains(88.5, 50.0) and not corridor.contains(87.5, 50.0)
    assert corridor.contains(100.0, 99.0) and corridor.contains(100.0, 111.0)  # the last waypoint keeps 40 ft
    # Around the corner (100, 0): the union covers what either band covers, and nothing more.
    assert corridor.contains(105.0, -8.0)  # 9.4 m from the corner: the wide band's round cap only
    assert corridor.contains(80.0, 2.5)  # the narrow band only
    assert corridor.contains(95.0, 2.0)  # both
    assert not corridor.contains(111.0, -6.0)  # 12.5 m beyond the outer corner
    assert not corridor.contains(80.0, 3.5)  # beside the narrow band, too far from the wide one


def test_distance_to_edge_matches_a_plain_reference() -> None:
    rng = np.random.default_rng(7)
    starts = rng.uniform(-50.0, 50.0, (6, 2))
    ends = starts + rng.uniform(-30.0, 30.0, (6, 2))
    ends[2] = starts[2]  # a zero-length segment is a disc
    radius = rng.uniform(1.0, 8.0, 6)
    corridor = Corridor(starts, ends, radius)
    points = rng.uniform(-90.0, 90.0, (2000, 2))
    got = corridor.distance_to_edge(points[:, 0], points[:, 1])
    for (east, north), value in zip(points, got, strict=True):
        expected = max(
            r - distance_to_segment((east, north), a, b) for a, b, r in zip(starts, ends, radius, strict=True)
        )
        assert value == pytest.approx(expected, abs=1e-9)
    assert np.array_equal(corridor.contains(points[:, 0], points[:, 1]), got >= 0.0)


def distance_to_segment(point: tuple[float, float], start: np.ndarray, end: np.ndarray) -> float:
    (px, py), (ax, ay), (bx, by) = point, start, end
    dx, dy = bx - ax, by - ay
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0.0 else min(1.0, max(0.0, ((px - ax) * dx + (py - ay) * dy) / length2))
    return math.hypot(px - (ax + t * dx), py - (ay + t * dy))


def test_courses_that_cannot_be_driven_are_refused() -> None:
    with pytest.raises(ValueError, match="at least 2"):
        Course(RIGHT_ANGLE[:1])
    with pytest.raises(ValueError, match="no length"):
        Course(waypoints_at([(0.0, 0.0), (0.0, 0.0)]))
    with pytest.raises(ValueError, match="positive speed limit"):
        Course(waypoints_at([(0.0, 0.0), (10.0, 0.0), (20.0, 0.0)], speed_mph=[10.0, 0.0, 0.0]))


def test_loaded_waypoints_and_course_agree(tmp_path: Path) -> None:
    path = tmp_path / "c.rddf"
    path.write_text(rddf_text(RIGHT_ANGLE))
    course = Course.from_file(path)
    assert len(course.waypoints) == len(load_rddf(path)) == 3
    assert course.length_m == pytest.approx(200.0, abs=1e-3)
