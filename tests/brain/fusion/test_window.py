"""Window placement: the vehicle and the road ahead are covered on every heading; a rectangle
turns its long side to the heading's axis without flapping; evidence survives the turn."""

from __future__ import annotations

import math

import numpy as np
import pytest

from brain.fusion import FusionConfig, HazardFusion, Pose
from brain.fusion.window import WindowPlacement
from brain.grid import GridWindow
from protocol.messages import Sensor
from tests.brain.fusion.helpers import box, enu_of, obstacles, probability_at, state

SQUARE = FusionConfig().placement()
PLANNER = FusionConfig(window_east_m=120.0, window_north_m=30.0).placement()


def covers(window: GridWindow, east: float, north: float, margin: float = 0.0) -> bool:
    return (
        window.origin_east_m + margin <= east <= window.origin_east_m + window.cols * window.resolution_m - margin
        and window.origin_north_m + margin
        <= north
        <= window.origin_north_m + window.rows * window.resolution_m - margin
    )


@pytest.mark.parametrize("yaw", np.linspace(-math.pi, math.pi, 25))
def test_the_default_square_covers_the_vehicle_and_85_m_ahead_on_any_heading(yaw: float) -> None:
    pose = Pose(1234.5, -678.9, float(yaw))
    window = SQUARE.place(pose)
    assert window.shape == (480, 480)
    # Just before the window moves, the vehicle has gone up to recentre_m past where it was placed.
    for late in (0.0, SQUARE.recentre_m):
        east, north = enu_of(pose.east_m, pose.north_m, pose.yaw_rad, late, 0.0)
        assert covers(window, east, north, margin=SQUARE.margin_m - late - 0.2)
        assert covers(window, *enu_of(east, north, pose.yaw_rad, 85.0 - late, 0.0))


def test_the_planners_rectangle_turns_to_the_heading_without_flapping() -> None:
    east_bound = PLANNER.place(Pose(0.0, 0.0, 0.1))
    assert east_bound.shape == (150, 600)
    assert covers(east_bound, *enu_of(0.0, 0.0, 0.1, 80.0, 0.0)) and covers(east_bound, 0.0, 0.0, margin=5.0)
    north_bound = PLANNER.place(Pose(0.0, 0.0, math.pi / 2 + 0.2))
    assert north_bound.shape == (600, 150)
    assert covers(north_bound, *enu_of(0.0, 0.0, math.pi / 2 + 0.2, 80.0, 0.0))
    # Within 10 deg of the diagonal the current orientation stays, past it the window turns.
    assert PLANNER.place(Pose(0.0, 0.0, math.radians(50.0)), east_bound).shape == (150, 600)
    assert PLANNER.needs_move(east_bound, Pose(0.0, 0.0, math.radians(56.0)))
    assert PLANNER.place(Pose(0.0, 0.0, math.radians(56.0)), east_bound).shape == (600, 150)
    # Across its short side the centre is held back so the vehicle stays 5 m inside.
    diagonal = PLANNER.place(Pose(0.0, 0.0, math.radians(44.0)))
    assert covers(diagonal, 0.0, 0.0, margin=5.0 - 0.2)


def test_the_window_moves_only_in_jumps() -> None:
    window = SQUARE.place(Pose(0.0, 0.0, 0.0))
    assert not SQUARE.needs_move(window, Pose(SQUARE.recentre_m - 0.1, 0.0, 0.0))
    assert SQUARE.needs_move(window, Pose(SQUARE.recentre_m + 0.1, 0.0, 0.0))
    assert SQUARE.needs_move(window, Pose(0.0, 0.0, 0.2))  # turning swings the centre 40 m ahead


def test_evidence_survives_the_rectangle_turning() -> None:
    fusion = HazardFusion(FusionConfig(window_east_m=120.0, window_north_m=30.0))
    yaw = math.radians(40.0)
    fusion.add_pose(0, state(0.0, 0.0, yaw))
    spot = enu_of(0.0, 0.0, yaw, 8.0, 0.0)
    for _ in range(3):
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT, box(8.0, 0.0)))
    before = fusion.cost_map()
    assert before.window.shape == (150, 600) and probability_at(before, *spot) >= 0.8
    fusion.add_pose(1_000_000, state(0.0, 0.0, math.radians(70.0)))
    after = fusion.cost_map()
    assert after.window.shape == (600, 150) and fusion.stats.moves == 1
    assert probability_at(after, *spot) == pytest.approx(probability_at(before, *spot))


def test_impossible_placements_are_refused() -> None:
    with pytest.raises(ValueError):
        WindowPlacement(96.0, 96.0, 0.2, lead_m=40.0, recentre_m=6.0, margin_m=5.0)
    with pytest.raises(ValueError):
        WindowPlacement(120.0, 8.0, 0.2, lead_m=40.0, recentre_m=3.0, margin_m=5.0)
    with pytest.raises(ValueError):
        HazardFusion(FusionConfig(window_north_m=0.0))
    with pytest.raises(ValueError):
        FusionConfig(evidence_min=0.5)
    with pytest.raises(ValueError):
        FusionConfig(half_life_s=0.0)
