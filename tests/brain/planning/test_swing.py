"""The front corners' swing: exact on a steady turn, taken from the nose's length behind."""

from __future__ import annotations

import math

import numpy as np
import pytest

from brain.planning import PlannerConfig
from brain.planning.swing import FrontSwing, curvature_at, vertex_curvature
from tests.brain.planning.scenes import body_outline

VEHICLE = PlannerConfig().vehicle
SWING = FrontSwing(VEHICLE.front_m, VEHICLE.half_width_m)


def arc(radius_m: float, length_m: float, chord_m: float = 0.5) -> np.ndarray:
    """Equal chords of a left turn from the origin heading east."""
    s = np.linspace(0.0, length_m, math.ceil(length_m / chord_m) + 1)
    return np.column_stack([radius_m * np.sin(s / radius_m), radius_m * (1.0 - np.cos(s / radius_m))])


@pytest.mark.parametrize("radius_m", [VEHICLE.turning_radius_m, 5.0, 10.0, 50.0])
def test_on_a_steady_turn_the_swing_is_how_far_the_outer_front_corner_runs_beyond_the_track(radius_m: float) -> None:
    # The body at every heading round the turn: its farthest point from the turn's centre.
    headings = np.linspace(0.0, math.pi, 50)
    poses = np.column_stack([radius_m * np.sin(headings), radius_m * (1.0 - np.cos(headings)), headings])
    outline = body_outline(poses, VEHICLE, spacing_m=0.01)
    farthest = np.max(np.hypot(outline[:, 0], outline[:, 1] - radius_m))
    assert SWING.of(1.0 / radius_m) == pytest.approx(farthest - (radius_m + VEHICLE.half_width_m), abs=1e-4)
    assert SWING.of(-1.0 / radius_m) == SWING.of(1.0 / radius_m)


def test_the_swing_at_full_lock_outgrows_the_margins_and_vanishes_on_a_straight() -> None:
    config = PlannerConfig()
    assert SWING.of(1.0 / VEHICLE.turning_radius_m) == pytest.approx(0.463, abs=0.001)
    assert SWING.of(1.0 / VEHICLE.turning_radius_m) > config.margin_m + config.corridor_margin_m
    assert SWING.of(0.0) == 0.0


def test_equal_chords_of_an_arc_give_its_curvature() -> None:
    along, curvature = vertex_curvature(arc(4.0, 6.0))
    chord = 8.0 * math.sin(0.5 / 8.0)
    assert along == pytest.approx(np.arange(1, 12) * chord)
    assert curvature == pytest.approx(np.full(11, 0.25), rel=1e-9)
    repeated = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    assert vertex_curvature(repeated)[1] == pytest.approx([0.0])


def test_the_float_forms_for_one_vertex_agree_with_the_array_forms() -> None:
    """Hybrid A* checks its analytic tail vertex by vertex with `curvature_at` and `of`; the gate
    checks the published path with `vertex_curvature` and `at`: they must agree exactly."""
    rng = np.random.default_rng(7)
    points = np.cumsum(rng.normal(0.0, 0.5, (200, 2)), axis=0)
    _along, curvature = vertex_curvature(points)
    one_by_one = [
        curvature_at(tuple(a), tuple(b), tuple(c))
        for a, b, c in zip(points[:-2], points[1:-1], points[2:], strict=True)
    ]
    assert one_by_one == pytest.approx(curvature.tolist(), rel=1e-12)
    assert [SWING.of(k) for k in curvature] == pytest.approx(SWING.at(curvature).tolist(), rel=1e-12)
    assert curvature_at((0.0, 0.0), (0.0, 0.0), (1.0, 0.0)) == 0.0


def test_a_sample_takes_the_tightest_turn_within_the_nose_behind_it() -> None:
    """A straight, then a full-lock turn from 10 m to 12 m, then straight: samples before the
    turn have no swing, the turn's own have its, and after it they keep some for the nose's
    length (the vertex where the turn ends is within it), then none."""
    straight = np.column_stack([np.arange(0.0, 10.5, 0.5), np.zeros(21)])
    turn = arc(VEHICLE.turning_radius_m, 2.0)[1:] + straight[-1]
    heading = 2.0 / VEHICLE.turning_radius_m
    after = turn[-1] + np.outer(np.arange(0.5, 5.5, 0.5), [math.cos(heading), math.sin(heading)])
    points = np.vstack([straight, turn, after])
    end_of_turn = vertex_curvature(points)[0][23]  # point 24; the chords are a hair short of the arc
    samples = np.array(
        [5.0, 10.0, 11.0, 11.9, end_of_turn + VEHICLE.front_m - 0.1, end_of_turn + VEHICLE.front_m + 0.1]
    )
    swing = SWING.along(points, samples)
    full = SWING.of(1.0 / VEHICLE.turning_radius_m)
    assert swing[:2] == pytest.approx([0.0, 0.0])  # up to the turn's first vertex (exclusive)
    assert swing[2:4] == pytest.approx([full, full], rel=1e-3)
    assert 0.0 < swing[4] < full
    assert swing[5] == 0.0
