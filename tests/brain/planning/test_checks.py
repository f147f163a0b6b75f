"""The path gate: hazard clearance (exactly what it promises), corridor, the nose at a stop."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brain.planning import PlannerConfig
from brain.planning.bounds import LocalCorridor
from brain.planning.checks import PathGate, densify
from brain.planning.hazards import HazardField
from brain.planning.swing import FrontSwing
from tests.brain.planning.scenes import Map, body_distance, body_poses, polyline_distance, straight_course

CLEARANCE = 1.0
COURSE = straight_course(200.0, half_width_m=6.0)


def gate_for(grid: Map, nose_m: float = 1.7) -> PathGate:
    hazards = HazardField(grid.window, grid.hazard, grid.cost, CLEARANCE, 10.0, 0.5)
    return PathGate(hazards, LocalCorridor(COURSE.corridor), CLEARANCE, 0.6, 0.25, FrontSwing(nose_m, 0.6))


def test_densify_keeps_vertices_and_spacing() -> None:
    points = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.1], [4.0, 4.1]])
    samples = densify(points, 0.25)
    steps = np.hypot(np.diff(samples.east_m), np.diff(samples.north_m))
    assert steps.max() <= 0.25 + 1e-12
    for vertex in points:
        assert np.min(np.hypot(samples.east_m - vertex[0], samples.north_m - vertex[1])) < 1e-12
    assert samples.along_m[-1] == pytest.approx(1.0 + 0.1 + 5.0)


def test_a_path_past_an_obstacle_passes_only_with_the_clearance() -> None:
    grid = Map.around(50.0, 0.0, 60.0, 16.0).disc(50.0, 2.0, 0.5)
    gate = gate_for(grid)
    near = np.array([[30.0, 0.0], [70.0, 0.0]])  # 2 m from the disc centre: about 1.5 m from its cells
    far_enough = gate.check(near)
    assert far_enough.ok
    touching = gate.check(near + np.array([0.0, 0.8]))
    assert not touching.ok and touching.blocked_at_m == pytest.approx(19.0, abs=1.5)


def test_leaving_the_corridor_fails_where_it_leaves() -> None:
    gate = gate_for(Map.around(50.0, 0.0, 60.0, 16.0))
    verdict = gate.check(np.array([[30.0, 0.0], [40.0, 0.0], [50.0, 5.8]]))
    assert not verdict.ok and np.isinf(verdict.blocked_at_m)
    # Leaves the 6 m band, less the 0.6 m half width, at north 5.4: 10 m + 5.4/5.8 of the slope.
    assert verdict.outside_at_m == pytest.approx(10.0 + np.hypot(10.0, 5.8) * 5.4 / 5.8, abs=0.5)


def test_a_stop_must_keep_its_nose_out_of_the_obstacle() -> None:
    grid = Map.around(50.0, 0.0, 60.0, 16.0).box(52.0, -3.0, 53.0, 3.0)
    gate = gate_for(grid)
    stop_short = np.array([[40.0, 0.0], [50.0, 0.0]])  # the wall's cells are 2.1 m ahead, the nose reaches 1.7
    assert not gate.check(stop_short).ok
    assert gate.check(stop_short, nose=False).ok
    assert gate_for(grid, nose_m=0.5).check(stop_short).ok


@settings(max_examples=40, deadline=None, derandomize=True, database=None)
@given(
    seed=st.integers(0, 10_000),
    vertices=st.lists(st.tuples(st.floats(32.0, 68.0), st.floats(-4.5, 4.5)), min_size=2, max_size=6),
)
def test_a_passing_path_keeps_the_clearance_exactly(seed: int, vertices: list[tuple[float, float]]) -> None:
    """Whatever the polyline, if the gate passes it no lethal cell centre is within the clearance."""
    rng = np.random.default_rng(seed)
    grid = Map.around(50.0, 0.0, 40.0, 12.0)
    for _ in range(6):
        grid.disc(rng.uniform(30.0, 70.0), rng.uniform(-6.0, 6.0), rng.uniform(0.1, 0.8))
    points = np.asarray(vertices)
    if gate_for(grid).check(points).ok:
        assert polyline_distance(points, grid.lethal_centres()) >= CLEARANCE - 1e-9


def test_a_full_lock_turn_keeps_its_front_corner_off_what_the_tube_clears() -> None:
    """A quarter turn left at full lock past a rock just beyond the rear axle's tube: the outer
    front corner runs 0.46 m outside the tube and would pass within the margin, so the gate
    refuses the turn; the straight past the same rock is fine."""
    config = PlannerConfig()
    radius, vehicle = config.turning_radius_m, config.vehicle
    centre = np.array([40.0, radius])
    rock = centre + 3.2 * np.array([math.sin(math.radians(60.0)), -math.cos(math.radians(60.0))])
    grid = Map.around(45.0, 2.0, 30.0, 20.0).box(rock[0] - 0.1, rock[1] - 0.1, rock[0] + 0.1, rock[1] + 0.1)
    (cell,) = grid.lethal_centres()
    hazards = HazardField(
        grid.window, grid.hazard, grid.cost, config.clearance_m, config.cost_cap, config.caution_probability
    )
    gate = PathGate(
        hazards,
        LocalCorridor(COURSE.corridor),
        config.clearance_m,
        config.corridor_clearance_m,
        config.check_spacing_m,
        config.front_swing,
    )
    angle = np.linspace(0.0, math.pi / 2.0, 10)
    turn = np.column_stack([centre[0] + radius * np.sin(angle), centre[1] - radius * np.cos(angle)])
    tube = config.clearance_m + config.check_spacing_m / 2.0
    assert polyline_distance(turn, grid.lethal_centres()) >= tube  # the tube and its sampling slack are clear
    assert body_distance(body_poses(turn, vehicle), np.array([cell]), vehicle) < config.margin_m  # the body is not
    assert not gate.check(turn, nose=False).ok
    straight = np.array([[30.0, cell[1] - config.clearance_m - 0.1], [60.0, cell[1] - config.clearance_m - 0.1]])
    assert gate.check(straight, nose=False).ok
