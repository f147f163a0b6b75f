"""The path gate: hazard clearance (exactly what it promises), corridor, the nose at a stop."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brain.planning.bounds import LocalCorridor
from brain.planning.checks import PathGate, densify
from brain.planning.hazards import HazardField
from tests.brain.planning.scenes import Map, polyline_distance, straight_course

CLEARANCE = 1.0
COURSE = straight_course(200.0, half_width_m=6.0)


def gate_for(grid: Map, nose_m: float = 1.7) -> PathGate:
    hazards = HazardField(grid.window, grid.hazard, grid.cost, CLEARANCE, 10.0, 0.5)
    return PathGate(hazards, LocalCorridor(COURSE.corridor), CLEARANCE, 0.6, 0.25, nose_m)


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
