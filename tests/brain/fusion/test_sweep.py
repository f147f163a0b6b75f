"""Sweeping-lidar ground lines in the map: the wash where it is, to its ends, and for long enough."""

from __future__ import annotations

import math

import numpy as np
import pytest

from brain.fusion import HazardFusion
from brain.fusion.sensors import SensorClass
from brain.pose import Pose
from modules.lidar.sweep import SWEEP_MOUNT, describe_sweep
from modules.sim.lidar.raycast import Scene
from modules.sim.lidar.sweep import sweep_scan
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
        returns = sweep_scan([wash], Scene.from_obstacles(()), Pose(EAST, NORTH, YAW), SWEEP_MOUNT, rng)
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


def wash_is_lethal(fusion: HazardFusion, x_m: float = LINE_M + 1.0, y_m: float = 3.0) -> bool:
    """Whether the map holds the wash, at (x, y) of where the vehicle stood when the line crossed it."""
    cost_map = fusion.cost_map()
    row, col = cost_map.window.cell_of(*enu_of(EAST, NORTH, YAW, x_m, y_m))
    return bool(cost_map.lethal[row, col])


def test_sweeps_placed_with_an_uncertain_heading_count_less_until_the_heading_is_known() -> None:
    """Standing at the start the heading is the compasses' (3.5 deg here): the line 37 m ahead may
    lie 2 m to one side, and what it marks would stay for minutes. It counts for a tenth then."""
    fusion = parked(EAST, NORTH, YAW)
    fusion.add_pose(0, state(EAST, NORTH, YAW, yaw_std=math.radians(3.5)))
    wash_sweeps(fusion, count=1)
    assert not wash_is_lethal(fusion)
    fusion.add_pose(0, state(EAST, NORTH, YAW, yaw_std=math.radians(0.3)))  # 0.2 m at the line: in full
    wash_sweeps(fusion, count=1)
    assert wash_is_lethal(fusion)


def test_one_sweep_of_the_wash_outlasts_obstacle_evidence_while_the_vehicle_stands() -> None:
    fusion = parked(EAST, NORTH, YAW)
    wash_sweeps(fusion, count=1)
    rock = (20.0, 3.0)
    for _ in range(4):
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT, box(*rock)))
    for t in range(100 * MS, 120_000 * MS + 1, 100 * MS):  # two minutes standing, no sensor renewing either
        fusion.add_pose(t, state(EAST, NORTH, YAW))
        if t == 15_000 * MS:  # three obstacle half-lives
            assert probability_at(fusion.cost_map(), *enu_of(EAST, NORTH, YAW, *rock)) < 0.8
    assert wash_is_lethal(fusion)


def test_one_sweep_of_the_wash_lasts_while_the_vehicle_drives_up_and_looks_for_a_way_round() -> None:
    fusion = parked(EAST, NORTH, YAW)
    wash_sweeps(fusion, count=1)
    # On to 4 m short of the wash in 10 s, then 60 m of searching back and forth beside it.
    t, travelled = 0, 0.0
    legs = [(0.0, LINE_M - 4.0, 100)] + [(LINE_M - 4.0, LINE_M - 14.0, 50), (LINE_M - 14.0, LINE_M - 4.0, 50)] * 3
    for begin, stop, steps in legs:
        for x in np.linspace(begin, stop, steps + 1)[1:]:
            t += 100 * MS
            fusion.add_pose(t, state(*enu_of(EAST, NORTH, YAW, float(x), 0.0), YAW))
        travelled += abs(stop - begin)
    assert travelled > 90.0
    assert wash_is_lethal(fusion)


def test_the_sweeps_ground_fades_with_the_distance_driven() -> None:
    slow = parked(EAST, NORTH, YAW, sweep_half_distance_m=10.0)
    wash_sweeps(slow, count=1)
    assert slow.layers is not None
    held = float(slow.layers.evidence[SensorClass.LIDAR_SWEEP].max())
    for step in range(1, 11):  # 10 m on in 1 s: one half-distance, a negligible part of the half-life
        slow.add_pose(step * 100 * MS, state(*enu_of(EAST, NORTH, YAW, float(step), 0.0), YAW))
    faded = float(slow.layers.evidence[SensorClass.LIDAR_SWEEP].max())
    assert faded == pytest.approx(held / 2.0, rel=0.01)


@pytest.mark.parametrize("metres_per_sweep", [0.36, 1.1])  # 30 mph at 37.5 Hz; a starved lidar's 110 ms
def test_sweeps_driving_up_to_the_wash_map_its_near_edge(metres_per_sweep: float) -> None:
    """The near wall: the beams that fall into the wash came back only from 0.7 m past where they
    met the plane, and the vehicle reaches the near wall first."""
    near_m = 60.0  # the wash's near edge, ahead of the first pose
    centre = enu_of(EAST, NORTH, YAW, near_m + 1.25, 0.0)
    wash = TerrainHazard("wash", HazardKind.DITCH, *centre, YAW, length_m=2.5, width_m=14.0, magnitude_m=0.7)
    fusion = parked(EAST, NORTH, YAW)
    rng = np.random.default_rng(3)
    for step, x in enumerate(np.arange(0.0, near_m - LINE_M + 4.0, metres_per_sweep), start=1):
        east, north = enu_of(EAST, NORTH, YAW, float(x), 0.0)
        fusion.add_pose(step * 27 * MS, state(east, north, YAW))
        returns = sweep_scan([wash], Scene.from_obstacles(()), Pose(east, north, YAW), SWEEP_MOUNT, rng)
        assert fusion.add_ground_sweep(step * 27 * MS, describe_sweep(returns, SWEEP_MOUNT, int(Sensor.LIDAR_SWEEP)))
    cost_map = fusion.cost_map()
    for lateral in np.arange(-6.5, 6.6, 0.5):
        row, col = cost_map.window.cell_of(*enu_of(EAST, NORTH, YAW, near_m + 0.05, float(lateral)))
        assert cost_map.lethal[row, col], f"the wash's near edge at {lateral:+.1f} m is not a hazard"


@pytest.mark.parametrize("angle_deg", [0.0, -32.0])
def test_a_ditch_seen_off_to_the_side_at_a_slant_keeps_its_end(angle_deg: float) -> None:
    """gen-2012's wash lay 32 deg across the vehicle's way, seen near the edge of the sweep's
    view: its end came out 0.9-1.3 m wider on the lane side, and a fair lane closed. Driving up to
    it sweep after sweep, its end now lands within 0.5 m (half a beam spacing, the noise, the
    line's own depth and a cell), as straight ahead."""
    yaw, north = math.radians(angle_deg), -17.0 if angle_deg else 1.8
    ditch = TerrainHazard("wash", HazardKind.DITCH, 80.0, north, yaw, length_m=2.761, width_m=3.265, magnitude_m=0.876)
    fusion, rng, rate_hz, speed_mps = HazardFusion(), np.random.default_rng(1), 37.5, 4.0
    for k in range(int(40.0 / speed_mps * rate_hz)):  # from 10 m on to 50 m: the line crosses it
        t_ns, east = round(k * 1e9 / rate_hz), 10.0 + k * speed_mps / rate_hz
        fusion.add_pose(t_ns, state(east, 0.0, 0.0, speed=speed_mps))
        returns = sweep_scan([ditch], Scene.from_obstacles(()), Pose(east, 0.0, 0.0), SWEEP_MOUNT, rng)
        assert fusion.add_ground_sweep(t_ns, describe_sweep(returns, SWEEP_MOUNT, int(Sensor.LIDAR_SWEEP)))
    cost_map = fusion.cost_map()
    for u in (-1.0, 0.0):
        across = np.arange(-4.0, 4.0, 0.05)
        points = [
            (80.0 + u * math.cos(yaw) - v * math.sin(yaw), north + u * math.sin(yaw) + v * math.cos(yaw))
            for v in across
        ]
        hazard = across[[probability_at(cost_map, *point) >= 0.8 for point in points]]
        assert hazard.min() >= -1.63 - 0.5 and hazard.max() <= 1.63 + 0.5
        assert hazard.min() <= -1.63 + 0.2 and hazard.max() >= 1.63 - 0.2  # all of it, though


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
