"""Descriptors land in the ENU cells where they are, whatever the vehicle's heading, and each with
the pose at its own measurement time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from brain.fusion import HazardFusion
from protocol.messages import Frame, Obstacle, Sensor
from tests.brain.fusion.helpers import MS, box, enu_of, obstacles, parked, probability_at, state

EAST, NORTH = 100.0, 50.0


def hazard_cells(fusion: HazardFusion) -> tuple[np.ndarray, np.ndarray]:
    """ENU centres of the cells the map calls hazards."""
    cost_map = fusion.cost_map()
    rows, cols = np.nonzero(cost_map.hazard_probability >= fusion.cost_config.hazard_threshold)
    return cost_map.window.centre_of(rows, cols)


@pytest.mark.parametrize("yaw", [0.0, 0.4, math.pi / 2, 2.5, math.pi, -2.0, -math.pi / 2])
def test_vehicle_frame_obstacle_lands_in_its_enu_cells(yaw: float) -> None:
    fusion = parked(EAST, NORTH, yaw)
    x, y, size, obstacle_yaw = 15.0, 3.0, 1.2, 0.3
    for _ in range(3):
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT, box(x, y, size, confidence=0.9, yaw=obstacle_yaw)))
    east, north = enu_of(EAST, NORTH, yaw, x, y)
    assert probability_at(fusion.cost_map(), east, north) >= fusion.cost_config.hazard_threshold
    hazard_east, hazard_north = hazard_cells(fusion)
    # In the obstacle's own frame every hazard cell lies within its half size, the position noise
    # at 15 m (0.07 m) and the half cell cv2 adds around a polygon.
    c, s = math.cos(yaw + obstacle_yaw), math.sin(yaw + obstacle_yaw)
    along = (hazard_east - east) * c + (hazard_north - north) * s
    across = -(hazard_east - east) * s + (hazard_north - north) * c
    limit = size / 2 + 0.08 + 0.2 * math.sqrt(2) / 2 + 0.1
    assert np.all(np.abs(along) <= limit) and np.all(np.abs(across) <= limit)
    # ... and they fill it: about (size + 2 * noise)^2 of 0.2 m cells, no fewer than the size alone.
    assert hazard_east.size >= (size / 0.2) ** 2


def test_enu_frame_obstacles_land_in_the_same_cells() -> None:
    yaw = 0.9
    east, north = enu_of(EAST, NORTH, yaw, 12.0, -2.0)
    in_vehicle = parked(EAST, NORTH, yaw)
    in_enu = parked(EAST, NORTH, yaw)
    for _ in range(3):
        in_vehicle.add_obstacles(0, obstacles(Sensor.LIDAR_H_RIGHT, box(12.0, -2.0, yaw=0.2)))
        enu = Obstacle(east, north, 1.0, 1.0, 0.7, yaw + 0.2, 0.86, 12.0)
        in_enu.add_obstacles(0, obstacles(Sensor.LIDAR_H_RIGHT, enu, frame=Frame.ENU))
    a, b = hazard_cells(in_vehicle), hazard_cells(in_enu)
    assert a[0].size > 0
    np.testing.assert_allclose(a[0], b[0])
    np.testing.assert_allclose(a[1], b[1])


def test_each_message_is_placed_with_the_pose_at_its_own_time() -> None:
    fusion = HazardFusion()
    fusion.add_pose(0, state(0.0, 0.0, 0.0, speed=10.0))
    fusion.add_pose(100 * MS, state(1.0, 0.0, 0.0, speed=10.0))
    fusion.add_pose(200 * MS, state(2.0, 0.0, 0.0, speed=10.0))
    # Measured at 50 ms, when the vehicle was at east 0.5, though it is at 2.0 by now.
    for _ in range(3):
        fusion.add_obstacles(50 * MS, obstacles(Sensor.LIDAR_H_LEFT, box(10.0, 0.0, confidence=1.0)))
    hazard_east, hazard_north = hazard_cells(fusion)
    assert np.mean(hazard_east) == pytest.approx(10.5, abs=0.11)
    assert np.mean(hazard_north) == pytest.approx(0.0, abs=0.11)


def test_messages_outside_the_pose_history_or_from_unknown_sensors_are_refused() -> None:
    fusion = HazardFusion()
    detection = box(10.0, 0.0)
    assert not fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT, detection))  # no pose yet
    fusion.add_pose(1_000 * MS, state(0.0, 0.0, 0.0))
    assert not fusion.add_obstacles(500 * MS, obstacles(Sensor.LIDAR_H_LEFT, detection))  # too old
    assert not fusion.add_obstacles(1_500 * MS, obstacles(Sensor.LIDAR_H_LEFT, detection))  # too new
    assert not fusion.add_obstacles(1_000 * MS, obstacles(Sensor.SYNTHETIC, detection))
    bad_frame = obstacles(Sensor.LIDAR_H_LEFT, detection)._replace(frame=7)
    assert not fusion.add_obstacles(1_000 * MS, bad_frame)
    far = obstacles(Sensor.LIDAR_H_LEFT, box(150.0, 0.0))
    assert fusion.add_obstacles(1_000 * MS, far)
    stats = fusion.stats
    assert (stats.no_pose, stats.unknown_sensor, stats.bad_frame, stats.out_of_range) == (3, 1, 1, 1)
    assert (fusion.poses.stats.empty, fusion.poses.stats.too_old, fusion.poses.stats.too_new) == (1, 1, 1)
    assert stats.messages == 1 and stats.descriptors == 0
    assert fusion.last_fused_ns == {Sensor.LIDAR_H_LEFT: 1_000 * MS}
