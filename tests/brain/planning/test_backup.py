"""Backing up: along the trail the vehicle came by, clipped to it and to the corridor, straight on
behind it where there is no trail and the map is clear."""

from __future__ import annotations

import math

import numpy as np
import pytest

from brain.planning.backup import MIN_BACK_UP_M, BackUpSettings, FloatArray, Trail, back_up

SETTINGS = BackUpSettings(length_m=4.0, speed_mps=1.0, clearance_m=0.9, trail_clearance_m=0.7)


def everywhere(east: FloatArray, _north: FloatArray) -> np.ndarray:
    return np.ones(np.shape(east), dtype=bool)


def far_from_any_edge(east: FloatArray, _north: FloatArray) -> FloatArray:
    return np.full(np.shape(east), np.inf)


def edge_at(east_m: float):  # type: ignore[no-untyped-def]
    """A corridor whose edge runs north-south at ``east_m``, inside to the east."""
    return lambda east, _north: np.asarray(east, dtype=float) - east_m


def driven_arc(radius_m: float = 6.0, length_m: float = 12.0) -> Trail:
    """A trail left turning left on a circle through the origin, ending at the origin heading north."""
    trail = Trail()
    for s in np.arange(-length_m, 0.0 + 1e-9, 0.05):
        angle = s / radius_m
        trail.add(radius_m * (1.0 - math.cos(angle)), radius_m * math.sin(angle))
    return trail


def test_the_way_back_follows_the_trail_newest_first_for_the_length_asked() -> None:
    trail = driven_arc()
    end_east, end_north = trail.points[-1]
    way = back_up(trail, end_east, end_north, math.pi / 2, far_from_any_edge, everywhere, SETTINGS)
    assert way is not None
    assert way.points[0] == (end_east, end_north)
    assert way.length_m == pytest.approx(4.0, abs=0.3)
    # Every point lies on the driven circle (centre (6, 0)), going back the way it came.
    for east, north in way.points:
        assert math.hypot(east - 6.0, north) == pytest.approx(6.0, abs=1e-6)
    assert [n for _e, n in way.points] == sorted((n for _e, n in way.points), reverse=True)
    assert way.speeds(1.0)[-1] == 0.0 and set(way.speeds(1.0)[:-1]) == {1.0}


def test_the_trail_it_backed_over_is_dropped() -> None:
    trail = driven_arc()
    before = len(trail.points)
    way = back_up(trail, *trail.points[-1], math.pi / 2, far_from_any_edge, everywhere, SETTINGS)
    assert way is not None
    trail.drop_newest(way.trail_used)
    assert len(trail.points) == before - way.trail_used
    assert 0.0 < math.dist(trail.points[-1], way.points[-1]) < 2 * trail.spacing_m


def test_the_way_back_ends_where_the_corridor_clearance_does() -> None:
    trail = Trail()
    for east in np.arange(-10.0, 0.01, 0.25):
        trail.add(float(east), 0.0)
    way = back_up(trail, 0.0, 0.0, 0.0, edge_at(-3.2), everywhere, SETTINGS)
    assert way is not None
    assert min(e for e, _n in way.points) >= -3.2 + SETTINGS.trail_clearance_m
    assert way.length_m == pytest.approx(2.5, abs=0.26)


def test_a_trail_driven_close_to_the_edge_is_backed_over_and_not_beyond() -> None:
    """The vehicle crept along the corridor's edge, its rear axle 0.8 m inside: closer than the
    clearance a straight way back needs (0.9 m), as far as its forward planner kept (0.7 m).
    It backs out the way it came, but not straight on past the trail's end."""
    trail = Trail()
    for north in np.arange(-2.0, 0.01, 0.25):
        trail.add(0.8, float(north))
    way = back_up(trail, 0.8, 0.0, math.pi / 2, edge_at(0.0), everywhere, SETTINGS)
    assert way is not None and way.trail_used == len(trail.points)
    assert way.points[-1] == pytest.approx((0.8, -2.0), abs=1e-9)


def test_without_a_trail_it_backs_straight_while_the_map_is_clear() -> None:
    way = back_up(Trail(), 0.0, 0.0, math.pi / 2, far_from_any_edge, everywhere, SETTINGS)
    assert way is not None and way.trail_used == 0
    assert way.points[-1] == pytest.approx((0.0, -4.0), abs=1e-9)
    hazard_behind = back_up(
        Trail(), 0.0, 0.0, math.pi / 2, far_from_any_edge, lambda e, n: np.asarray(n) > -2.0, SETTINGS
    )
    assert hazard_behind is not None and hazard_behind.points[-1][1] > -2.0


def test_a_short_trail_is_continued_straight_on_the_way_it_last_went() -> None:
    trail = Trail()
    for east in np.arange(-1.5, 0.01, 0.25):
        trail.add(float(east), 0.0)
    way = back_up(trail, 0.0, 0.0, 0.0, far_from_any_edge, everywhere, SETTINGS)
    assert way is not None
    assert way.points[-1] == pytest.approx((-4.0, 0.0), abs=1e-9)


def test_no_room_behind_means_no_way_back() -> None:
    assert (
        back_up(Trail(), 0.0, 0.0, 0.0, edge_at(-MIN_BACK_UP_M + 0.2 - SETTINGS.clearance_m), everywhere, SETTINGS)
        is None
    )
