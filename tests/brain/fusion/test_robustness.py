"""Whatever a peer sends, fusion answers True or False and the map stays finite and bounded."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from brain.fusion import FusionConfig, HazardFusion
from protocol.messages import (
    Frame,
    LaneBorder,
    LaneBorders,
    Obstacle,
    ObstacleList,
    Sensor,
    SurfaceProfile,
    VehicleState,
)
from tests.brain.fusion.helpers import state

ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True) | st.floats(-200.0, 200.0)
SENSORS = st.sampled_from(list(Sensor)) | st.integers(-5, 50)
TIMES = st.integers(-200_000_000, 200_000_000)
SMALL = FusionConfig(window_east_m=40.0, window_north_m=40.0, lead_m=10.0)  # the same code, less to allocate

obstacle = st.builds(Obstacle, *(ANY_FLOAT for _ in range(8)))
obstacle_lists = st.builds(
    ObstacleList, SENSORS, st.sampled_from([Frame.VEHICLE, Frame.ENU, 9]), st.lists(obstacle, max_size=6).map(tuple)
)
profiles = st.builds(
    SurfaceProfile,
    SENSORS,
    ANY_FLOAT,
    st.lists(ANY_FLOAT, max_size=12).map(tuple),
    st.lists(ANY_FLOAT, max_size=12).map(tuple),
)
borders = st.builds(
    LaneBorders,
    SENSORS,
    st.lists(st.builds(LaneBorder, st.integers(-2, 2), *(ANY_FLOAT for _ in range(6))), max_size=3).map(tuple),
)


def check_map(fusion: HazardFusion) -> None:
    layers = fusion.layers
    assert layers is not None
    assert np.isfinite(layers.evidence).all() and np.isfinite(layers.lane).all()
    assert layers.evidence.min() >= fusion.config.evidence_min and layers.evidence.max() <= fusion.config.evidence_max
    cost_map = fusion.cost_map()
    assert not np.isnan(cost_map.cost).any() and cost_map.cost.min() >= 0.0
    assert 0.0 <= cost_map.hazard_probability.min() <= cost_map.hazard_probability.max() <= 1.0


@settings(max_examples=150, deadline=None, derandomize=True)
@given(st.lists(st.tuples(TIMES, obstacle_lists | profiles | borders), min_size=1, max_size=6))
def test_no_message_crashes_fusion_or_corrupts_the_map(messages: list) -> None:
    fusion = HazardFusion(SMALL)
    fusion.add_pose(0, state(10.0, -20.0, 0.7))
    for t, message in messages:
        if isinstance(message, ObstacleList):
            accepted = fusion.add_obstacles(t, message)
        elif isinstance(message, SurfaceProfile):
            accepted = fusion.add_profile(t, message)
        else:
            accepted = fusion.add_lane_borders(t, message)
        assert accepted in (True, False)
    check_map(fusion)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.lists(st.tuples(TIMES, ANY_FLOAT, ANY_FLOAT, ANY_FLOAT), min_size=1, max_size=5))
def test_no_navigation_state_crashes_fusion(states: list) -> None:
    fusion = HazardFusion(SMALL)
    fusion.add_pose(0, state(0.0, 0.0, 0.0))
    for t, east, north, yaw in states:
        accepted = fusion.add_pose(t, VehicleState(east, north, 0.0, yaw, 0.0, 0.0, 0.0, 0.0, (0.0,) * 25, 3))
        if not all(math.isfinite(v) for v in (east, north, yaw)):
            assert not accepted
    check_map(fusion)
