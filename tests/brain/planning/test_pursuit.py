"""The track the vehicle makes along a polyline: pure pursuit on a kinematic bicycle."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from brain.planning.config import PlannerConfig
from brain.planning.pursuit import pursue

CONFIG = PlannerConfig()
BICYCLE = CONFIG.bicycle
RADIUS_M = CONFIG.turning_radius_m  # 2.29 m


def turn_per_metre(track: np.ndarray) -> np.ndarray:
    """Heading change between consecutive steps, per metre of arc."""
    step = np.diff(track, axis=0)
    heading = np.unwrap(np.arctan2(step[:, 1], step[:, 0]))
    return np.abs(np.diff(heading)) / np.hypot(step[1:, 0], step[1:, 1])


def test_a_straight_path_ahead_is_driven_along_it_to_its_end() -> None:
    track = pursue(np.array([[0.0, 0.0], [30.0, 0.0]]), 0.0, 0.0, 0.0, BICYCLE)
    assert track is not None
    assert np.abs(track[:, 1]).max() < 1e-9
    assert track[-1, 0] == pytest.approx(30.0, abs=BICYCLE.step_m)


def test_a_bend_wider_than_the_turning_circle_is_followed_closely() -> None:
    angle = np.linspace(0.0, math.pi / 2, 40)
    arc = np.column_stack([6.0 * np.sin(angle), 6.0 * (1.0 - np.cos(angle))])
    path = np.vstack([[[-10.0, 0.0]], arc, arc[-1] + [[0.0, 10.0]]])
    track = pursue(path, -10.0, 0.0, 0.0, BICYCLE)
    assert track is not None
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])
    fine = np.arange(0.0, along[-1], 0.05)
    dense = np.column_stack([np.interp(fine, along, path[:, 0]), np.interp(fine, along, path[:, 1])])
    gap = np.hypot(track[:, None, 0] - dense[None, :, 0], track[:, None, 1] - dense[None, :, 1]).min(axis=1)
    assert gap.max() < 0.35  # pure pursuit cuts the bend a little, within the planner's margins
    assert track[-1] == pytest.approx(path[-1], abs=0.3)


def test_the_track_never_turns_tighter_than_the_vehicle_can() -> None:
    """A right-angle corner in the polyline: the track rounds it at no less than the radius."""
    path = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    track = pursue(path, 0.0, 0.0, 0.0, BICYCLE)
    assert track is not None
    assert turn_per_metre(track).max() <= 1.0 / RADIUS_M + 1e-9
    assert track[-1] == pytest.approx([10.0, 10.0], abs=0.5)


def test_a_path_stepping_sideways_in_front_of_the_vehicle_cannot_be_driven() -> None:
    """What the search gave in front of the wash: 8 m across within 1.3 m of the vehicle."""
    path = np.array([[0.0, 0.0], [1.3, 8.0], [20.0, 8.0]])
    assert pursue(path, 0.0, 0.0, 0.0, BICYCLE) is None


def test_an_end_point_beside_the_vehicle_is_not_orbited_for_ever() -> None:
    path = np.array([[0.0, 0.0], [0.3, 1.0]])
    track = pursue(path, 0.0, 0.0, 0.0, BICYCLE)
    assert track is None or len(track) < 200


def test_the_wheels_turn_at_the_actuator_rate() -> None:
    """From straight wheels, full lock takes max angle / rate seconds of slow-speed travel."""
    path = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 20.0]])
    track = pursue(path, 0.0, 0.0, 0.0, BICYCLE)
    assert track is not None
    first_step_turn = turn_per_metre(track[:3])[0]
    limit = math.tan(BICYCLE.max_steering_rate_radps * BICYCLE.step_m / BICYCLE.speed_mps) / BICYCLE.wheelbase_m
    assert first_step_turn <= limit + 1e-9


@pytest.mark.parametrize(
    "changes",
    [{"wheelbase_m": 0.0}, {"max_steering_rad": 1.6}, {"step_m": -0.1}, {"lookahead_m": math.nan}],
)
def test_a_bicycle_with_bad_numbers_is_refused(changes: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="Bicycle"):
        dataclasses.replace(BICYCLE, **changes)
