"""Drive measures on a replayed drive of the default course."""

from __future__ import annotations

import math

import numpy as np
import pytest

from modules.referee.measures import Referee, distance_to_polyline
from modules.sim.nav import replay
from modules.sim.scenario import DEFAULT_SCENARIO, load_scenario
from modules.sim.simulator import WorldState
from modules.sim.vehicle import VehicleParams
from protocol.messages import Path, PathPoint, SimTruth


def test_distance_to_a_polyline() -> None:
    points = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    assert distance_to_polyline(points, 5.0, 2.0) == pytest.approx(2.0)
    assert distance_to_polyline(points, 12.0, 5.0) == pytest.approx(2.0)
    assert distance_to_polyline(points, -3.0, -4.0) == pytest.approx(5.0)


def test_a_pure_pursuit_drive_is_measured() -> None:
    scenario = load_scenario(DEFAULT_SCENARIO)
    world = WorldState(scenario, VehicleParams())
    driver = replay.route_driver(scenario.route, max_speed_mps=8.0)
    referee = Referee(scenario)
    route = scenario.route
    referee.on_path(
        Path(1, tuple(PathPoint(e, n, 5.0) for e, n in zip(route.east_m, route.north_m, strict=True)), False)
    )
    for step in range(4000):  # 40 s
        world.advance(driver(world.state, step * 0.01), 0.01)
        referee.on_truth(world.truth())
    result = referee.result()
    assert not result.finished and 0.05 < result.completion < 0.2
    assert result.progress_m == pytest.approx(world.progress_m)
    assert 0.0 < result.speed_ratio <= 1.0
    assert result.cross_track_rms_m < 0.5  # pure pursuit cuts corners a little
    assert result.collisions == world.collisions and result.corridor_exits == world.corridor_exits
    assert result.min_clearance_m > 0.0 or result.collisions > 0
    assert math.isfinite(result.min_clearance_m)
    assert result.as_dict()["samples"] == 4000


def _truth(east: float, north: float, yaw: float = 0.0) -> SimTruth:
    return SimTruth(east, north, yaw, 2.0, 0.0, 0.0, 0.0, 0)


def test_driving_onto_a_ditch_or_a_berm_is_an_entry() -> None:
    """The simulator drives through ditches and over berms; the referee counts each time the
    footprint comes onto one, and not while it passes beside it."""
    scenario = load_scenario(DEFAULT_SCENARIO)
    (wash,) = [h for h in scenario.world.hazards if h.name == "wash"]
    c, s = math.cos(wash.yaw_rad), math.sin(wash.yaw_rad)

    def drive_across(lateral_m: float) -> int:
        referee = Referee(scenario)
        for along in np.arange(-12.0, 12.0, 0.1):  # rear axle from 12 m before to 12 m past
            east = wash.east_m + c * along - s * lateral_m
            north = wash.north_m + s * along + c * lateral_m
            referee.on_truth(_truth(east, north, wash.yaw_rad))
        return referee.result().hazard_entries

    assert drive_across(0.0) == 1  # through the middle
    assert drive_across(wash.width_m / 2 - 0.2) == 1  # clipping its end with one side
    assert drive_across(wash.width_m / 2 + 1.2) == 0  # in the strip beside it
