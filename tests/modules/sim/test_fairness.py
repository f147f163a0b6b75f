"""The fairness rule: whatever a scenario places leaves a lane of the vehicle's width + 1 m."""

from __future__ import annotations

import math
import re
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from brain.corridor import FT_TO_M, Course
from brain.rddf import Waypoint
from modules.sim.fairness import LANE_WIDTH_M, Blocker, Stations, blockers, find_unfairness
from modules.sim.scenario import DEFAULT_SCENARIO, ScenarioError, load_scenario

M_PER_DEG = 111_320.0  # near enough: the brute force and the checker share the course
LAT0, LON0 = 34.865, -116.89


def course_file(tmp_path: Path, offset_ft: float, length_m: float = 200.0) -> Path:
    """A straight course due east."""
    end_lon = LON0 + length_m / (M_PER_DEG * math.cos(math.radians(LAT0)))
    path = tmp_path / "course.rddf"
    path.write_text(f"1,{LAT0},{LON0},{offset_ft},25\n2,{LAT0},{end_lon:.7f},{offset_ft},25\n")
    return path


def scenario_file(tmp_path: Path, body: str, head: str = "", offset_ft: float = 30.0) -> Path:
    course_file(tmp_path, offset_ft)
    path = tmp_path / "scenario.toml"
    path.write_text(f'[scenario]\nrddf = "course.rddf"\n{head}\n{body}')
    return path


def box(name: str, at_m: float, offset_m: float, width_m: float, length_m: float = 1.0) -> str:
    return (
        f"[[obstacle]]\nname = '{name}'\nshape = 'box'\nat_m = {at_m}\noffset_m = {offset_m}\n"
        f"length_m = {length_m}\nwidth_m = {width_m}\nheight_m = 1.0\n"
    )


def test_the_default_scenario_is_fair_and_checked_in_well_under_0_2_s() -> None:
    scenario = load_scenario(DEFAULT_SCENARIO)
    timings = []
    for _ in range(3):
        start = time.perf_counter()
        unfair = find_unfairness(Stations.along(scenario.course), blockers(scenario.world))
        timings.append(time.perf_counter() - start)
    assert unfair is None
    assert min(timings) < 0.2


def test_the_old_default_wash_is_refused_naming_the_place(tmp_path: Path) -> None:
    text = DEFAULT_SCENARIO.read_text().replace("width_m = 13.8", "width_m = 14.0")
    rddf = DEFAULT_SCENARIO.with_name("mojave.rddf")
    path = tmp_path / "old.toml"
    path.write_text(text.replace('rddf = "mojave.rddf"', f'rddf = "{rddf}"'))
    # A random rock stands beside the wash (the loader keeps them apart from other obstacles only).
    message = (
        "at 1,849.6 m along the course the widest free lane is 2.14 m, needs 2.20 m: "
        "obstacle 'random_0' / hazard 'wash'"
    )
    with pytest.raises(ScenarioError, match=re.escape(f"{path}: unfair: {message}") + "$"):
        load_scenario(path)


def test_a_gap_too_narrow_between_two_rocks_names_both(tmp_path: Path) -> None:
    half = 30 * FT_TO_M

    def gate(gap_m: float) -> str:
        """Two rocks from the corridor's edges to 1.0 m right and gap_m - 1.0 m left of the centreline."""
        left, right = half - (gap_m - 1.0), half - 1.0
        return box("left", 50.0, half - left / 2, left) + box("right", 50.0, -(half - right / 2), right)

    message = (
        r"at 4\d\.\d m along the course the widest free lane is 2\.00 m, needs 2\.20 m: obstacles 'left', 'right'$"
    )
    with pytest.raises(ScenarioError, match=message):
        load_scenario(scenario_file(tmp_path, gate(2.0)))
    with pytest.raises(ScenarioError, match=r"widest free lane is 2\.15 m"):
        load_scenario(scenario_file(tmp_path, gate(2.15)))
    assert len(load_scenario(scenario_file(tmp_path, gate(2.25))).world.obstacles) == 2


def test_fair_false_lets_a_test_block_the_course(tmp_path: Path) -> None:
    wall = box("wall", 80.0, 0.0, 20.0)
    with pytest.raises(ScenarioError, match=r"widest free lane is 0\.00 m, needs 2\.20 m: obstacle 'wall'$"):
        load_scenario(scenario_file(tmp_path, wall))
    assert load_scenario(scenario_file(tmp_path, wall, head="fair = false")).world.obstacles[0].name == "wall"
    with pytest.raises(ScenarioError, match=r"scenario\.fair: expected true or false"):
        load_scenario(scenario_file(tmp_path, wall, head="fair = 'no'"))


def test_a_thin_wall_between_two_stations_is_seen(tmp_path: Path) -> None:
    stations = Stations.along(Course.from_file(course_file(tmp_path, 30.0)))
    j = len(stations) // 2
    # 5 cm thick, across the whole corridor, half-way between two stations.
    middle = [(stations.east_m[j] + stations.east_m[j + 1]) / 2, (stations.north_m[j] + stations.north_m[j + 1]) / 2]
    yaw = math.atan2(stations.normal_north[j], stations.normal_east[j])
    wall = Blocker("wall", False, *middle, yaw_rad=yaw, half_length_m=12.0, half_width_m=0.025)
    unfair = find_unfairness(stations, [wall])
    assert unfair is not None and unfair.widest_m == 0.0 and unfair.obstacles == ("wall",)


def test_a_3_7_m_corridor_takes_a_rock_at_its_edge_but_not_in_its_middle(tmp_path: Path) -> None:
    offset_ft = 1.85 / FT_TO_M
    edge = "[[obstacle]]\nshape = 'cylinder'\nat_m = 60.0\noffset_m = 1.25\nradius_m = 0.6\nheight_m = 1.0\n"
    assert load_scenario(scenario_file(tmp_path, edge, offset_ft=offset_ft)).world.obstacles
    middle = "[[obstacle]]\nname = 'r'\nshape = 'cylinder'\nat_m = 60.0\nradius_m = 0.3\nheight_m = 1.0\n"
    with pytest.raises(ScenarioError, match=r"widest free lane is 1\.[56]\d m, needs 2\.20 m: obstacle 'r'$"):
        load_scenario(scenario_file(tmp_path, middle, offset_ft=offset_ft))


def test_a_course_narrower_than_the_lane_needs_all_of_it(tmp_path: Path) -> None:
    assert load_scenario(scenario_file(tmp_path, "", offset_ft=3.0)).world.obstacles == ()
    pebble = (
        "[[obstacle]]\nname = 'p'\nshape = 'cylinder'\nat_m = 60.0\noffset_m = 0.85\nradius_m = 0.05\nheight_m = 0.1\n"
    )
    with pytest.raises(ScenarioError, match=r"needs 1\.83 m: obstacle 'p'"):
        load_scenario(scenario_file(tmp_path, pebble, offset_ft=3.0))


def test_a_lane_that_changes_sides_between_two_stations_is_no_lane(tmp_path: Path) -> None:
    stations = Stations.along(Course.from_file(course_file(tmp_path, 30.0)))
    j = len(stations) // 2
    half = float(stations.half_width_m[j])

    def wall(name: str, k: int, along_m: float, low: float, high: float) -> Blocker:
        """A rectangle from ``low`` to ``high`` across the course, 2 m long, ending ``along_m`` past station k."""
        tangent = np.array([stations.normal_north[k], -stations.normal_east[k]])
        normal = np.array([stations.normal_east[k], stations.normal_north[k]])
        centre = np.array([stations.east_m[k], stations.north_m[k]]) + tangent * along_m + normal * (low + high) / 2
        yaw = math.atan2(tangent[1], tangent[0])
        return Blocker(name, False, *centre, yaw_rad=yaw, half_length_m=1.0, half_width_m=(high - low) / 2)

    # The first leaves a lane at the left edge up to station j, the second one at the right edge
    # from station j + 1: each is 2.5 m wide, but the vehicle would have to jump from one to the other.
    first = wall("first", j, -0.95, -half - 1.0, half - 2.5)
    second = wall("second", j + 1, 0.95, -half + 2.5, half + 1.0)
    unfair = find_unfairness(stations, [first, second])
    assert unfair is not None and unfair.at_m == pytest.approx(stations.s_m[j + 1])
    assert unfair.obstacles == ("first", "second") and unfair.widest_m == 0.0
    # Lanes that overlap by the lane's width are one lane.
    first = wall("first", j, -0.95, -half - 1.0, -1.0)
    assert find_unfairness(stations, [first, wall("second", j + 1, 0.95, 1.25, half + 1.0)]) is None
    unfair = find_unfairness(stations, [first, wall("second", j + 1, 0.95, 1.15, half + 1.0)])
    assert unfair is not None and unfair.widest_m == pytest.approx(2.15)


def test_every_point_of_a_bent_corridor_is_near_a_cross_section() -> None:
    """Corner fans: the outside of a sharp bend is looked at too, as densely as the straights."""
    east = np.array([0.0, 60.0, 60.0, 10.0])  # east, a left turn north, a sharper left turn back
    north = np.array([0.0, 0.0, 40.0, 30.0])
    course = synthetic_course(east, north, half_width_m=6.0)
    stations = Stations.along(course)
    rng = np.random.default_rng(5)
    points = rng.uniform([-5.0, -10.0], [70.0, 55.0], size=(4000, 2))
    inside = course.corridor.contains(points[:, 0], points[:, 1])
    first, last = np.array([course.east_m[0], course.north_m[0]]), np.array([course.east_m[-1], course.north_m[-1]])
    beyond_ends = (points - first) @ (np.array([course.east_m[1], course.north_m[1]]) - first) < 0
    beyond_ends |= (points - last) @ (np.array([course.east_m[-2], course.north_m[-2]]) - last) < 0
    for point in points[inside & ~beyond_ends]:
        rel = point - np.column_stack([stations.east_m, stations.north_m])
        across = rel[:, 0] * stations.normal_east + rel[:, 1] * stations.normal_north
        along = rel[:, 0] * stations.normal_north - rel[:, 1] * stations.normal_east
        distance = np.hypot(along, np.maximum(np.abs(across) - stations.half_width_m, 0.0))
        assert distance.min() <= 0.13, point


def synthetic_course(east: np.ndarray, north: np.ndarray, half_width_m: float | list[float]) -> Course:
    """A course through local points (metres), for geometry that must not depend on a file."""
    lat = LAT0 + north / M_PER_DEG
    lon = LON0 + east / (M_PER_DEG * math.cos(math.radians(LAT0)))
    halves = np.broadcast_to(np.asarray(half_width_m, dtype=float), east.shape)
    return Course(
        [
            Waypoint(i + 1, float(a), float(o), float(h) / FT_TO_M, 25.0 if i < len(east) - 1 else 0.0)
            for i, (a, o, h) in enumerate(zip(lat, lon, halves, strict=True))
        ]
    )


# Brute force: each station's strip cut into 2 cm cells across and 9 lines along, a cell blocked
# if a blocker holds its centre on any of the lines; the lane is followed cell run by cell run.
CELL_M = 0.02
LINES = 9


def blocked_cells(stations: Stations, blocking: list[Blocker]) -> tuple[np.ndarray, np.ndarray]:
    widest = float(stations.half_width_m.max())
    grid = np.arange(-widest, widest + CELL_M / 2, CELL_M)
    blocked = np.abs(grid)[None, :] > stations.half_width_m[:, None]
    for along in np.linspace(-stations.strip_m, stations.strip_m, LINES):
        east = stations.east_m[:, None] + along * stations.normal_north[:, None] + grid * stations.normal_east[:, None]
        north = (
            stations.north_m[:, None] - along * stations.normal_east[:, None] + grid * stations.normal_north[:, None]
        )
        for b in blocking:
            d_east, d_north = east - b.east_m, north - b.north_m
            if b.radius_m > 0:
                blocked |= np.hypot(d_east, d_north) <= b.radius_m
            else:
                c, s = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
                blocked |= (np.abs(d_east * c + d_north * s) <= b.half_length_m) & (
                    np.abs(-d_east * s + d_north * c) <= b.half_width_m
                )
    return blocked, stations.half_width_m


def brute_force_fair(blocked: np.ndarray, half_width_m: np.ndarray, lane_m: float) -> bool:
    lane: list[tuple[int, int]] | None = None  # cell runs [first, last) the lane can be in
    need_before = 0.0
    for k, row in enumerate(blocked):
        need = min(lane_m, 2 * float(half_width_m[k]))
        edges = np.flatnonzero(np.diff(np.concatenate([[1], row.astype(int), [1]])))
        runs = [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]
        lane = [
            (a, b)
            for a, b in runs
            if (b - a) * CELL_M >= need
            and (lane is None or any((min(b, y) - max(a, x)) * CELL_M >= min(need, need_before) for x, y in lane))
        ]
        if not lane:
            return False
        need_before = need
    return True


@st.composite
def corridors(draw: st.DrawFn) -> tuple[Stations, list[Blocker]]:
    turns = draw(st.lists(st.floats(-2.0, 2.0), min_size=0, max_size=2))
    lengths = draw(st.lists(st.floats(8.0, 25.0), min_size=len(turns) + 1, max_size=len(turns) + 1))
    halves = draw(st.lists(st.floats(1.5, 6.0), min_size=len(lengths), max_size=len(lengths)))
    heading = np.cumsum([0.0, *turns])
    east = np.concatenate([[0.0], np.cumsum(np.array(lengths) * np.cos(heading))])
    north = np.concatenate([[0.0], np.cumsum(np.array(lengths) * np.sin(heading))])
    stations = Stations.along(synthetic_course(east, north, [*halves, halves[-1]]))
    blocking = []
    for i in range(draw(st.integers(1, 6))):
        k = draw(st.integers(0, len(stations) - 1))
        across = draw(st.floats(-7.0, 7.0))
        centre_east = float(stations.east_m[k] + across * stations.normal_east[k])
        centre_north = float(stations.north_m[k] + across * stations.normal_north[k])
        if draw(st.booleans()):
            blocking.append(Blocker(f"c{i}", False, centre_east, centre_north, radius_m=draw(st.floats(0.05, 3.0))))
        else:
            sizes = draw(st.tuples(st.floats(0.1, 6.0), st.floats(0.1, 6.0)))
            yaw = draw(st.floats(-math.pi, math.pi))
            blocking.append(Blocker(f"r{i}", True, centre_east, centre_north, 0.0, yaw, *sizes))
    return stations, blocking


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(corridors())
def test_the_checker_agrees_with_a_brute_force_check(case: tuple[Stations, list[Blocker]]) -> None:
    stations, blocking = case
    # Cells decide widths to within a few cells: cases that close to the limit are not judged.
    margin = 3 * CELL_M
    cells = blocked_cells(stations, blocking)
    lenient = brute_force_fair(*cells, LANE_WIDTH_M - margin)
    strict = brute_force_fair(*cells, LANE_WIDTH_M + margin)
    assume(lenient == strict)
    assert (find_unfairness(stations, blocking) is None) == strict
