"""The corridor frame: ENU <-> (station, lateral offset) along the course's centre path."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brain.corridor import Course
from brain.planning.frame import CorridorFrame
from brain.planning.speed import curvature
from tests.brain.planning.scenes import course_through, straight_course

BENT = course_through([(0.0, 0.0), (60.0, 0.0), (100.0, 40.0), (100.0, 120.0), (40.0, 160.0)], half_width_m=6.0)


def test_straight_course_is_east_and_north() -> None:
    frame = CorridorFrame(straight_course(200.0).interpolate())
    s, d = frame.locate([10.0, 55.5, 199.0], [0.0, 3.0, -4.5])
    np.testing.assert_allclose(s, [10.0, 55.5, 199.0], atol=1e-6)
    np.testing.assert_allclose(d, [0.0, 3.0, -4.5], atol=1e-6)
    east, north = frame.to_enu([10.0, 55.5], [2.0, -1.0])
    np.testing.assert_allclose(east, [10.0, 55.5], atol=1e-6)
    np.testing.assert_allclose(north, [2.0, -1.0], atol=1e-6)
    assert frame.heading_at(50.0) == pytest.approx(0.0, abs=1e-9)


def test_centre_line_points_have_zero_offset_and_their_arc_length() -> None:
    path = BENT.interpolate()
    frame = CorridorFrame(path)
    pick = np.arange(0, len(path.s_m), 7)
    s, d = frame.locate(path.east_m[pick], path.north_m[pick])
    np.testing.assert_allclose(d, 0.0, atol=1e-6)
    np.testing.assert_allclose(s, path.s_m[pick], atol=1e-6)


@settings(max_examples=60, deadline=None, derandomize=True, database=None)
@given(s=st.floats(1.0, 270.0), d=st.floats(-5.5, 5.5))
def test_round_trip_through_the_bends(s: float, d: float) -> None:
    """Every (s, d) within the corridor maps to ENU and back: offsets up to the half width stay
    within the window-smoothed normals' radius at these 45 and 56 degree bends."""
    frame = CorridorFrame(BENT.interpolate())
    east, north = frame.to_enu(s, d)
    back_s, back_d = frame.locate(east, north, near_s_m=s)
    assert float(back_s) == pytest.approx(s, abs=1e-6)
    assert float(back_d) == pytest.approx(d, abs=1e-6)
    # The lateral offset is a true distance: the point lies |d| from the centre point at s.
    centre_e, centre_n = frame.to_enu(s, 0.0)
    assert np.hypot(east - centre_e, north - centre_n) == pytest.approx(abs(d), abs=1e-9)


def test_offset_paths_stay_continuous_round_the_outside_of_a_corner() -> None:
    """Interpolated normals: a constant offset of 6 m sweeps round the 45-degree corners instead
    of jumping (with one normal per segment it would jump 6 x 2 sin(22.5 deg) = 4.6 m there):
    finer stations give proportionally smaller steps."""
    frame = CorridorFrame(BENT.interpolate())
    for step in (0.1, 0.01):
        s = np.arange(0.0, 250.0, step)
        east, north = frame.to_enu(s, np.full_like(s, -6.0))
        assert np.max(np.hypot(np.diff(east), np.diff(north))) < 5.0 * step


@pytest.mark.parametrize("d", [-5.0, 5.0])
def test_offsets_inside_a_right_angle_do_not_fold_back(d: float) -> None:
    """A 90-degree RDDF corner is a sharp vertex of the centre path; the normals turn over 16 m
    around it, so a 5 m offset on either side still moves forwards all the way round."""
    frame = CorridorFrame(course_through([(0.0, 0.0), (50.0, 0.0), (50.0, 50.0)], 6.0).interpolate())
    s = np.arange(30.0, 70.0, 0.05)
    east, north = frame.to_enu(s, np.full_like(s, d))
    step = np.column_stack([np.diff(east), np.diff(north)])
    heading = frame.heading_at(s[:-1])
    forward = step[:, 0] * np.cos(heading) + step[:, 1] * np.sin(heading)
    assert forward.min() > 0.0


def test_search_window_keeps_the_vehicle_on_its_own_leg() -> None:
    """A hairpin: the way back runs 12 m from the way out. Near station 50 on the way out, a
    point next to the way back still belongs to the way out; a global search picks the way back."""
    hairpin = CorridorFrame(course_through([(0.0, 0.0), (100.0, 0.0), (100.0, 12.0), (0.0, 12.0)], 5.0).interpolate())
    s_near, d_near = hairpin.locate(50.0, 10.0, near_s_m=50.0, behind_m=15.0, ahead_m=30.0)
    assert float(s_near) == pytest.approx(50.0, abs=1e-6)
    assert float(d_near) == pytest.approx(10.0, abs=1e-6)
    s_any, d_any = hairpin.locate(50.0, 10.0)
    assert float(s_any) == pytest.approx(162.0, abs=1e-6)
    assert float(d_any) == pytest.approx(2.0, abs=1e-6)


def test_points_beyond_the_ends_extend_the_end_segments() -> None:
    frame = CorridorFrame(straight_course(100.0).interpolate())
    s, d = frame.locate([-5.0, 110.0], [1.0, -2.0])
    np.testing.assert_allclose(s, [-5.0, 110.0], atol=1e-6)
    np.testing.assert_allclose(d, [1.0, -2.0], atol=1e-6)


def test_cross_sections_match_to_enu() -> None:
    frame = CorridorFrame(BENT.interpolate())
    s = np.array([5.0, 61.3, 140.0, 230.5])
    lateral = np.linspace(-4.0, 4.0, 9)
    east, north = frame.cross_sections(s, lateral)
    ref_e, ref_n = frame.to_enu(s[:, None] + 0 * lateral, lateral[None, :] + 0 * s[:, None])
    np.testing.assert_allclose(east, ref_e, atol=1e-9)
    np.testing.assert_allclose(north, ref_n, atol=1e-9)


def test_course_speeds_and_widths_by_station() -> None:
    path = BENT.interpolate()
    frame = CorridorFrame(path)
    np.testing.assert_allclose(frame.speed_at(path.s_m[10:20]), path.speed_mps[10:20])
    np.testing.assert_allclose(frame.half_width_at([3.0, 150.5]), 6.0)
    assert float(frame.heading_at(150.0)) == pytest.approx(np.pi / 2, abs=1e-9)


def test_bad_locate_window_is_refused() -> None:
    frame = CorridorFrame(straight_course(100.0).interpolate())
    with pytest.raises(ValueError, match="finite"):
        frame.locate(1.0, 1.0, near_s_m=float("nan"))


def _out_and_back(tmp_path: Path) -> CorridorFrame:
    """About 180 m east, then back west 11 m further north: the course passes its start twice."""
    rddf = tmp_path / "back.rddf"
    rddf.write_text(
        "1,35.0000000,-117.0000000,30,20\n2,35.0000000,-116.9980000,30,20\n3,35.0001000,-117.0000000,30,20\n"
    )
    return CorridorFrame(Course.from_file(rddf).interpolate())


def test_a_point_behind_the_start_is_on_the_start_extension(tmp_path: Path) -> None:
    frame = _out_and_back(tmp_path)
    s, d = frame.locate(-0.5, 0.2)
    assert float(s) == pytest.approx(-0.5, abs=1e-4) and float(d) == pytest.approx(0.2, abs=1e-4)


def test_a_start_where_the_course_passes_twice_takes_the_pass_along_the_heading(tmp_path: Path) -> None:
    frame = _out_and_back(tmp_path)
    east, north = 2.0, 5.5  # between the outbound and the return leg
    outbound = frame.locate_start(east, north, yaw_rad=0.0)
    inbound = frame.locate_start(east, north, yaw_rad=math.pi)
    assert outbound == pytest.approx(2.0, abs=0.5)
    assert inbound > frame.length_m - 20.0


def test_rounded_corners_are_no_sharper_than_the_course_speed_assumes() -> None:
    """The RDDF's 90-degree corner is a vertex: along it a path would have to slow to 2.5 m/s
    at 2 m/s^2 (its turn over the planner's 3 m curvature window), while the course's speed
    profile spreads the turn over 8 m. Rounded over 16 m, the centre line's own curvature never
    asks for less than that speed, it cuts the corner by under 3 m, and the offsets the frame
    vouches for stay inside the corridor."""
    course = course_through([(0.0, 0.0), (50.0, 0.0), (50.0, 50.0)], 6.0)
    path = course.interpolate()
    sharp, rounded = CorridorFrame(path), CorridorFrame(path, rounding_m=16.0)
    s = np.arange(0.0, path.length_m, 1.0)
    for frame, slower in ((sharp, True), (rounded, False)):
        centre = np.column_stack(frame.to_enu(s, np.zeros_like(s)))
        turn_speed = np.sqrt(2.0 / np.maximum(curvature(centre, 3.0), 1e-12))
        assert bool(np.any(turn_speed < frame.speed_at(s) - 0.5)) is slower
    centre_e, centre_n = rounded.to_enu(s, np.zeros_like(s))
    assert 2.0 < np.hypot(centre_e - 50.0, centre_n).min() < 3.0
    np.testing.assert_allclose(rounded.to_enu([0.0, path.length_m], [0.0, 0.0]), [[0.0, 50.0], [0.0, 50.0]], atol=1e-9)
    sure = rounded.sure_half_width_at(s)
    for side in (-1.0, 1.0):
        east, north = rounded.to_enu(s, side * sure)
        assert course.corridor.distance_to_edge(east, north).min() >= -1e-6


@settings(max_examples=40, deadline=None)
@given(st.floats(0.0, 240.0), st.floats(1.0, 90.0), st.floats(0.0, 3.0))
def test_the_band_box_holds_the_corridor_between_its_stations(start: float, length: float, margin: float) -> None:
    """The frame's points up to the half width either side, and the course's own (unrounded) line
    widened by its half width, lie in the box with the margin to spare."""
    frame = CorridorFrame(BENT.interpolate(), rounding_m=16.0)
    low_e, low_n, high_e, high_n = frame.band_box(start, start + length, margin)
    s = np.linspace(start, start + length, 200)
    for d in (-1.0, 0.0, 1.0):
        east, north = frame.to_enu(s, d * frame.half_width_at(s))
        assert np.all((east >= low_e + margin - 1e-9) & (east <= high_e - margin + 1e-9))
        assert np.all((north >= low_n + margin - 1e-9) & (north <= high_n - margin + 1e-9))
    path = BENT.interpolate()
    inner = (path.s_m >= start) & (path.s_m <= start + length)
    assert np.all(
        (path.east_m[inner] >= low_e + margin + 6.0 - 1e-9) & (path.east_m[inner] <= high_e - margin - 6.0 + 1e-9)
    )
    assert np.all(
        (path.north_m[inner] >= low_n + margin + 6.0 - 1e-9) & (path.north_m[inner] <= high_n - margin - 6.0 + 1e-9)
    )
