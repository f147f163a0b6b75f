"""Vertical-lidar profiles: which stretches are hazards, which are seen level, and where they land."""

from __future__ import annotations

import math

import numpy as np
import pytest

from brain.fusion import HazardFusion
from brain.fusion.profile import classify_profile
from brain.pose import Pose
from modules.lidar.profile import VERTICAL_MOUNTS
from modules.sim.lidar.profile import profile_scan
from modules.sim.terrain import ground_height
from modules.sim.world import HazardKind, TerrainHazard
from protocol.messages import Sensor, SurfaceProfile
from tests.brain.fusion.helpers import enu_of, parked

STEP, SLOPE, GAP, END = 0.15, 0.5, 3.0, 24.0


def classify(ranges: list[float], heights: list[float]) -> tuple[list, list]:
    stretches = classify_profile(ranges, heights, STEP, SLOPE, GAP, expected_end_m=END)
    return [tuple(row) for row in stretches.hazard.tolist()], [tuple(row) for row in stretches.level.tolist()]


def test_flat_ground_is_one_level_stretch() -> None:
    ranges = np.linspace(4.5, 24.0, 40)
    hazard, level = classify(ranges.tolist(), [0.01] * 40)
    assert hazard == [] and level == [(4.5, 24.0)]


def test_a_ditch_is_a_hazard_from_the_last_level_return_to_the_first_after_it() -> None:
    ranges = [5.0, 6.0, 7.0, 9.5, 10.0, 10.5, 11.0, 12.0, 13.0, 24.0]
    heights = [0.0, 0.0, 0.0, -0.6, -0.6, -0.3, 0.0, 0.0, 0.0, 0.0]
    hazard, level = classify(ranges, heights)
    assert hazard == [(7.0, 11.0)]
    assert level == [(5.0, 7.0), (11.0, 13.0)]  # 13 -> 24 m is too wide a gap to call level


def test_a_berm_a_steep_step_and_lost_ground_are_hazards() -> None:
    berm, _ = classify([5.0, 6.0, 6.5, 7.0, 9.0, 23.5], [0.0, 0.0, 0.4, 0.4, 0.0, 0.0])
    assert berm == [(6.0, 9.0)]
    step, _ = classify([5.0, 5.2, 5.4, 23.5], [0.0, 0.12, 0.12, 0.12])  # within 0.15 m, but a 0.6 rise
    assert step == [(5.0, 5.2)]
    lost, level = classify([5.0, 6.0, 7.0], [0.0, 0.0, 0.0])  # nothing beyond 7 m: the ground fell away
    assert lost == [(7.0, 10.0)] and level == [(5.0, 7.0)]
    lone, _ = classify([20.0, 23.5], [-0.5, 0.0])
    assert lone == [(20.0, 23.5)]
    alone, _ = classify([23.5], [-0.5])
    assert alone == [pytest.approx((23.4, 23.6))]


def test_range_noise_between_the_nearest_returns_is_not_a_wall() -> None:
    # The nearest beams meet the ground 6 cm apart: 1 cm of range noise gives slopes above 0.5.
    # A drive met such a wall 3.5 m ahead at 12.7 m/s, swerved, and left the corridor.
    rng = np.random.default_rng(11)
    mount, sensor = VERTICAL_MOUNTS["lidar_v_left"], int(Sensor.LIDAR_V_LEFT)
    walls = {0.0: 0, 0.05: 0}
    for _ in range(500):
        profile = profile_scan([], Pose(0.0, 0.0, 0.0), mount, sensor, rng)
        for rise in walls:
            stretches = classify_profile(profile.ranges_m, profile.heights_m, STEP, SLOPE, GAP, END, min_rise_m=rise)
            walls[rise] += len(stretches.hazard)
    assert walls[0.05] == 0 < walls[0.0]


def test_mismatched_profiles_are_refused() -> None:
    with pytest.raises(ValueError):
        classify_profile([1.0, 2.0], [0.0], STEP, SLOPE, GAP, END)
    fusion = parked()
    assert not fusion.add_profile(0, SurfaceProfile(Sensor.LIDAR_V_LEFT, 0.5, (5.0, 6.0), (0.0,)))
    assert fusion.stats.bad_descriptor == 1


def test_a_simulated_ditch_lands_where_it_is_and_level_ground_is_cleared() -> None:
    east, north, yaw = 200.0, -40.0, 2.2
    centre = enu_of(east, north, yaw, 15.0, 0.0)
    ditch = TerrainHazard("wash", HazardKind.DITCH, *centre, yaw, length_m=2.5, width_m=14.0, magnitude_m=0.7)
    fusion = parked(east, north, yaw)
    rng = np.random.default_rng(3)
    pose = Pose(east, north, yaw)
    for _ in range(3):
        for name, sensor in (("lidar_v_left", Sensor.LIDAR_V_LEFT), ("lidar_v_right", Sensor.LIDAR_V_RIGHT)):
            assert fusion.add_profile(0, profile_scan([ditch], pose, VERTICAL_MOUNTS[name], int(sensor), rng))
    cost_map = fusion.cost_map()
    hazard = cost_map.hazard_probability >= fusion.cost_config.hazard_threshold
    rows, cols = np.nonzero(hazard)
    hazard_east, hazard_north = cost_map.window.centre_of(rows, cols)
    # Along the vehicle's heading every hazard cell lies in the ditch or the shadow before it.
    c, s = math.cos(yaw), math.sin(yaw)
    along = (hazard_east - east) * c + (hazard_north - north) * s
    across = -(hazard_east - east) * s + (hazard_north - north) * c
    assert along.min() > 13.75 - 1.5 and along.max() < 16.25 + 0.8
    assert np.all(np.abs(np.abs(across) - 0.5) < 0.45)  # on the two scan lines
    assert np.count_nonzero(ground_height([ditch], hazard_east, hazard_north) < -0.5) >= 10  # its floor
    # Both lines see the ditch's floor.
    for lateral in (0.5, -0.5):
        row, col = cost_map.window.cell_of(*enu_of(east, north, yaw, 15.0, lateral))
        assert hazard[row, col]
    # Ground seen level before the ditch is cleared, not merely unknown.
    row, col = cost_map.window.cell_of(*enu_of(east, north, yaw, 8.0, 0.5))
    assert cost_map.hazard_probability[row, col] < 0.3


def test_profiles_from_unknown_sensors_or_without_pose_are_refused() -> None:
    fusion = HazardFusion()
    flat = SurfaceProfile(Sensor.LIDAR_V_LEFT, 0.5, (5.0, 6.0), (0.0, 0.0))
    assert not fusion.add_profile(0, flat)
    assert not parked().add_profile(0, flat._replace(sensor=Sensor.SIM))
