"""The path interface: closest point, signs, windowed search, look-ahead and speeds."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from modules.control.path_tracking import PathError, PathTracker, TrackedPath, wrap_angle
from protocol.messages import PathPoint


def straight_east(length_m: float = 100.0, speed_mps: float = 5.0) -> TrackedPath:
    east = np.arange(0.0, length_m + 0.5, 1.0)
    return TrackedPath(east, np.zeros_like(east), np.full_like(east, speed_mps))


def arc(radius_m: float, left: bool, sweep_rad: float = math.pi, spacing_m: float = 1.0) -> TrackedPath:
    """An arc starting at the origin heading east, turning left (centre north) or right."""
    n = int(radius_m * sweep_rad / spacing_m) + 1
    a = np.linspace(0.0, sweep_rad, n)
    sign = 1.0 if left else -1.0
    return TrackedPath(radius_m * np.sin(a), sign * radius_m * (1.0 - np.cos(a)), np.full(n, 4.0))


def hairpin(gap_m: float = 4.0) -> TrackedPath:
    """East 50 m, a tight U-turn, back west ``gap_m`` further north."""
    out = [(x, 0.0) for x in np.arange(0.0, 50.5, 1.0)]
    turn = [(50.0 + 0.5 * gap_m * math.sin(a), 0.5 * gap_m * (1 - math.cos(a))) for a in np.linspace(0, math.pi, 7)[1:]]
    back = [(x, gap_m) for x in np.arange(49.0, -0.5, -1.0)]
    points = out + turn + back
    return TrackedPath([p[0] for p in points], [p[1] for p in points], [3.0] * len(points))


def test_closest_point_on_a_straight_path() -> None:
    tracker = PathTracker()
    tracker.set_path(straight_east())
    where = tracker.locate(20.3, 1.5, 0.0)
    assert where.s_m == pytest.approx(20.3)
    assert (where.east_m, where.north_m) == pytest.approx((20.3, 0.0))
    assert where.heading_rad == pytest.approx(0.0)
    assert where.curvature_1pm == pytest.approx(0.0)
    assert where.beyond_end_m == 0.0


def test_cross_track_is_positive_left_of_the_path_and_negative_right() -> None:
    tracker = PathTracker()
    tracker.set_path(straight_east())
    assert tracker.locate(10.0, 1.5, 0.0).cross_track_m == pytest.approx(1.5)
    assert tracker.locate(10.0, -0.7, 0.0).cross_track_m == pytest.approx(-0.7)
    # The same on a path heading north: left of it is west.
    north = TrackedPath([0.0, 0.0, 0.0], [0.0, 10.0, 20.0], [1.0, 1.0, 1.0])
    tracker.set_path(north)
    where = tracker.locate(-2.0, 5.0, math.pi / 2)
    assert where.cross_track_m == pytest.approx(2.0)
    assert where.heading_rad == pytest.approx(math.pi / 2)


@pytest.mark.parametrize("left", [True, False])
def test_closest_point_on_an_arc(left: bool) -> None:
    radius = 20.0
    tracker = PathTracker()
    tracker.set_path(arc(radius, left))
    sign = 1.0 if left else -1.0
    centre = (0.0, sign * radius)
    # Walk the vehicle along the arc 1 m outside of it; the closest point is 1 m in (the chord
    # sag of 1 m segments on a 20 m radius is 6 mm).
    for angle in np.linspace(0.3, 2.8, 12):
        east = centre[0] + (radius + 1.0) * math.sin(angle)
        north = centre[1] - sign * (radius + 1.0) * math.cos(angle)
        where = tracker.locate(east, north, sign * angle)
        assert abs(where.cross_track_m) == pytest.approx(1.0, abs=0.01)
        # Outside a left turn is right of the path, outside a right turn is left of it.
        assert math.copysign(1.0, where.cross_track_m) == -sign
        assert where.s_m == pytest.approx(radius * angle, abs=0.05)
        assert wrap_angle(where.heading_rad - sign * angle) == pytest.approx(0.0, abs=0.03)
        assert where.curvature_1pm == pytest.approx(sign / radius, rel=0.05)


def test_the_windowed_search_never_jumps_to_a_closer_distant_part() -> None:
    tracker = PathTracker()
    tracker.set_path(hairpin(gap_m=4.0))
    for x in np.arange(5.0, 41.0, 0.5):
        tracker.locate(x, 0.2, 0.0)
    # Drifted to 3 m north of the outbound leg: the return leg is 1 m away, the outbound 3 m.
    where = tracker.locate(40.0, 3.0, 0.0)
    assert where.s_m == pytest.approx(40.0)
    assert where.cross_track_m == pytest.approx(3.0)


def test_a_new_path_is_joined_where_it_heads_the_vehicle_s_way() -> None:
    path = hairpin(gap_m=4.0)
    tracker = PathTracker()
    tracker.set_path(path)
    eastbound = tracker.locate(30.0, 3.0, 0.0)  # nearer the westbound leg, but heading east
    assert eastbound.s_m == pytest.approx(30.0)
    tracker.set_path(path)
    westbound = tracker.locate(30.0, 3.0, math.pi)
    assert westbound.s_m > 50.0
    assert westbound.north_m == pytest.approx(4.0)


def test_a_new_path_is_joined_at_its_earliest_nearly_closest_point() -> None:
    # A closed square: the vehicle at the start is as close to the start as to the end.
    corners = [(0, 0), (20, 0), (20, 20), (0, 20), (0, 0.5)]
    east = np.concatenate([np.linspace(a[0], b[0], 21)[:-1] for a, b in itertools.pairwise(corners)])
    north = np.concatenate([np.linspace(a[1], b[1], 21)[:-1] for a, b in itertools.pairwise(corners)])
    tracker = PathTracker()
    tracker.set_path(TrackedPath(east, north, np.ones_like(east)))
    assert tracker.locate(0.0, 0.1, 0.0).s_m == pytest.approx(0.0, abs=0.01)


def test_beyond_the_ends_the_path_extends_along_its_end_segments() -> None:
    tracker = PathTracker()
    tracker.set_path(straight_east(20.0))
    for x in np.arange(0.0, 20.0, 0.5):
        tracker.locate(x, 0.0, 0.0)
    past = tracker.locate(23.0, -1.0, 0.0)
    assert past.s_m == pytest.approx(23.0)
    assert past.beyond_end_m == pytest.approx(3.0)
    assert past.cross_track_m == pytest.approx(-1.0)
    tracker.set_path(straight_east(20.0))
    before = tracker.locate(-2.0, 0.5, 0.0)
    assert before.s_m == pytest.approx(-2.0)
    assert before.cross_track_m == pytest.approx(0.5)


def test_look_ahead_point_and_speeds_ahead() -> None:
    east = np.arange(0.0, 31.0)
    speeds = np.where(east < 15, 10.0, 4.0)
    tracker = PathTracker()
    tracker.set_path(TrackedPath(east, np.zeros_like(east), speeds))
    where = tracker.locate(5.0, 1.0, 0.0)
    assert where.speed_mps == pytest.approx(10.0)
    assert tracker.lookahead_point(where, 7.5) == pytest.approx((12.5, 0.0))
    assert tracker.lookahead_point(where, 40.0) == pytest.approx((45.0, 0.0))  # on the extension
    assert tracker.speed_ahead(where, 2.0) == pytest.approx(10.0)
    assert tracker.speed_ahead(where, 9.5) == pytest.approx(7.0)  # halfway between 14 m and 15 m
    assert tracker.speed_ahead(where, 20.0) == pytest.approx(4.0)


def test_heading_turns_smoothly_through_a_corner() -> None:
    path = TrackedPath([0.0, 10.0, 10.0], [0.0, 0.0, 10.0], [1.0, 1.0, 1.0])  # a square left corner
    samples = [path.heading_at(s) for s in np.arange(0.0, 20.01, 0.25)]
    assert samples[0] == pytest.approx(0.0) and samples[-1] == pytest.approx(math.pi / 2)
    assert max(abs(b - a) for a, b in itertools.pairwise(samples)) < 0.05
    assert path.curvature_at(10.0, 2.0) > 0.0  # a left turn


def test_repeated_points_are_dropped() -> None:
    path = TrackedPath.from_points([PathPoint(0, 0, 1), PathPoint(0, 0, 1), PathPoint(5, 0, 1), PathPoint(5, 0, 1)])
    assert path.segments == 1
    assert path.length_m == pytest.approx(5.0)


@pytest.mark.parametrize(
    ("points", "match"),
    [
        ([], "no points"),
        ([PathPoint(1, 1, 1)], "at least 2"),
        ([PathPoint(1, 1, 1), PathPoint(1, 1, 1)], "at least 2"),
        ([PathPoint(0, 0, 1), PathPoint(5, 0, -1)], "negative"),
        ([PathPoint(0, 0, 1), PathPoint(math.nan, 0, 1)], "non-finite"),
    ],
)
def test_unusable_paths_are_refused_with_the_reason(points: list[PathPoint], match: str) -> None:
    with pytest.raises(PathError, match=match):
        TrackedPath.from_points(points)


def test_locating_without_a_path_is_an_error() -> None:
    with pytest.raises(PathError):
        PathTracker().locate(0.0, 0.0, 0.0)
