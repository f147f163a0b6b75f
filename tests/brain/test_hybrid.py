"""Hybrid A*: drivable paths through tight gaps, exactly what the gate checks, bounded work."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from brain.corridor import Course
from brain.grid import GridWindow
from brain.planning import PlannerConfig
from brain.planning.bounds import LocalCorridor
from brain.planning.checks import PathGate
from brain.planning.dubins import dubins_points
from brain.planning.hazards import HazardField
from brain.planning.hybrid import HybridResult, Terrain, hybrid_search
from brain.pose import Pose
from tests.brain.planning.scenes import (
    Map,
    body_distance,
    body_outline,
    body_poses,
    course_through,
    densified,
    polyline_distance,
    straight_course,
)

CONFIG = PlannerConfig()
RADIUS_M = CONFIG.turning_radius_m
COURSE = straight_course(200.0)  # 9.144 m half width
EXAMPLES = settings(
    max_examples=30, deadline=None, derandomize=True, database=None, suppress_health_check=[HealthCheck.too_slow]
)


def gate_for(grid: Map, course: Course) -> PathGate:
    hazards = HazardField(
        grid.window, grid.hazard, grid.cost, CONFIG.clearance_m, CONFIG.cost_cap, CONFIG.caution_probability
    )
    return PathGate(
        hazards,
        LocalCorridor(course.corridor),
        CONFIG.clearance_m,
        CONFIG.corridor_clearance_m,
        CONFIG.check_spacing_m,
        CONFIG.front_swing,
    )


def terrain_for(gate: PathGate) -> Terrain:
    """The search's grid as the planner builds it: free cells with the gate's margins plus the
    slack of any point in the cell, the corridor's depth, footprint cost as the step weight."""
    hazards, window = gate.hazards, gate.hazards.window
    slack = CONFIG.check_spacing_m / 2.0 + window.resolution_m * math.sqrt(2.0) / 2.0
    depth = gate.corridor.depth(window)
    free = (depth >= CONFIG.corridor_clearance_m + slack) & (
        hazards.clearance_m[1:-1, 1:-1] >= CONFIG.clearance_m + slack
    )
    weight = 1.0 + hazards.footprint_cost.astype(float)
    half_spacing = gate.spacing_m / 2
    return Terrain(
        window,
        hazards.clearance_m,
        depth,
        free,
        weight,
        gate.clearance_m + half_spacing,
        gate.corridor_clearance_m + half_spacing,
        gate.spacing_m,
        gate.swing,
    )


def search_east(grid: Map, start: Pose, goal_east: float, **changes: object) -> HybridResult:
    """A search on the straight course to its cross-section at ``goal_east``."""
    half = COURSE.corridor.half_width_m[0]
    settings_ = dataclasses.replace(CONFIG, **changes).hybrid if changes else CONFIG.hybrid
    terrain = terrain_for(gate_for(grid, COURSE))
    return hybrid_search(terrain, settings_, start, np.array([goal_east, -half]), np.array([goal_east, half]), 0.0)


def turn_per_metre(points: np.ndarray) -> np.ndarray:
    """Heading change between consecutive chords per metre of their mean length."""
    chord = np.diff(points, axis=0)
    length = np.hypot(chord[:, 0], chord[:, 1])
    turn = np.abs(np.diff(np.unwrap(np.arctan2(chord[:, 1], chord[:, 0]))))
    return turn / ((length[1:] + length[:-1]) / 2.0)


def assert_drivable(points: np.ndarray, start: Pose) -> None:
    """From the vehicle's pose along its heading, and never tighter than its turning radius."""
    assert points[0] == pytest.approx(start[:2])
    first = math.atan2(points[1, 1] - points[0, 1], points[1, 0] - points[0, 0])
    assert abs(math.remainder(first - start[2], math.tau)) <= 0.11  # half the tightest chord's turn
    assert turn_per_metre(points).max() <= 1.01 / RADIUS_M
    assert np.hypot(*np.diff(points, axis=0).T).max() <= 0.5 + 1e-9


def test_a_gap_of_2_2_m_beside_the_vehicle_is_threaded() -> None:
    """Lethal cell centres 2.2 m apart across a 1 m wall, the gap's middle 3 m to the left of
    the vehicle: the 1.2 m vehicle with 0.15 m margins each side has 0.6 m of play, less the
    gate's sampling slack. The path swerves, lines up and goes through the middle."""
    grid = Map.around(30.0, 0.0, 60.0, 30.0).box(25.0, -15.0, 26.0, 1.95).box(25.0, 4.05, 26.0, 15.0)
    start = Pose(8.0, 0.0, 0.0)
    result = search_east(grid, start, 50.0)
    points = result.points
    assert result.reached_goal and points[-1, 0] == pytest.approx(50.0, abs=0.5)
    assert_drivable(points, start)
    assert gate_for(grid, COURSE).check(points, nose=False).ok
    crossing = densified(points)
    crossing = crossing[np.abs(crossing[:, 0] - 25.5) <= 0.6]
    assert np.all((crossing[:, 1] > 1.9 + CONFIG.clearance_m) & (crossing[:, 1] < 4.1 - CONFIG.clearance_m))


def test_a_gap_on_the_far_side_of_the_corridor_is_reached_by_a_drivable_path() -> None:
    """The vehicle near the right edge, heading along the course; a wall 14 m ahead leaves a gap
    only at the left edge. The path crosses the corridor in turns the vehicle can make."""
    grid = Map.around(30.0, 0.0, 60.0, 30.0).box(22.0, -15.0, 23.0, 4.0)
    start = Pose(8.0, -6.5, 0.0)
    result = search_east(grid, start, 50.0)
    points = result.points
    assert result.reached_goal
    assert_drivable(points, start)
    assert gate_for(grid, COURSE).check(points, nose=False).ok
    crossing = densified(points)
    crossing = crossing[np.abs(crossing[:, 0] - 22.5) <= 0.6]
    assert np.all(crossing[:, 1] > 4.0 + CONFIG.clearance_m)


def test_a_blocked_corridor_ends_short_of_the_wall_without_flooding() -> None:
    """A wall across the whole corridor: the labelling shows the goal unreachable, so the
    search drives to the cells nearest it, in front of the wall, and says it did not get there."""
    grid = Map.around(30.0, 0.0, 60.0, 30.0).box(30.0, -15.0, 31.0, 15.0)
    start = Pose(8.0, 1.0, 0.2)
    result = search_east(grid, start, 50.0)
    points = result.points
    assert not result.reached_goal
    assert_drivable(points, start)
    assert gate_for(grid, COURSE).check(points, nose=False).ok
    assert 30.0 - 3.0 < points[-1, 0] < 30.0 - CONFIG.clearance_m
    assert result.expansions < 200


def test_a_search_out_of_expansions_returns_its_best_way_towards_the_goal() -> None:
    grid = Map.around(30.0, 0.0, 60.0, 30.0).box(22.0, -15.0, 23.0, 4.0)
    start = Pose(8.0, -6.5, 0.0)
    result = search_east(grid, start, 50.0, hybrid_max_expansions=15, hybrid_analytic_every=1000)
    assert not result.reached_goal and result.expansions == 15
    assert len(result.points) >= 2 and result.points[-1, 1] > start[1]  # on its way to the gap
    assert_drivable(result.points, start)


def test_a_start_too_close_to_a_hazard_has_no_path() -> None:
    grid = Map.around(30.0, 0.0, 60.0, 30.0).disc(8.5, 0.3, 0.3)
    result = search_east(grid, Pose(8.0, 0.0, 0.0), 50.0)
    assert len(result.points) == 0 and not result.reached_goal


@given(
    start=st.builds(Pose, st.floats(-10.0, 10.0), st.floats(-10.0, 10.0), st.floats(-math.pi, math.pi)),
    goal=st.builds(Pose, st.floats(-10.0, 10.0), st.floats(-10.0, 10.0), st.floats(-math.pi, math.pi)),
)
@settings(max_examples=200, deadline=None, derandomize=True, database=None)
def test_dubins_curves_end_at_the_goal_pose_in_turns_of_the_radius(start: Pose, goal: Pose) -> None:
    points = np.array(list(dubins_points(start, goal, RADIUS_M, 0.5)))
    assert points[0] == pytest.approx(start[:2]) and points[-1] == pytest.approx(goal[:2], abs=1e-6)
    if len(points) < 2:
        return  # already there
    assert np.hypot(*np.diff(points, axis=0).T).min() > 0.0
    if len(points) >= 3:
        assert turn_per_metre(points).max() <= 1.01 / RADIUS_M
    last = points[-1] - points[-2]
    # The last chord of a turn points half its angle short of the goal's heading.
    assert abs(math.remainder(math.atan2(last[1], last[0]) - goal[2], math.tau)) <= 0.5 / RADIUS_M / 2 + 1e-9


@st.composite
def fields(draw: st.DrawFn) -> tuple[Course, Map, Pose, np.ndarray, np.ndarray, float]:
    """Two legs of 35 m (the second turned up to 60 degrees) 4-10 m half width, up to 20 discs
    and boxes in and around it, the vehicle near the start and the goal across the second leg."""
    half_width = draw(st.floats(4.0, 10.0))
    turn = draw(st.floats(-math.pi / 3, math.pi / 3))
    corner = np.array([35.0, 0.0])
    end = corner + 35.0 * np.array([math.cos(turn), math.sin(turn)])
    course = course_through([(0.0, 0.0), tuple(corner), tuple(end)], half_width_m=half_width)
    grid = Map(GridWindow.centred(float(end[0] + 5.0) / 2.0, float(end[1]) / 2.0, 70.0, 70.0, 0.25))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    start = Pose(3.0, draw(st.floats(-0.5, 0.5)) * (half_width - 1.5), draw(st.floats(-0.5, 0.5)))
    for _ in range(draw(st.integers(0, 20))):
        leg = rng.random() < 0.5
        along, across = rng.uniform(8.0, 33.0), rng.uniform(-half_width, half_width)
        heading = turn if leg else 0.0
        base = corner if leg else np.zeros(2)
        centre = base + along * np.array([math.cos(heading), math.sin(heading)])
        centre += across * np.array([-math.sin(heading), math.cos(heading)])
        if rng.random() < 0.5:
            grid.disc(float(centre[0]), float(centre[1]), rng.uniform(0.2, 1.5))
        else:
            half = rng.uniform(0.2, 2.0, 2)
            grid.box(*(centre - half), *(centre + half))
    goal = corner + 25.0 * np.array([math.cos(turn), math.sin(turn)])
    normal = np.array([-math.sin(turn), math.cos(turn)])
    return course, grid, start, goal - half_width * normal, goal + half_width * normal, turn


@EXAMPLES
@given(scene=fields())
def test_every_path_stays_in_the_corridor_clear_of_hazards_and_drivable(
    scene: tuple[Course, Map, Pose, np.ndarray, np.ndarray, float],
) -> None:
    course, grid, start, goal_a, goal_b, heading = scene
    gate = gate_for(grid, course)
    assume(gate.check(np.array([start[:2]]), nose=False).ok)
    result = hybrid_search(terrain_for(gate), CONFIG.hybrid, start, goal_a, goal_b, heading)
    assert result.expansions <= CONFIG.hybrid_max_expansions
    points = result.points
    if len(points) < 2:
        return
    assert gate.check(points, nose=False).ok
    assert course.corridor.distance_to_edge(*densified(points).T).min() >= CONFIG.corridor_clearance_m - 1e-6
    assert polyline_distance(points, grid.lethal_centres()) >= CONFIG.clearance_m - 1e-6
    assert_drivable(points, start)
    # The whole body, not just the rear axle's tube: its front corners swing out on the turns.
    # (Poses every 5 cm headed along their chord: within a centimetre of the continuous arc.)
    poses = body_poses(points, CONFIG.vehicle)
    assert body_distance(poses, grid.lethal_centres(), CONFIG.vehicle) >= CONFIG.margin_m - 0.01
    depth = course.corridor.distance_to_edge(*body_outline(poses, CONFIG.vehicle).T)
    assert np.min(depth, initial=np.inf) >= CONFIG.corridor_margin_m - 0.01


def test_the_search_method_is_checked() -> None:
    assert CONFIG.search_method == "hybrid"
    assert dataclasses.replace(CONFIG, search_method="lattice").search_method == "lattice"
    with pytest.raises(ValueError, match="search_method"):
        dataclasses.replace(CONFIG, search_method="bfs")
    with pytest.raises(ValueError, match="hybrid_step_m"):
        dataclasses.replace(CONFIG, hybrid_step_m=0.5)  # not out of its 0.5 m bin on a diagonal
