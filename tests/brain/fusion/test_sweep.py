"""Sweeping-lidar ground lines in the map: the wash where it is, to its ends, and for long enough."""

from __future__ import annotations

import math

import numpy as np
import pytest

from brain.fusion import HazardFusion
from brain.fusion.sensors import SensorClass
from modules.lidar.raycast import Pose2D, Scene
from modules.lidar.sweep import SWEEP_MOUNT, describe_sweep, sweep_scan
from modules.sim.world import HazardKind, TerrainHazard
from protocol.messages import GroundStretch, GroundSweep, Sensor
from tests.brain.fusion.helpers import MS, box, enu_of, obstacles, parked, probability_at, state

EAST, NORTH, YAW = 300.0, -20.0, 0.6
LINE_M = SWEEP_MOUNT.x_m + SWEEP_MOUNT.ground_m


def wash_sweeps(fusion: HazardFusion, count: int = 3) -> None:
    """``count`` sweeps of the default scenario's wash lying under the scan line."""
    centre = enu_of(EAST, NORTH, YAW, LINE_M + 0.5, 0.0)
    wash = TerrainHazard("wash", HazardKind.DITCH, *centre, YAW, length_m=2.5, width_m=14.0, magnitude_m=0.7)
    rng = np.random.default_rng(7)
    for _ in range(count):
        returns = sweep_scan([wash], Scene.from_obstacles(()), Pose2D(EAST, NORTH, YAW), SWEEP_MOUNT, rng)
        assert fusion.add_ground_sweep(0, describe_sweep(returns, SWEEP_MOUNT, int(Sensor.LIDAR_SWEEP)))


def across_of(east: np.ndarray, north: np.ndarray) -> np.ndarray:
    return -(east - EAST) * math.sin(YAW) + (north - NORTH) * math.cos(YAW)


def test_one_sweep_lands_a_wash_to_its_ends_and_clears_the_ground_beside_it() -> None:
    fusion = parked(EAST, NORTH, YAW)
    wash_sweeps(fusion, count=1)  # a busy machine may publish only one while the line is on it
    cost_map = fusion.cost_map()
    rows, cols = np.nonzero(cost_map.lethal)
    across = across_of(*cost_map.window.centre_of(rows, cols))
    # The ends within 0.35 m of the truth (+-7 m): half a beam spacing, the noise and a cell.
    # The strip beside the wash stays open.
    assert across.min() == pytest.approx(-7.0, abs=0.35) and across.max() == pytest.approx(7.0, abs=0.35)
    # The ground beside it is seen level, and after three sweeps cleared.
    wash_sweeps(fusion, count=2)
    cost_map = fusion.cost_map()
    for lateral in (-8.3, 8.3):
        assert probability_at(cost_map, *enu_of(EAST, NORTH, YAW, LINE_M, lateral)) < 0.3
    # Ground the line never crossed is unknown, not cleared.
    assert probability_at(cost_map, *enu_of(EAST, NORTH, YAW, 20.0, 8.3)) == pytest.approx(0.5)


def test_the_ground_line_outlasts_obstacle_evidence() -> None:
    fusion = parked(EAST, NORTH, YAW)
    wash_sweeps(fusion)
    rock = (20.0, 3.0)
    for _ in range(4):
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT, box(*rock)))
    assert fusion.config.sweep_half_life_s >= 3 * fusion.config.half_life_s
    for t in range(100 * MS, 15_000 * MS + 1, 100 * MS):  # 15 s: three obstacle half-lives
        fusion.add_pose(t, state(EAST, NORTH, YAW))
    cost_map = fusion.cost_map()
    assert probability_at(cost_map, *enu_of(EAST, NORTH, YAW, *rock)) < 0.8  # faded from lethal
    row, col = cost_map.window.cell_of(*enu_of(EAST, NORTH, YAW, LINE_M + 1.0, 3.0))
    assert cost_map.lethal[row, col]  # the wash is still there


def test_bad_stretches_are_counted_and_dropped() -> None:
    fusion = parked(EAST, NORTH, YAW)
    good = GroundStretch(LINE_M, LINE_M, -2.0, 2.0, 0.0)
    bad = (
        GroundStretch(math.nan, LINE_M, -2.0, 2.0, 0.0),
        GroundStretch(LINE_M + 1.0, LINE_M, -2.0, 2.0, -0.1),  # near end beyond the far end
        GroundStretch(LINE_M, LINE_M, 2.0, -2.0, 0.0),  # right of left
    )
    assert fusion.add_ground_sweep(0, GroundSweep(Sensor.LIDAR_SWEEP, (good, *bad)))
    assert fusion.stats.bad_descriptor == 3
    far = GroundStretch(200.0, 201.0, -1.0, 1.0, -0.3)
    assert fusion.add_ground_sweep(0, GroundSweep(Sensor.LIDAR_SWEEP, (far,)))
    assert fusion.stats.out_of_range == 1
    assert not fusion.add_ground_sweep(0, GroundSweep(Sensor.SIM, (good,)))  # no model for it
    assert fusion.stats.unknown_sensor == 1
    assert fusion.layers is not None
    assert np.count_nonzero(fusion.layers.evidence[SensorClass.LIDAR_SWEEP]) > 0
