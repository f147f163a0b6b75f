"""Stochastic categorisation: what it takes for a detection to become a hazard, and how evidence
is cleared by clear views, fades with age and stays in place as the window rolls."""

from __future__ import annotations

import math

import numpy as np
import pytest

from brain.fusion import CostMap, HazardFusion
from protocol.messages import Sensor
from tests.brain.fusion.helpers import MS, box, enu_of, obstacles, parked, probability_at, state

EAST, NORTH, YAW = 100.0, 50.0, 0.6
AHEAD = (20.0, 0.5)  # in view of both horizontal lidars and of the stereo cameras (10-35 m)


def hazard_centres(cost_map: CostMap) -> set[tuple[float, float]]:
    rows, cols = np.nonzero(cost_map.hazard_probability >= 0.8)
    east, north = cost_map.window.centre_of(rows, cols)
    return set(zip(np.round(east, 6).tolist(), np.round(north, 6).tolist(), strict=True))


def p_ahead(fusion: HazardFusion) -> float:
    return probability_at(fusion.cost_map(), *enu_of(EAST, NORTH, YAW, *AHEAD))


def messages_to_cross(sensors: list[Sensor], confidence: float, limit: int = 20) -> int:
    """How many messages, cycling through ``sensors``, until the cell ahead is a hazard."""
    fusion = parked(EAST, NORTH, YAW)
    for count in range(1, limit + 1):
        sensor = sensors[(count - 1) % len(sensors)]
        fusion.add_obstacles(0, obstacles(sensor, box(*AHEAD, confidence=confidence)))
        if p_ahead(fusion) >= fusion.cost_config.hazard_threshold:
            return count
    raise AssertionError(f"{sensors} never crossed the threshold in {limit} messages")


@pytest.mark.parametrize("sensor", [Sensor.LIDAR_H_LEFT, Sensor.LIDAR_H_RIGHT, Sensor.ESVS])
def test_a_single_detection_stays_below_the_threshold(sensor: Sensor) -> None:
    fusion = parked(EAST, NORTH, YAW)
    fusion.add_obstacles(0, obstacles(sensor, box(*AHEAD, confidence=1.0)))
    cost_map = fusion.cost_map()
    assert 0.5 < p_ahead(fusion) < fusion.cost_config.hazard_threshold
    assert not cost_map.lethal.any()


def test_repeated_detections_cross_it() -> None:
    assert messages_to_cross([Sensor.LIDAR_H_LEFT], confidence=0.86) == 2
    assert messages_to_cross([Sensor.LIDAR_H_LEFT, Sensor.LIDAR_H_RIGHT], confidence=0.86) == 2
    assert messages_to_cross([Sensor.ESVS], confidence=0.86) == 3


def test_agreement_between_sensor_types_crosses_faster() -> None:
    weak = 0.5  # e.g. a lidar cluster of 3-4 returns
    lidar_alone = messages_to_cross([Sensor.LIDAR_H_LEFT], weak)
    two_lidars = messages_to_cross([Sensor.LIDAR_H_LEFT, Sensor.LIDAR_H_RIGHT], weak)
    stereo_alone = messages_to_cross([Sensor.ESVS], weak)
    together = messages_to_cross([Sensor.LIDAR_H_LEFT, Sensor.ESVS], weak)
    assert together == 2
    assert together < min(lidar_alone, stereo_alone)
    assert two_lidars == lidar_alone  # two lidars are one kind of sensor: no agreement bonus


def test_seen_clear_cells_are_cleared() -> None:
    fusion = parked(EAST, NORTH, YAW)
    for _ in range(3):
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT, box(*AHEAD)))
    assert p_ahead(fusion) >= fusion.cost_config.hazard_threshold
    # The object is gone: the lidar now reports nothing there, with the cell in its view.
    for _ in range(6):
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT))
    assert p_ahead(fusion) < 0.5
    for _ in range(6):
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT))
    assert p_ahead(fusion) <= fusion.cost_config.clear_probability


def test_shadows_are_not_cleared() -> None:
    fusion = parked(EAST, NORTH, YAW)
    near, behind_it = (12.0, 0.5), AHEAD
    for _ in range(3):
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT, box(*near), box(*behind_it)))
    # The near object now hides the far one: the far one goes unreported but is not seen clear.
    for _ in range(10):
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT, box(*near)))
    assert p_ahead(fusion) >= fusion.cost_config.hazard_threshold


@pytest.mark.parametrize(
    ("detector", "viewer", "outside_view"),
    [
        # The right lidar, turned 15 deg right, cannot see 10 m to the left beside the bumper.
        (Sensor.LIDAR_H_LEFT, Sensor.LIDAR_H_RIGHT, (3.0, 10.0)),
        # Stereo sees from 10 to 35 m but reports detections a little farther.
        (Sensor.ESVS, Sensor.ESVS, (40.0, 0.0)),
    ],
)
def test_only_cells_in_view_are_cleared(detector: Sensor, viewer: Sensor, outside_view: tuple[float, float]) -> None:
    fusion = parked(EAST, NORTH, YAW)
    for _ in range(4):
        fusion.add_obstacles(0, obstacles(detector, box(*AHEAD), box(*outside_view)))
    cost_map = fusion.cost_map()
    assert p_ahead(fusion) >= 0.8 and probability_at(cost_map, *enu_of(EAST, NORTH, YAW, *outside_view)) >= 0.8
    for _ in range(12):
        fusion.add_obstacles(0, obstacles(viewer))
    cost_map = fusion.cost_map()
    assert p_ahead(fusion) < 0.5  # in view, reported clear
    assert probability_at(cost_map, *enu_of(EAST, NORTH, YAW, *outside_view)) >= 0.8  # out of view: kept


def test_a_low_obstacle_seen_by_stereo_survives_the_lidar_plane_passing_over_it() -> None:
    fusion = parked(EAST, NORTH, YAW)
    for _ in range(4):
        fusion.add_obstacles(0, obstacles(Sensor.ESVS, box(*AHEAD)))
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT))  # sees over it: clear at 0.7 m
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_RIGHT))
    assert p_ahead(fusion) >= fusion.cost_config.hazard_threshold


def test_evidence_fades_toward_unknown_when_unobserved() -> None:
    fusion = parked(EAST, NORTH, YAW)
    for _ in range(4):
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT, box(*AHEAD)))
    row, col = fusion.cost_map().window.cell_of(*enu_of(EAST, NORTH, YAW, *AHEAD))
    before = float(fusion.hazard_log_odds()[row, col])
    half_life_ns = round(fusion.config.half_life_s * 1e9)
    for t in range(50 * MS, half_life_ns + 1, 50 * MS):  # navigation keeps coming, no sensor sees the cell
        fusion.add_pose(t, state(EAST, NORTH, YAW))
    after = float(fusion.hazard_log_odds()[row, col])
    assert after == pytest.approx(before / 2, rel=0.02)
    fusion.add_pose(10 * half_life_ns, state(EAST, NORTH, YAW))
    cost_map = fusion.cost_map()
    assert cost_map.hazard_probability[row, col] == pytest.approx(0.5, abs=0.01)
    assert cost_map.cost[row, col] == pytest.approx(fusion.cost_config.unknown_cost, abs=0.05)


def test_rolling_the_window_keeps_evidence_where_it_is() -> None:
    fusion = parked(EAST, NORTH, YAW)
    for _ in range(3):
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT, box(*AHEAD)))
    spot = enu_of(EAST, NORTH, YAW, *AHEAD)
    first = fusion.cost_map()
    before = probability_at(first, *spot)
    # Drive on 8 m without seeing anything: the window moves, the hazard must not.
    step = 0.5
    for i in range(1, 17):
        east, north = enu_of(EAST, NORTH, YAW, i * step, 0.0)
        fusion.add_pose(i * MS, state(east, north, YAW, speed=5.0))
    second = fusion.cost_map()
    assert fusion.stats.moves >= 2 and second.window != first.window
    assert probability_at(second, *spot) == pytest.approx(before, abs=1e-3)
    assert hazard_centres(second) == hazard_centres(first)  # the very same cells, not shifted ones
    turned = math.pi + YAW  # facing back: the hazard is behind, out of every sensor's view
    east, north = enu_of(EAST, NORTH, YAW, 8.0, 0.0)
    fusion.add_pose(20 * MS, state(east, north, turned))
    for _ in range(10):
        fusion.add_obstacles(20 * MS, obstacles(Sensor.LIDAR_H_LEFT))
        fusion.add_obstacles(20 * MS, obstacles(Sensor.LIDAR_H_RIGHT))
    assert probability_at(fusion.cost_map(), *spot) == pytest.approx(before, abs=1e-3)


def test_a_far_detection_makes_its_noise_ring_suspect_never_lethal() -> None:
    # Stereo places a rock 30 m off within about 0.7 m: the rock is a hazard, the ring round it
    # only a place where it may be, however often it is seen, so a passage beside it stays open
    # until nearer views place it.
    fusion = parked(EAST, NORTH, YAW)
    for _ in range(30):
        fusion.add_obstacles(0, obstacles(Sensor.ESVS, box(30.0, 0.0, confidence=1.0)))
    cost_map = fusion.cost_map()
    threshold = fusion.cost_config.hazard_threshold
    assert probability_at(cost_map, *enu_of(EAST, NORTH, YAW, 30.0, 0.0)) >= threshold
    ring = probability_at(cost_map, *enu_of(EAST, NORTH, YAW, 30.0, 1.0))
    assert 0.6 < ring < threshold
