"""End to end on the default scenario: the simulated lidars (their sans-IO ray-casting, clustering and
profiling) drive the fusion along the route, and the map is checked against the world's truth
(which only tests may read): the rocks are hazards where they stand, the ground between is clear,
the wash is a hazard across the road."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest

from brain.fusion import CostMap, HazardFusion
from brain.pose import Pose
from modules.lidar.cluster import describe_scan
from modules.lidar.profile import VERTICAL_MOUNTS
from modules.lidar.scan import HORIZONTAL_MOUNTS
from modules.sim.lidar.profile import profile_scan
from modules.sim.lidar.raycast import Scene, cast
from modules.sim.scenario import DEFAULT_SCENARIO, Scenario, load_scenario
from modules.sim.terrain import ground_height
from modules.sim.world import Shape, WorldObstacle
from protocol.messages import Frame, ObstacleList, Sensor
from tests.brain.fusion.helpers import MS, state

SPEED_MPS = 5.0
NAV_PERIOD_NS = 20 * MS  # 50 Hz navigation states
LIDAR_PERIOD_NS = 40 * MS  # each lidar publishes at 25 Hz, offset from the navigation states
SCAN_PLANE_M = HORIZONTAL_MOUNTS["lidar_h_left"].z_m


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    return load_scenario(DEFAULT_SCENARIO)


def route_pose(scenario: Scenario, s_m: float) -> Pose:
    route = scenario.route
    east = float(np.interp(s_m, route.s_m, route.east_m))
    north = float(np.interp(s_m, route.s_m, route.north_m))
    ahead_e = float(np.interp(s_m + 1.0, route.s_m, route.east_m))
    ahead_n = float(np.interp(s_m + 1.0, route.s_m, route.north_m))
    return Pose(east, north, math.atan2(ahead_n - north, ahead_e - east))


def drive(scenario: Scenario, start_m: float, end_m: float) -> Iterator[tuple[int, Pose, bool]]:
    """(t_ns, pose, is_navigation_tick) along the route at SPEED_MPS, navigation states every
    20 ms and lidar sweeps every 40 ms, 10 ms after a navigation state (so they interpolate)."""
    duration_ns = round((end_m - start_m) / SPEED_MPS * 1e9)
    for t in range(0, duration_ns, 10 * MS):
        nav = t % NAV_PERIOD_NS == 0
        lidar = t % LIDAR_PERIOD_NS == 10 * MS
        if nav or lidar:
            yield t, route_pose(scenario, start_m + SPEED_MPS * t * 1e-9), nav


def distance_to(obstacle: WorldObstacle, east: np.ndarray, north: np.ndarray) -> np.ndarray:
    """Distance from points to the obstacle's footprint (0 inside)."""
    dx, dy = east - obstacle.east_m, north - obstacle.north_m
    if obstacle.shape is Shape.CYLINDER:
        return np.maximum(np.hypot(dx, dy) - obstacle.radius_m, 0.0)
    c, s = math.cos(obstacle.yaw_rad), math.sin(obstacle.yaw_rad)
    u = np.maximum(np.abs(dx * c + dy * s) - obstacle.length_m / 2, 0.0)
    v = np.maximum(np.abs(-dx * s + dy * c) - obstacle.width_m / 2, 0.0)
    return np.hypot(u, v)


def hazard_centres(fusion: HazardFusion, cost_map: CostMap) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.nonzero(cost_map.hazard_probability >= fusion.cost_config.hazard_threshold)
    return cost_map.window.centre_of(rows, cols)


def test_rocks_become_hazards_where_they_stand_and_the_road_between_stays_clear(scenario: Scenario) -> None:
    start_m, end_m = 550.0, 598.0  # up to the narrow passage between two rocks at 601 m
    scene = Scene.from_obstacles(scenario.world.obstacles)
    rng = np.random.default_rng(2005)
    fusion = HazardFusion()
    scanned_from: list[Pose] = []
    in_flight: list[tuple[int, ObstacleList]] = []  # sweeps arrive after the next navigation state
    for t, pose, nav in drive(scenario, start_m, end_m):
        if nav:
            assert fusion.add_pose(t, state(pose.east_m, pose.north_m, pose.yaw_rad, SPEED_MPS))
            for t_meas, message in in_flight:
                assert fusion.add_obstacles(t_meas, message)
            in_flight.clear()
            continue
        for name, sensor in (("lidar_h_left", Sensor.LIDAR_H_LEFT), ("lidar_h_right", Sensor.LIDAR_H_RIGHT)):
            descriptors = describe_scan(cast(scene, pose, HORIZONTAL_MOUNTS[name], rng=rng))
            in_flight.append((t, ObstacleList(sensor, Frame.VEHICLE, descriptors)))
        scanned_from.append(pose)
    assert fusion.poses.stats.interpolated > 0 and fusion.stats.no_pose == 0 and fusion.stats.moves > 5
    cost_map = fusion.cost_map()
    window = cost_map.window
    hazard_east, hazard_north = hazard_centres(fusion, cost_map)
    assert hazard_east.size > 0

    # Every obstacle tall enough for the scan plane and passed within 35 m is a hazard inside its
    # true footprint.
    visible = [
        o
        for o in scenario.world.obstacles
        if o.height_m > SCAN_PLANE_M and window.inside(*window.cell_of(o.east_m, o.north_m))
    ]
    east, north = np.array([p.east_m for p in scanned_from]), np.array([p.north_m for p in scanned_from])
    seen = [o for o in visible if np.hypot(east - o.east_m, north - o.north_m).min() < 35.0]
    assert {"passage_left_rock", "passage_right_rock"} <= {o.name for o in seen}
    for obstacle in seen:
        inside = distance_to(obstacle, hazard_east, hazard_north) <= 0.1
        assert inside.sum() >= 2, f"{obstacle.name} is not a hazard where it stands"
    # ... and no hazard is anywhere else: footprints grow by the lidar's position noise (0.05-0.2 m)
    # and the half cell rasterising adds, so every hazard cell lies within about 0.4 m of an obstacle.
    nearest = np.min([distance_to(o, hazard_east, hazard_north) for o in scenario.world.obstacles], axis=0)
    assert nearest.max() <= 0.5 and np.percentile(nearest, 90) <= 0.35

    # The road from the vehicle through the passage and 35 m on is seen clear, and never lethal.
    for s_m in np.arange(end_m - 3.0, end_m + 35.0, 0.5):
        on_road = route_pose(scenario, s_m)
        row, col = window.cell_of(on_road.east_m, on_road.north_m)
        assert window.inside(row, col) and not cost_map.lethal[row, col]
        clearance = min(distance_to(o, np.array(on_road.east_m), np.array(on_road.north_m)) for o in visible)
        if clearance > 1.5:
            assert cost_map.hazard_probability[row, col] <= fusion.cost_config.clear_probability, s_m
        if clearance > fusion.cost_config.inflation_radius_m + 0.5:
            assert cost_map.cost[row, col] < 0.1 * fusion.cost_config.unknown_cost, s_m


def test_the_wash_becomes_a_hazard_across_the_road(scenario: Scenario) -> None:
    (wash,) = [h for h in scenario.world.hazards if h.name == "wash"]
    start_m, end_m = 1815.0, 1838.0  # the wash is 1848.75-1851.25 m along the route
    rng = np.random.default_rng(1850)
    fusion = HazardFusion()
    for t, pose, nav in drive(scenario, start_m, end_m):
        if nav:
            fusion.add_pose(t, state(pose.east_m, pose.north_m, pose.yaw_rad, SPEED_MPS))
            continue
        for name, sensor in (("lidar_v_left", Sensor.LIDAR_V_LEFT), ("lidar_v_right", Sensor.LIDAR_V_RIGHT)):
            profile = profile_scan(scenario.world.hazards, pose, VERTICAL_MOUNTS[name], int(sensor), rng)
            assert fusion.add_profile(t, profile)
    cost_map = fusion.cost_map()
    hazard_east, hazard_north = hazard_centres(fusion, cost_map)
    # In the wash's frame (u along the road, v across): the hazards cover the ditch's length,
    # extended by the shadow of its near wall and the edge noise (0.35 m at 10 m, 0.8 m at 20 m).
    c, s = math.cos(wash.yaw_rad), math.sin(wash.yaw_rad)
    u = (hazard_east - wash.east_m) * c + (hazard_north - wash.north_m) * s
    v = -(hazard_east - wash.east_m) * s + (hazard_north - wash.north_m) * c
    half = wash.length_m / 2
    assert u.min() > -half - 1.5 and u.max() < half + 1.0
    assert u.min() < -half + 0.3 and u.max() > half - 0.3
    assert np.all(np.abs(v) < wash.width_m / 2)
    deep = ground_height(scenario.world.hazards, hazard_east, hazard_north) < -0.3
    assert deep.sum() > 20
    # Level ground up to the wash is cleared on both scan lines.
    for s_m in np.arange(end_m + 6.0, 1847.0, 0.5):
        pose = route_pose(scenario, s_m)
        for lateral in (0.5, -0.5):
            east = pose.east_m - lateral * math.sin(pose.yaw_rad)
            north = pose.north_m + lateral * math.cos(pose.yaw_rad)
            row, col = cost_map.window.cell_of(east, north)
            assert cost_map.hazard_probability[row, col] < 0.5, (s_m, lateral)
