"""The planner's behaviour, scenario by scenario: keep, re-plan around, search through, stop."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from brain.grid import GridWindow
from brain.planning import PlanMode, Planner, PlannerConfig, PlanResult
from brain.planning import planner as planning_planner
from brain.planning.hazards import HazardField
from brain.planning.speed import arc_length, curvature
from protocol.codec import Codec, decode_body
from protocol.messages import NavQuality, Path, VehicleState
from tests.brain.planning.scenes import (
    Map,
    Pose,
    course_through,
    densified,
    path_points,
    polyline_distance,
    straight_course,
)

CONFIG = PlannerConfig()
RDDF_SPEED = 25.0 * 0.44704  # the test courses' 25 mph limit
COURSE = straight_course(400.0)  # 30 ft lateral offset: 9.144 m half width


def planner(course=COURSE, **changes: object) -> Planner:
    return Planner.for_course(course, dataclasses.replace(CONFIG, **changes) if changes else CONFIG)


def field(east: float = 150.0) -> Map:
    """Fusion's window: 120 x 30 m at 0.2 m (600 x 150 cells) centred ahead of the vehicle."""
    return Map.around(east, 0.0, 120.0, 30.0)


def plan(p: Planner, grid: Map, pose: Pose | VehicleState, max_speed: float = 20.0) -> PlanResult:
    return p.plan(pose, grid.window, grid.hazard, grid.cost, max_speed)


def assert_safe(points: np.ndarray, grid: Map, course=COURSE) -> None:
    """Published path: every point of its polyline at least half a width inside the corridor and
    at least half width plus margin from every lethal cell centre."""
    xy = points[:, :2]
    inside = course.corridor.distance_to_edge(*densified(xy).T)
    assert inside.min() >= CONFIG.corridor_clearance_m - 1e-6
    assert polyline_distance(xy, grid.lethal_centres()) >= CONFIG.clearance_m - 1e-6


def test_clear_grid_follows_the_centre_line_at_the_rddf_speed() -> None:
    p = planner()
    grid = field()
    first = plan(p, grid, Pose(100.0, 0.0, 0.0, RDDF_SPEED))
    points = path_points(first.path)
    assert first.mode is PlanMode.REPLAN and not first.slow_mode
    assert np.abs(points[:, 1]).max() < 1e-6
    assert points[0, 0] == pytest.approx(100.0) and points[-1, 0] == pytest.approx(180.0)
    assert np.diff(points[:, 0]).max() <= CONFIG.point_spacing_m + 1e-9
    np.testing.assert_allclose(points[:, 2], RDDF_SPEED)
    second = plan(p, grid, Pose(101.5, 0.05, 0.0, RDDF_SPEED))
    assert second.mode is PlanMode.KEEP and second.path.path_id == first.path.path_id
    assert path_points(second.path)[0, 0] == pytest.approx(101.5)


def test_an_obstacle_on_the_path_makes_a_swerve_with_clearance() -> None:
    p = planner()
    grid = field()
    kept = plan(p, grid, Pose(100.0, 0.0, 0.0, 8.0))
    grid.disc(140.0, 0.0, 1.0)
    result = plan(p, grid, Pose(101.0, 0.0, 0.0, 8.0))
    points = path_points(result.path)
    assert result.mode is PlanMode.REPLAN and not result.slow_mode
    assert result.path.path_id != kept.path.path_id
    assert_safe(points, grid)
    beside = points[np.abs(points[:, 0] - 140.0) < 1.0]
    assert np.all(np.abs(beside[:, 1]) >= 1.0 + CONFIG.clearance_m - 0.2)  # round the 1 m disc
    assert abs(points[-1, 1]) < 0.01  # and back on the centre line afterwards
    assert points[:, 2].max() > 4.0
    # Speeds near the obstacle stay under the clearance cap at each point's distance to its cells ...
    lethal = grid.lethal_centres()
    clearance = np.hypot(points[:, None, 0] - lethal[None, :, 0], points[:, None, 1] - lethal[None, :, 1]).min(axis=1)
    cap = CONFIG.near_hazard_speed_mps + CONFIG.hazard_speed_gain_mps_per_m * (clearance - CONFIG.clearance_m)
    assert np.all(points[:, 2] <= cap + 1e-6)
    # ... and the swerve takes the room the corridor has rather than shaving the disc and slowing.
    assert np.abs(beside[:, 1]).min() > 1.0 + CONFIG.clearance_m + 0.5
    assert points[np.abs(points[:, 0] - 140.0) < 2.0, 2].min() >= 7.5


def chicane(grid: Map) -> Map:
    """Two walls 14 m apart, their gaps on opposite sides: no single swerve gets through. Between
    them there is room for the vehicle's turns (2.3 m radius at the tightest) within the
    clearances; 7 m apart there would not, and the search would find a way only a polyline takes."""
    grid.box(140.0, -15.0, 141.0, 15.0).clear_box(139.0, 3.5, 142.0, 7.5)
    return grid.box(154.0, -15.0, 155.0, 15.0).clear_box(153.0, -7.5, 156.0, -3.5)


def test_a_wash_across_the_road_is_passed_through_the_strip_beside_it_at_speed() -> None:
    """A ditch across the corridor, mapped 0.4 m wider than the default scenario's wash at each
    end (the drive benchmark saw up to 0.58 m), leaves a strip 1.7 m wide at each side: only
    offsets within about 0.15 m of 8.3 m pass the gate, between the regular 0.5 m offset steps.
    A gap-centred offset swerves through it without dropping to the search's slow mode."""
    p = planner()
    grid = field()
    plan(p, grid, Pose(100.0, 0.0, 0.0, 10.0))
    grid.box(150.0, -7.4, 152.5, 7.4)
    result = plan(p, grid, Pose(101.0, 0.0, 0.0, 10.0))
    points = path_points(result.path)
    assert result.mode is PlanMode.REPLAN and not result.slow_mode
    assert_safe(points, grid)
    beside = points[np.abs(points[:, 0] - 151.0) < 2.0]
    assert np.all(np.abs(beside[:, 1]) > 8.1) and np.all(np.abs(beside[:, 1]) < 8.45)
    assert beside[:, 2].min() > 3.0
    without = plan(planner(max_gap_offsets=0), grid, Pose(101.0, 0.0, 0.0, 10.0))
    # The regular offsets alone do not get through: at most a stop short of the wash.
    assert without.mode is not PlanMode.REPLAN or without.partial


def test_a_kept_path_slowed_by_a_rock_beside_it_gives_way_to_a_faster_one() -> None:
    """A rock 1.2 m from the kept centre line leaves it clear but slows it to the near-hazard
    speed; a path passing further away is faster, and replaces it while there is time."""
    p = planner()
    grid = field()
    kept = plan(p, grid, Pose(100.0, 0.0, 0.0, RDDF_SPEED))
    grid.disc(150.0, 1.7, 0.5)
    assert polyline_distance(path_points(kept.path)[:, :2], grid.lethal_centres()) > CONFIG.clearance_m
    slow_there = CONFIG.near_hazard_speed_mps + CONFIG.hazard_speed_gain_mps_per_m * (1.2 - CONFIG.clearance_m)
    result = plan(p, grid, Pose(101.0, 0.0, 0.0, RDDF_SPEED))
    points = path_points(result.path)
    assert result.mode is PlanMode.REPLAN and result.path.path_id != kept.path.path_id
    assert_safe(points, grid)
    beside = points[np.abs(points[:, 0] - 150.0) < 1.0]
    assert beside[:, 1].max() < -0.5 and beside[:, 2].min() > slow_there + 2.0
    again = plan(p, grid, Pose(102.0, float(points[1, 1]), 0.0, RDDF_SPEED))
    assert again.mode is PlanMode.KEEP and again.path.path_id == result.path.path_id


@pytest.mark.parametrize("method", ["hybrid", "lattice"])
def test_a_zigzag_of_gaps_is_searched_through_at_the_search_speed(method: str) -> None:
    p = planner(search_method=method)
    grid = chicane(field())
    result = plan(p, grid, Pose(128.0, 0.0, 0.0, 8.0))  # too fast to stop short of the second wall
    points = path_points(result.path)
    assert result.mode is PlanMode.SEARCH and not result.slow_mode and result.reached_goal
    assert CONFIG.slow_speed_mps < points[:, 2].max() <= CONFIG.search_speed_mps + 1e-9
    assert points[-1, 2] == 0.0
    # Swinging from lock to lock, the steering keeps up at the speeds planned (within one chord).
    wheel = np.arctan(CONFIG.vehicle.wheelbase_m * curvature(points[:, :2], CONFIG.curvature_window_m, signed=True))
    along = arc_length(points[:, :2])
    rate = np.abs(np.diff(wheel)) / np.diff(along) * np.minimum(points[1:, 2], points[:-1, 2])
    assert rate.max() <= 1.3 * CONFIG.vehicle.max_steering_rate_radps
    assert_safe(points, grid)
    dense = densified(points[:, :2])
    through_first = dense[np.abs(dense[:, 0] - 140.5) < 0.5]
    through_second = dense[np.abs(dense[:, 0] - 154.5) < 0.5]
    assert np.all(through_first[:, 1] > 3.5) and np.all(through_second[:, 1] < -3.5)
    # It is the track the vehicle drives, turning no tighter than it can.
    chord = np.diff(points[:-1, :2], axis=0)
    length = np.hypot(chord[:, 0], chord[:, 1])
    turn = np.abs(np.diff(np.unwrap(np.arctan2(chord[:, 1], chord[:, 0])))) / ((length[1:] + length[:-1]) / 2)
    assert turn.max() <= 1.05 / CONFIG.turning_radius_m
    assert points[-1, 0] == pytest.approx(128.0 + CONFIG.horizon_m, abs=0.5)  # on to the horizon
    again = plan(p, grid, Pose(128.5, 0.0, 0.0, 1.0))
    assert again.mode is PlanMode.SEARCH and again.path.path_id == result.path.path_id  # kept while clear


def test_a_gap_narrower_than_the_lattice_is_found_cell_by_cell() -> None:
    """Lethal cell centres 3.2 m apart across a wall leave one row of free cells for the search
    (clearance plus slack plus the front corners' swing at full lock, which the lattice's cells
    keep for pursuit's turns, is 1.40 m each side), at north 0.9: off the stride-3 lattice
    through the vehicle's row (0.1, 0.7, 1.3, ...). The search retries on every cell and gets
    through. Candidates are held to the centre line here, which passes the gap 0.7 m from a wall
    cell."""
    p = planner(max_offsets=1, max_gap_offsets=0, search_method="lattice")
    grid = field().box(140.0, -15.0, 141.0, 15.0).clear_box(139.0, -0.6, 142.0, 2.4)
    assert CONFIG.search_stride == 3
    result = plan(p, grid, Pose(130.0, 0.0, 0.0, 2.0))
    points = path_points(result.path)
    assert result.mode is PlanMode.SEARCH and result.reached_goal
    assert_safe(points, grid)
    crossing = densified(points[:, :2])
    crossing = crossing[np.abs(crossing[:, 0] - 140.5) < 0.6]
    assert np.all(np.abs(crossing[:, 1] - 0.9) < 0.2)


def test_a_lane_no_sure_cell_spans_is_still_a_way_through() -> None:
    """Lethal cell centres 2.0 m apart across a wall, beside the centre line, with a margin of
    0.24 m: the gate asks 0.89 m each side, so the lane's middle 0.2 m passes; but the best cell
    centre is 1.0 m from each wall, below the 1.03 m that makes a cell sure (clearance plus half
    a diagonal and half a sample). The way is labelled on the cells a passing point may lie in,
    so Hybrid A* is sent through the lane, not stopped short of the wall in slow mode."""
    margin = 0.24
    p = planner(max_offsets=1, max_gap_offsets=0, margin_m=margin)
    grid = field().box(140.0, -15.0, 141.0, 15.0).clear_box(139.0, 2.2, 142.0, 4.0)
    sure = CONFIG.half_width_m + margin + CONFIG.check_spacing_m / 2 + 0.2 * math.sqrt(2.0) / 2
    assert polyline_distance(np.array([[140.5, 3.1]]), grid.lethal_centres()) < sure
    result = plan(p, grid, Pose(130.0, 0.0, 0.0, 2.0))
    points = path_points(result.path)
    assert result.mode is PlanMode.SEARCH and result.reached_goal and not result.slow_mode
    crossing = densified(points[:, :2])
    crossing = crossing[np.abs(crossing[:, 0] - 140.5) < 0.6]
    assert len(crossing) and np.all(np.abs(crossing[:, 1] - 3.1) <= 0.11)
    assert polyline_distance(points[:, :2], grid.lethal_centres()) >= CONFIG.half_width_m + margin - 1e-6


def test_a_far_chicane_is_approached_at_speed_and_stopped_short_of() -> None:
    """Far ahead, a candidate clear for well over the stopping distance will do while the search
    confirms there is a way through: drive on, planning a stop short of the chicane."""
    p = planner()
    grid = chicane(field())
    result = plan(p, grid, Pose(100.0, 0.0, 0.0, 6.0))
    points = path_points(result.path)
    assert result.mode is PlanMode.REPLAN and result.partial and not result.slow_mode
    assert points[:5, 2].min() >= 6.0 and points[-1, 2] == 0.0
    nose = CONFIG.vehicle.front_m
    assert points[-1, 0] + nose <= 154.1 - CONFIG.clearance_m  # through the first gap, short of the second wall
    assert_safe(points, grid)
    # Driven on, every path safe, the vehicle is through both gaps without stopping.
    pose = Pose(100.0, 0.0, 0.0, 6.0)
    for _ in range(40):
        result = plan(p, grid, pose)
        points = path_points(result.path)
        assert_safe(points, grid)
        assert result.mode is not PlanMode.STOP
        if pose.east_m > 156.0:
            break
        pose = _step_along(points, 2.0)
    assert pose.east_m > 156.0


def test_a_partial_path_gives_way_to_the_search_while_there_is_room_to_turn() -> None:
    """Walls 10 m apart: a swerve gets through the first gap, and stopping beyond it would leave
    the vehicle 3 m from the second wall, too close to turn for the other gap. Nearing the
    partial path's stop, the search takes over in time, and its track (the vehicle's turns, not
    a polyline's) gets through both."""
    p = planner()
    grid = field().box(140.0, -15.0, 141.0, 15.0).clear_box(139.0, 3.5, 142.0, 7.5)
    grid.box(150.0, -15.0, 151.0, 15.0).clear_box(149.0, -7.5, 152.0, -3.5)
    pose, modes = Pose(100.0, 0.0, 0.0, 6.0), []
    for _ in range(80):
        result = plan(p, grid, pose)
        points = path_points(result.path)
        assert_safe(points, grid)
        modes.append(result.mode)
        if pose.east_m > 156.0 or len(points) < 2:
            break
        pose = _step_along(points, 1.5)
    assert result.mode is not PlanMode.STOP and pose.east_m > 156.0
    searched = modes.index(PlanMode.SEARCH)
    assert searched > 0 and modes[searched - 1] is PlanMode.REPLAN  # from the partial path


def _step_along(points: np.ndarray, distance_m: float) -> Pose:
    """The pose ``distance_m`` along a published path, heading along it, at its speed there."""
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(points[:, :2], axis=0).T))])
    i = min(int(np.searchsorted(along, distance_m)), len(points) - 1)
    heading = math.atan2(points[i, 1] - points[i - 1, 1], points[i, 0] - points[i - 1, 0])
    return Pose(float(points[i, 0]), float(points[i, 1]), heading, max(float(points[i, 2]), 0.5))


@pytest.mark.parametrize("method", ["hybrid", "lattice"])
def test_a_blocked_corridor_stops_short_with_the_nose_clear(method: str) -> None:
    p = planner(search_method=method)
    grid = field().box(150.0, -15.0, 151.0, 15.0)
    result = plan(p, grid, Pose(110.0, 0.0, 0.0, 9.0))
    points = path_points(result.path)
    assert result.slow_mode and not result.reached_goal
    assert points[:, 2].max() <= 1.0 + 1e-9 and points[-1, 2] == 0.0
    assert_safe(points, grid)
    nose = 2.1 - 0.4
    assert points[-1, 0] + nose <= 150.0 - CONFIG.clearance_m + 1e-6
    assert points[-1, 0] > 150.0 - CONFIG.clearance_m - nose - 1.0  # as far as it can go
    # Followed decisively: the same search is kept while more than min_partial_m of it is left,
    # and searched again only nearer its end.
    for east in (112.0, 125.0):
        again = plan(p, grid, Pose(east, 0.0, 0.0, 1.0))
        assert again.mode is PlanMode.SEARCH and again.path.path_id == result.path.path_id
        assert path_points(again.path)[0, 0] == pytest.approx(east, abs=0.01)
    near_end = points[-1, 0] - CONFIG.min_partial_m + 1.0
    assert plan(p, grid, Pose(near_end, 0.0, 0.0, 1.0)).path.path_id != result.path.path_id


def test_a_search_that_stops_short_gives_way_to_one_that_gets_through_once_the_vehicle_moves_on() -> None:
    """Walls 10 m apart, a gap in the first and none yet in the second: the search stops short.
    Then a gap in the second shows (nearer views place a hazard's edges), a zigzag no swerve
    makes. The kept search is not dropped at once (one search followed decisively), but searched
    again ``faster_retry_m`` further on, and the search that gets through replaces it: driven at
    the search speed, not crept along to a stop before the wall with no room left to turn."""
    p = planner()
    grid = field().box(140.0, -15.0, 141.0, 15.0).clear_box(139.0, 3.5, 142.0, 7.5).box(150.0, -15.0, 151.0, 15.0)
    short = plan(p, grid, Pose(110.0, 0.0, 0.0, 9.0))
    assert short.mode is PlanMode.SEARCH and not short.reached_goal
    grid.clear_box(149.0, -7.5, 152.0, -3.5)
    for east in (111.0, 111.0 + CONFIG.faster_retry_m - 0.5):  # the first kept cycle starts the count
        kept = plan(p, grid, Pose(east, 0.0, 0.0, 1.0))
        assert kept.path.path_id == short.path.path_id and not kept.reached_goal
    through = plan(p, grid, Pose(111.0 + CONFIG.faster_retry_m + 0.5, 0.0, 0.0, 1.0))
    assert through.mode is PlanMode.SEARCH and through.reached_goal and not through.slow_mode
    assert through.path.path_id != short.path.path_id
    points = path_points(through.path)
    assert_safe(points, grid)
    assert points[-1, 0] > 152.0 and points[:, 2].max() > 1.0


def test_a_search_that_stops_short_gives_way_to_one_that_gets_further() -> None:
    """As above, with a third wall, closed, 20 m on: the new search stops short too, but past the
    second wall, which is progress; the vehicle follows it (still slowly, to its stop). Searches
    that get no further keep it, so the path changes only as the way ahead opens."""
    p = planner()
    grid = field().box(140.0, -15.0, 141.0, 15.0).clear_box(139.0, 3.5, 142.0, 7.5).box(150.0, -15.0, 151.0, 15.0)
    grid.box(170.0, -15.0, 171.0, 15.0)
    short = plan(p, grid, Pose(110.0, 0.0, 0.0, 9.0))
    assert not short.reached_goal and path_points(short.path)[-1, 0] < 150.0
    grid.clear_box(149.0, -7.5, 152.0, -3.5)
    plan(p, grid, Pose(111.0, 0.0, 0.0, 1.0))
    further = plan(p, grid, Pose(111.0 + CONFIG.faster_retry_m + 0.5, 0.0, 0.0, 1.0))
    assert further.path.path_id != short.path.path_id and not further.reached_goal and further.slow_mode
    points = path_points(further.path)
    assert_safe(points, grid)
    assert 152.0 < points[-1, 0] < 170.0
    for east in (111.0 + 2 * CONFIG.faster_retry_m + 1.0, 111.0 + 3 * CONFIG.faster_retry_m + 1.5):
        assert plan(p, grid, Pose(east, 0.0, 0.0, 1.0)).path.path_id == further.path.path_id


def test_a_blockage_far_ahead_is_driven_towards_at_speed_until_it_is_near() -> None:
    """A wall across the corridor 70 m ahead (as far hazards often look before a lane through them
    is mapped): the vehicle drives on at speed towards a stop short of it, not in slow mode; once
    the stop is within the stopping distance plus ``far_partial_m``, it searches (slowly)."""
    p = planner()
    grid = field(east=120.0).box(150.0, -15.0, 151.0, 15.0)
    far = plan(p, grid, Pose(80.0, 0.0, 0.0, 9.0))
    points = path_points(far.path)
    assert far.mode is PlanMode.REPLAN and far.partial and not far.slow_mode
    assert points[:, 2].max() > 8.0 and points[-1, 2] == 0.0
    assert_safe(points, grid)
    assert points[-1, 0] + 2.1 - 0.4 <= 150.0 - CONFIG.clearance_m + 1e-6
    near = plan(planner(), grid, Pose(110.0, 0.0, 0.0, 9.0))
    assert near.mode is PlanMode.SEARCH and near.slow_mode


def _whole_window_layers(self: Planner, window, hazard, cost, *_: object) -> HazardField:
    cfg = self.config
    return HazardField(window, hazard, cost, cfg.clearance_m, cfg.cost_cap, cfg.caution_probability)


CORNER = course_through([(0.0, 0.0), (130.0, 0.0), (200.0, 70.0)], half_width_m=6.0)


@pytest.mark.parametrize(
    ("course", "scene", "pose"),
    [
        (COURSE, lambda grid: grid.disc(140.0, 0.5, 1.0), Pose(100.0, 0.0, 0.0, 8.0)),
        (COURSE, chicane, Pose(128.0, 0.0, 0.0, 8.0)),  # Hybrid A* through both gaps
        (COURSE, lambda grid: grid.box(150.0, -15.0, 151.0, 15.0), Pose(110.0, 0.0, 0.0, 9.0)),  # blocked
        (CORNER, lambda grid: grid.disc(150.0, 21.0, 1.0).disc(135.0, 3.0, 0.6), Pose(110.0, 0.0, 0.0, 8.0)),
    ],
)
def test_the_layers_cover_only_the_corridor_ahead_and_plan_as_the_whole_window_does(
    course, scene, pose: Pose, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Fusion's window is a 96 m square; the planner builds its layers on the corridor ahead
    widened by its map reach, and plans exactly as it would on the whole window (rocks off the
    corridor, and the cut edges' walls, change nothing)."""
    grid = Map.around(pose.east_m + 40.0, pose.north_m, 96.0, 96.0)
    rng = np.random.default_rng(3)
    for east, north in zip(
        rng.uniform(pose.east_m - 8.0, pose.east_m + 88.0, 60), rng.uniform(-48.0, 48.0, 60), strict=True
    ):
        if course.corridor.distance_to_edge(east, north) < -3.0:
            grid.disc(float(east), float(north), 0.5)
    scene(grid)
    built: list[GridWindow] = []
    layers = planning_planner.HazardField

    def recorded(window: GridWindow, *args: object, **kwargs: object) -> HazardField:
        built.append(window)
        return layers(window, *args, **kwargs)

    monkeypatch.setattr(planning_planner, "HazardField", recorded)
    cropped = plan(planner(course), grid, pose)
    assert len(built) == 1 and built[0].rows * built[0].cols < 0.6 * grid.window.rows * grid.window.cols
    monkeypatch.setattr(Planner, "_hazards", _whole_window_layers)
    whole = plan(planner(course), grid, pose)
    assert cropped.mode is whole.mode and cropped.expansions == whole.expansions
    np.testing.assert_allclose(path_points(cropped.path), path_points(whole.path), rtol=0.0, atol=1e-9)
    assert_safe(path_points(cropped.path), grid, course)


def test_no_faster_way_past_is_looked_for_again_until_the_vehicle_has_moved_on(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Rocks either side of the kept centre line slow it, and no candidate passes them faster:
    the search for one (a re-plan's cost) runs once, then again ``faster_retry_m`` further on."""
    p = planner()
    grid = field()
    kept = plan(p, grid, Pose(100.0, 0.0, 0.0, RDDF_SPEED))
    grid.disc(150.0, 1.7, 0.5).disc(150.0, -1.7, 0.5).box(149.5, 2.4, 150.5, 15.0).box(149.5, -15.0, 150.5, -2.4)
    calls: list[float] = []
    real_choose = planning_planner.choose

    def counted(*args: object, **kwargs: object):
        calls.append(float(args[4]))  # the station it plans from
        return real_choose(*args, **kwargs)

    monkeypatch.setattr(planning_planner, "choose", counted)
    for east in (101.0, 102.0, 103.0, 104.5):
        result = plan(p, grid, Pose(east, 0.0, 0.0, RDDF_SPEED))
        assert result.mode is PlanMode.KEEP and result.path.path_id == kept.path.path_id
    assert calls == pytest.approx([101.0, 104.5])


def test_a_vehicle_already_too_close_to_a_hazard_stands_still() -> None:
    p = planner()
    grid = field().disc(111.0, 0.5, 0.4)
    result = plan(p, grid, Pose(110.0, 0.0, 0.0, 3.0))
    assert result.mode is PlanMode.STOP and result.slow_mode
    assert len(result.path.points) == 1 and result.path.points[0].speed_mps == 0.0


def test_a_swerve_sharper_than_the_vehicle_turns_is_not_offered() -> None:
    """Standing with a 3 m rock 1 m beyond the nose: round it the lattice has only swerves that
    step 2 m sideways in 1 m (a vehicle turning no tighter than 2.3 m would overshoot them), and
    no search gets round forwards. The planner stands still, so the brain backs up."""
    p = planner()
    grid = field().box(102.7, -1.5, 103.7, 1.5)
    result = plan(p, grid, Pose(100.0, 0.0, 0.0, 0.0))
    assert result.mode is PlanMode.STOP and len(result.path.points) == 1
    # Further back, a gentle enough swerve exists and is taken.
    p.reset()
    result = plan(p, grid, Pose(92.0, 0.0, 0.0, 0.0))
    points = path_points(result.path)
    assert result.mode is PlanMode.REPLAN and not result.slow_mode
    assert_safe(points, grid)
    radius = CONFIG.turning_radius_m
    ahead = points[:, 0] - 92.0
    reach = np.where(ahead < radius, radius - np.sqrt(np.maximum(radius**2 - ahead**2, 0.0)), np.inf)
    assert np.all(np.abs(points[:, 1]) <= reach + 0.1)  # within the turning circles from the start


def test_a_vehicle_backed_up_behind_the_start_drives_off_again() -> None:
    """Behind the course's first waypoint (still inside its corridor) the path moves at once: the
    course's own speed does not ramp up from 0 at the start."""
    result = plan(planner(), Map.around(20.0, 0.0, 60.0, 30.0), Pose(-3.0, 0.0, 0.0, 0.0))
    points = path_points(result.path)
    assert result.mode is PlanMode.REPLAN and points[0, 2] == pytest.approx(CONFIG.start_speed_mps)
    assert np.all(points[1:, 2] > CONFIG.start_speed_mps)


def test_outside_the_corridor_or_the_window_means_stop() -> None:
    p = planner()
    assert plan(p, field(), Pose(110.0, 9.0, 0.0, 3.0)).mode is PlanMode.STOP
    p.reset()
    assert plan(p, field(400.0), Pose(110.0, 0.0, 0.0, 3.0)).mode is PlanMode.STOP


def test_the_health_limit_caps_every_speed() -> None:
    result = plan(planner(), field(), Pose(100.0, 0.0, 0.0, 8.0), max_speed=3.0)
    assert path_points(result.path)[:, 2].max() <= 3.0 + 1e-9
    stopped = plan(planner(), field(), Pose(100.0, 0.0, 0.0, 8.0), max_speed=0.0)
    assert path_points(stopped.path)[:, 2].max() == 0.0


def test_speeds_respect_the_turn_and_the_end_of_the_course() -> None:
    corner = course_through([(0.0, 0.0), (100.0, 0.0), (100.0, 60.0)], half_width_m=9.144)
    p = planner(corner)
    grid = Map.around(100.0, 20.0, 60.0, 60.0)
    result = plan(p, grid, Pose(90.0, 0.0, 0.0, 8.0))
    points = path_points(result.path)
    s, _ = p.frame.locate(points[:, 0], points[:, 1], 90.0)
    assert np.all(points[:, 2] <= p.frame.speed_at(s) + 1e-9)
    assert points[:, 2].min() < 5.0  # slowed for the corner
    assert points[-1, 1] == pytest.approx(60.0) and points[-1, 2] == 0.0  # the course ends within the horizon


def test_a_new_profile_starts_from_the_last_one_where_the_vehicle_is() -> None:
    """A vehicle lagging its planned acceleration gets the last plan's speed where it is (up to
    speed_lead_mps more than its own), not its own speed again: the profile keeps accelerating
    instead of waiting for the vehicle."""
    p = planner()
    grid = field()
    first = path_points(plan(p, grid, Pose(100.0, 0.0, 0.0, 4.0)).path)
    assert first[0, 2] == pytest.approx(4.0)
    planned = float(np.interp(106.0, first[:, 0], first[:, 2]))
    assert planned > 4.4
    lagging = path_points(plan(p, grid, Pose(106.0, 0.0, 0.0, 4.0)).path)
    assert lagging[0, 2] == pytest.approx(min(planned, 4.0 + CONFIG.speed_lead_mps))
    far_behind = path_points(plan(p, grid, Pose(120.0, 0.0, 0.0, 1.0)).path)
    assert far_behind[0, 2] == pytest.approx(1.0 + CONFIG.speed_lead_mps)
    off_the_path = path_points(plan(p, grid, Pose(121.0, 3.0, 0.0, 1.0)).path)
    assert off_the_path[0, 2] == pytest.approx(1.0)


def test_path_ids_change_only_on_a_new_plan() -> None:
    p = Planner.for_course(COURSE, CONFIG, first_path_id=500)
    grid = field()
    ids = [plan(p, grid, Pose(100.0 + i, 0.0, 0.0, 8.0)).path.path_id for i in range(3)]
    assert ids == [500, 500, 500]
    grid.disc(150.0, 0.0, 1.0)
    assert plan(p, grid, Pose(103.0, 0.0, 0.0, 8.0)).path.path_id == 501


def test_driving_the_plans_through_an_obstacle_field() -> None:
    """Closed loop: step a few metres along each published path and plan again; every path is
    safe and the vehicle gets past all the obstacles."""
    rng = np.random.default_rng(12)
    course = straight_course(400.0)
    p = planner(course)
    obstacles = [(rng.uniform(120.0, 180.0), rng.uniform(-7.0, 7.0), rng.uniform(0.3, 1.2)) for _ in range(12)]
    pose = Pose(100.0, 0.0, 0.0, 6.0)
    modes = set()
    for _ in range(40):
        grid = Map.around(pose.east_m + 50.0, 0.0, 120.0, 30.0)
        for east, north, radius in obstacles:
            grid.disc(east, north, radius)
        result = plan(p, grid, pose)
        modes.add(result.mode)
        points = path_points(result.path)
        assert_safe(points, grid, course)
        if len(points) < 2:
            break
        ahead = np.searchsorted(np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(points[:, :2], axis=0).T))]), 3.0)
        target = points[min(ahead, len(points) - 1)]
        heading = math.atan2(target[1] - pose.north_m, target[0] - pose.east_m)
        pose = Pose(float(target[0]), float(target[1]), heading, max(float(target[2]), 1.0))
    assert pose.east_m > 185.0
    assert PlanMode.REPLAN in modes


def test_partial_paths_can_be_switched_off() -> None:
    result = plan(planner(allow_partial=False), chicane(field()), Pose(100.0, 0.0, 0.0, 6.0))
    assert result.mode is PlanMode.SEARCH and not result.partial


def test_the_path_is_a_valid_protocol_message_from_a_navigation_state() -> None:
    state = VehicleState(100.0, 0.0, 0.0, 0.0, 8.0, 8.0, 0.0, 0.0, (0.0,) * 25, NavQuality.DGPS)
    result = plan(planner(), field().disc(140.0, 0.0, 1.0), state)
    codec = Codec(None)
    data = codec.encode(b"PATH", result.path, source_id=5, seq=1, t_meas_ns=1, t_pub_ns=2)
    opened = codec.open(data)
    decoded = decode_body(opened.type_id, opened.body)
    assert isinstance(decoded, Path) and decoded == result.path
    assert len(data) < 8192


@pytest.mark.parametrize(
    ("pose", "max_speed", "message"),
    [
        (Pose(float("nan"), 0.0), 5.0, "finite"),
        (Pose(100.0, 0.0, 0.0, -1.0), 5.0, "negative"),
        (Pose(100.0, 0.0), -1.0, "negative"),
    ],
)
def test_bad_inputs_are_refused(pose: Pose, max_speed: float, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        plan(planner(), field(), pose, max_speed)


def test_a_map_of_the_wrong_shape_is_refused() -> None:
    grid = field()
    with pytest.raises(ValueError, match="shape"):
        planner().plan(Pose(100.0, 0.0), grid.window, grid.hazard[:, :-1], grid.cost, 5.0)


@pytest.mark.parametrize(
    "changes",
    [{"margin_m": -0.1}, {"search_stride": 0}, {"max_offsets": 0}, {"transition_times_s": ()}],
)
def test_bad_settings_are_refused(changes: dict[str, object]) -> None:
    with pytest.raises(ValueError, match="PlannerConfig"):
        dataclasses.replace(CONFIG, **changes)
