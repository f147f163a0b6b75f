"""Invariants over random corridors and random obstacle fields (Hypothesis, bounded examples).

Whatever the field: a published path never leaves the corridor (with the vehicle's half width
inside it) and never passes a lethal cell centre closer than half width plus margin; slow mode
never commands more than 1 m/s; and when the corridor is walled off, nothing faster is commanded.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from brain.corridor import Course
from brain.grid import GridWindow
from brain.planning import PlanMode, Planner, PlannerConfig, PlanResult
from tests.brain.planning.scenes import Map, Pose, course_through, densified, path_points, polyline_distance

CONFIG = PlannerConfig()
RESOLUTION_M = 0.25
WINDOW_M = 70.0
# Derandomised: the same examples every run, so the suite stays deterministic.
EXAMPLES = settings(
    max_examples=50, deadline=None, derandomize=True, database=None, suppress_health_check=[HealthCheck.too_slow]
)


@st.composite
def corridors(draw: st.DrawFn) -> Course:
    """Two to four legs of 40-120 m turning up to 60 degrees each, 3-10 m half width."""
    heading = draw(st.floats(-math.pi, math.pi))
    points = [(0.0, 0.0)]
    for _ in range(draw(st.integers(1, 3))):
        heading += draw(st.floats(-math.pi / 3, math.pi / 3))
        length = draw(st.floats(40.0, 120.0))
        points.append((points[-1][0] + length * math.cos(heading), points[-1][1] + length * math.sin(heading)))
    return course_through(points, half_width_m=draw(st.floats(3.0, 10.0)))


@st.composite
def scenes(draw: st.DrawFn) -> tuple[Course, Planner, Pose, Map]:
    course = draw(corridors())
    planner = Planner.for_course(course, CONFIG)
    frame = planner.frame
    station = draw(st.floats(5.0, 30.0))
    east, north = (float(v) for v in frame.to_enu(station, draw(st.floats(-1.0, 1.0))))
    heading = float(frame.heading_at(station)) + draw(st.floats(-0.3, 0.3))
    pose = Pose(east, north, heading, draw(st.floats(0.0, 12.0)))
    ahead_e, ahead_n = (float(v) for v in frame.to_enu(station + 25.0, 0.0))
    grid = Map(GridWindow.centred(ahead_e, ahead_n, WINDOW_M, WINDOW_M, RESOLUTION_M))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    for _ in range(draw(st.integers(0, 14))):
        s, d = rng.uniform(station + 4.0, station + 60.0), rng.uniform(-10.0, 10.0)
        centre_e, centre_n = (float(v) for v in frame.to_enu(s, d))
        if math.hypot(centre_e - east, centre_n - north) < 4.0:
            continue  # keep the vehicle's own spot clear, or every example would be a stop
        if rng.random() < 0.5:
            grid.disc(centre_e, centre_n, rng.uniform(0.2, 1.5))
        else:
            half = rng.uniform(0.2, 2.0, 2)
            grid.box(centre_e - half[0], centre_n - half[1], centre_e + half[0], centre_n + half[1])
    grid.hazard[rng.random(grid.window.shape) < 0.02] = 0.7  # uncertain, not lethal
    return course, planner, pose, grid


def check(result: PlanResult, course: Course, grid: Map, max_speed: float) -> None:
    points = path_points(result.path)
    assert np.all(np.isfinite(points))
    assert points[:, 2].min() >= 0.0 and points[:, 2].max() <= max_speed + 1e-9
    if result.path.slow_mode:
        assert points[:, 2].max() <= CONFIG.slow_speed_mps + 1e-9
    if result.mode is PlanMode.STOP:
        assert len(points) == 1 and points[0, 2] == 0.0
        return
    xy = points[:, :2]
    assert course.corridor.distance_to_edge(*densified(xy).T).min() >= CONFIG.corridor_clearance_m - 1e-6
    assert polyline_distance(xy, grid.lethal_centres()) >= CONFIG.clearance_m - 1e-6


def step_along(result: PlanResult, pose: Pose, metres: float) -> Pose:
    points = path_points(result.path)
    if len(points) < 2:
        return pose
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(points[:, :2], axis=0).T))])
    k = min(int(np.searchsorted(along, metres)), len(points) - 1)
    heading = math.atan2(points[k, 1] - points[k - 1, 1], points[k, 0] - points[k - 1, 0])
    return Pose(float(points[k, 0]), float(points[k, 1]), heading, float(points[k, 2]))


@EXAMPLES
@given(scene=scenes(), max_speed=st.floats(0.0, 15.0))
def test_published_paths_stay_in_the_corridor_and_clear_of_lethal_cells(
    scene: tuple[Course, Planner, Pose, Map], max_speed: float
) -> None:
    course, planner, pose, grid = scene
    for _ in range(3):  # plan, drive a little along the plan, plan again (keep or re-plan)
        result = planner.plan(pose, grid.window, grid.hazard, grid.cost, max_speed)
        check(result, course, grid, max_speed)
        pose = step_along(result, pose, 2.5)


@EXAMPLES
@given(scene=scenes(), wall_ahead_m=st.floats(8.0, 35.0))
def test_a_walled_off_corridor_never_gets_more_than_slow_speed(
    scene: tuple[Course, Planner, Pose, Map], wall_ahead_m: float
) -> None:
    course, planner, pose, grid = scene
    frame = planner.frame
    s_wall = float(frame.locate(pose.east_m, pose.north_m)[0]) + wall_ahead_m
    assume(s_wall + 3.0 < frame.length_m)  # a wall beyond the end of the course stops nothing
    centre_e, centre_n = (float(v) for v in frame.to_enu(s_wall, 0.0))
    heading = float(frame.heading_at(s_wall))
    along = (grid.east - centre_e) * math.cos(heading) + (grid.north - centre_n) * math.sin(heading)
    across = -(grid.east - centre_e) * math.sin(heading) + (grid.north - centre_n) * math.cos(heading)
    width = float(frame.half_width_at(s_wall))
    grid._lethal((np.abs(along) < 0.5) & (np.abs(across) < 3.0 * width))
    # Only walls that really cut the corridor count: outside the window is unknown, so free.
    free = course.corridor.contains(grid.east, grid.north) & ~np.isposinf(grid.cost)
    _, labels = cv2.connectedComponents(np.pad(free, 1, constant_values=True).astype(np.uint8), connectivity=8)
    row, col = grid.window.cell_of(pose.east_m, pose.north_m)
    beyond = grid.window.cell_of(*frame.to_enu(s_wall + 3.0, 0.0))
    assume(labels[row + 1, col + 1] != labels[beyond[0] + 1, beyond[1] + 1])
    result = planner.plan(pose, grid.window, grid.hazard, grid.cost, 15.0)
    check(result, course, grid, 15.0)
    points = path_points(result.path)
    assert result.path.slow_mode and points[:, 2].max() <= CONFIG.slow_speed_mps + 1e-9
    assert points[-1, 2] == 0.0
