"""Scan -> obstacle descriptors: accuracy against the true obstacles, and splitting.

"Truth" (see modules/lidar/README.md): a cylinder's centre; a small box's centre, which a lidar
that sees one face only can place to within half the difference of the box's sides (the hidden
side is assumed as long as the visible one); for a large box, the distance from the vehicle to
its nearest point. "In range": within 40 m of the scanner, inside its field of view, and wide
enough to return 3 rays (cylinders) or 5 (boxes, whose corners need two returns per face).
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest

from brain.pose import Pose
from modules.lidar.cluster import ClusterParams, describe_scan, split
from modules.lidar.scan import HORIZONTAL_MOUNTS, Mount, ScanSpec, sensor_pose
from modules.sim.lidar.raycast import Scene, cast
from modules.sim.world import Shape, WorldObstacle
from protocol.messages import Obstacle

SPEC = ScanSpec()
CASES = 300


def place(rng: np.random.Generator, radius: float, max_distance_m: float = 40.0) -> tuple[Pose, Mount, np.ndarray]:
    """A random vehicle pose, one of the horizontal lidars, and an ENU point 3..max m in front of
    that lidar such that a footprint of ``radius`` around it lies inside the field of view."""
    pose = Pose(float(rng.uniform(-200, 200)), float(rng.uniform(-200, 200)), float(rng.uniform(-math.pi, math.pi)))
    mount = HORIZONTAL_MOUNTS[str(rng.choice(sorted(HORIZONTAL_MOUNTS)))]
    origin, yaw = sensor_pose(pose, mount)
    distance = float(rng.uniform(max(3.0, radius + 1.0), max_distance_m))
    limit = math.pi / 2 - math.asin(min(radius / distance, 1.0)) - math.radians(1.0)
    bearing = yaw + float(rng.uniform(-limit, limit))
    return pose, mount, origin + distance * np.array((math.cos(bearing), math.sin(bearing)))


def in_vehicle_frame(pose: Pose, east: float, north: float) -> np.ndarray:
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    dx, dy = east - pose.east_m, north - pose.north_m
    return np.array((c * dx + s * dy, -s * dx + c * dy))


def observe(
    obstacle: WorldObstacle, pose: Pose, mount: Mount, rng: np.random.Generator
) -> tuple[int, tuple[Obstacle, ...]]:
    scan = cast(Scene.from_obstacles([obstacle]), pose, mount, SPEC, rng)
    return int(np.isfinite(scan.ranges_m).sum()), describe_scan(scan)


def position_error(pose: Pose, obstacle: WorldObstacle, found: Obstacle) -> float:
    truth = in_vehicle_frame(pose, obstacle.east_m, obstacle.north_m)
    return math.hypot(found.x_m - truth[0], found.y_m - truth[1])


def observed_cylinders(seed: int) -> Iterator[tuple[Pose, WorldObstacle, Obstacle]]:
    """Random cylinders 0.25-1.5 m in radius, each with the one descriptor the lidar gave for it,
    skipping those it saw with fewer than 3 returns."""
    rng = np.random.default_rng(seed)
    for _ in range(CASES):
        radius = float(rng.uniform(0.25, 1.5))
        pose, mount, centre = place(rng, radius)
        obstacle = WorldObstacle("c", Shape.CYLINDER, *centre, 2.0, radius_m=radius)
        returns, found = observe(obstacle, pose, mount, rng)
        if returns >= 3:
            assert len(found) == 1
            yield pose, obstacle, found[0]


def test_cylinder_centres_are_within_0_2_m_in_range() -> None:
    errors = [position_error(pose, obstacle, o) for pose, obstacle, o in observed_cylinders(20240601)]
    assert len(errors) > 0.95 * CASES
    assert max(errors) <= 0.2


def test_a_cylinder_reaches_no_further_across_the_vehicle_than_its_radius() -> None:
    """What closes a lane past a cylinder is how far its footprint reaches across the vehicle's
    x axis, along which the lane runs: the reported square is square to the vehicle, so its
    corners do not add r (cos theta + sin theta - 1) there, as one square to a lidar mounted at
    15 deg did (0.13 m on a shrub of 0.57 m), or one facing a lidar close beside it."""
    excess = []
    for pose, obstacle, o in observed_cylinders(20261205):
        c, s = math.cos(o.yaw_rad), math.sin(o.yaw_rad)
        across = abs(s) * o.length_m / 2 + abs(c) * o.width_m / 2
        truth = in_vehicle_frame(pose, obstacle.east_m, obstacle.north_m)
        excess.append(across + abs(o.y_m - truth[1]) - obstacle.radius_m)
    assert len(excess) > 0.95 * CASES
    assert np.percentile(excess, 95) <= 0.06


def test_small_box_centres_are_within_0_2_m_plus_the_unobservable_part() -> None:
    rng = np.random.default_rng(20240602)
    resolved, few = [], []  # error beyond the unobservable part, by number of returns
    for _ in range(CASES):
        length, width = rng.uniform(0.3, 1.0, 2)
        pose, mount, centre = place(rng, math.hypot(length, width) / 2)
        yaw = float(rng.uniform(-math.pi, math.pi))
        obstacle = WorldObstacle("b", Shape.BOX, *centre, 2.0, length_m=length, width_m=width, yaw_rad=yaw)
        returns, found = observe(obstacle, pose, mount, rng)
        if returns < 3:
            continue
        assert len(found) == 1
        excess = position_error(pose, obstacle, found[0]) - abs(length - width) / 2
        (resolved if returns >= 5 else few).append(excess)
    assert len(resolved) > 0.4 * CASES and len(resolved) + len(few) > 0.8 * CASES
    assert max(resolved) <= 0.2
    # Three or four returns (a small box beyond ~25 m) place each silhouette edge only to half a
    # ray spacing (0.17 m at 40 m): the criterion does not hold there, this does.
    assert max(few) <= 0.25


def test_large_box_ranges_are_within_0_2_m_of_the_nearest_surface() -> None:
    rng = np.random.default_rng(20240603)
    for _ in range(CASES):
        length, width = rng.uniform(1.0, 6.0, 2)
        pose, mount, centre = place(rng, math.hypot(length, width) / 2)
        yaw = float(rng.uniform(-math.pi, math.pi))
        obstacle = WorldObstacle("b", Shape.BOX, *centre, 2.0, length_m=length, width_m=width, yaw_rad=yaw)
        _, found = observe(obstacle, pose, mount, rng)
        assert found
        nearest = min(o.range_m for o in found)
        assert abs(nearest - distance_to_box(in_vehicle_frame(pose, *centre), yaw - pose.yaw_rad, length, width)) <= 0.2


def distance_to_box(centre: np.ndarray, yaw: float, length: float, width: float) -> float:
    """Distance from the vehicle origin to a box footprint given in the vehicle frame."""
    c, s = math.cos(yaw), math.sin(yaw)
    x, y = -centre[0] * c - centre[1] * s, centre[0] * s - centre[1] * c
    return math.hypot(max(abs(x) - length / 2, 0.0), max(abs(y) - width / 2, 0.0))


@pytest.mark.parametrize("distance", [5.0, 10.0, 20.0, 30.0, 40.0])
def test_two_obstacles_with_a_1_5_m_gap_are_two_clusters(distance: float) -> None:
    # The narrow passage: merged, it would look like one wide obstacle; split, the planner can
    # see the gap (and that it is too narrow for the vehicle).
    mount = Mount(0.0, 0.0, 0.7)
    radius, gap = 0.5, 1.5
    centres = [(distance, radius + gap / 2), (distance, -radius - gap / 2)]
    scene = Scene.from_obstacles(
        [WorldObstacle(str(i), Shape.CYLINDER, x, y, 2.0, radius_m=radius) for i, (x, y) in enumerate(centres)]
    )
    found = describe_scan(cast(scene, Pose(0.0, 0.0, 0.0), mount, SPEC, np.random.default_rng(7)))
    assert len(found) == 2
    for x, y in centres:
        assert min(math.hypot(o.x_m - x, o.y_m - y) for o in found) <= 0.2


def test_a_range_jump_splits_an_obstacle_from_the_wall_behind_it() -> None:
    scene = Scene.from_obstacles(
        [
            WorldObstacle("post", Shape.CYLINDER, 10.0, 0.0, 2.0, radius_m=0.3),
            WorldObstacle("wall", Shape.BOX, 12.0, 0.0, 2.0, length_m=0.5, width_m=8.0),
        ]
    )
    clusters = split(cast(scene, Pose(0.0, 0.0, 0.0), Mount(0.0, 0.0, 0.7), SPEC), ClusterParams())
    assert [round(float(c.ranges_m.min())) for c in clusters] == [12, 10, 12]


def test_descriptors_follow_the_vehicle_frame_conventions() -> None:
    mount = HORIZONTAL_MOUNTS["lidar_h_left"]
    pose = Pose(100.0, -50.0, 1.0)
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)

    def enu(x: float, y: float) -> tuple[float, float]:
        return pose.east_m + c * x - s * y, pose.north_m + s * x + c * y

    near = WorldObstacle("near", Shape.BOX, *enu(8.0, 2.0), 3.0, length_m=2.0, width_m=1.0, yaw_rad=pose.yaw_rad - 0.6)
    far = WorldObstacle("far", Shape.CYLINDER, *enu(20.0, -3.0), 3.0, radius_m=0.6)
    found = describe_scan(cast(Scene.from_obstacles([far, near]), pose, mount, SPEC, np.random.default_rng(3)))
    assert len(found) == 2
    first, second = found
    assert first.range_m < second.range_m  # nearest first
    assert (
        math.hypot(first.x_m - 8.0, first.y_m - 2.0) <= 0.2 and math.hypot(second.x_m - 20.0, second.y_m + 3.0) <= 0.2
    )
    for obstacle in found:
        assert obstacle.height_m == mount.z_m  # a lower bound: the scan plane's height
        assert -math.pi / 4 <= obstacle.yaw_rad < math.pi / 4
        assert 0.0 < obstacle.confidence < 1.0
        assert obstacle.range_m <= math.hypot(obstacle.x_m, obstacle.y_m)
    # The box is closer, so more rays hit it: more returns, more confidence.
    assert first.confidence > second.confidence
    # Its long side (2 m) lies -0.6 rad from the vehicle's x axis: reported as length at yaw -0.6.
    assert abs(first.yaw_rad + 0.6) < 0.05
    assert abs(first.length_m - 2.0) < 0.2 and abs(first.width_m - 1.0) < 0.2


def test_an_empty_scan_describes_nothing() -> None:
    scan = cast(Scene.from_obstacles([]), Pose(0.0, 0.0, 0.0), Mount(0.0, 0.0, 0.7), SPEC)
    assert describe_scan(scan) == ()
