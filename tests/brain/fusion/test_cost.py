"""The cost layer: C(p) from clear to unknown to suspect, lethal hazards, inflation falling off
with distance, lane borders as cost but never as walls."""

from __future__ import annotations

import math

import numpy as np
import pytest

from brain.fusion import CostConfig, build_cost_map
from brain.grid import GridWindow
from protocol.messages import LaneBorder, LaneBorders, Sensor
from tests.brain.fusion.helpers import enu_of, parked

WINDOW = GridWindow(0.0, 0.0, 0.2, rows=150, cols=600)  # the planner benchmark's 120 x 30 m


def logit(p: float) -> float:
    return math.log(p / (1 - p))


def test_cost_rises_from_clear_through_unknown_to_lethal() -> None:
    config = CostConfig()
    probabilities = [0.05, config.clear_probability, 0.5, 0.65, 0.79, 0.8, 0.95]
    log_odds = np.zeros(WINDOW.shape, dtype=np.float32)
    columns = [20 + 80 * i for i in range(len(probabilities))]  # far apart: no inflation between them
    for col, p in zip(columns, probabilities, strict=True):
        log_odds[75, col] = logit(p)
    cost_map = build_cost_map(WINDOW, log_odds, None, config, t_ns=7)
    costs = [float(cost_map.cost[75, col]) for col in columns]
    assert costs[0] == pytest.approx(config.clear_cost) and costs[1] == pytest.approx(config.clear_cost, abs=0.02)
    assert costs[2] == pytest.approx(config.unknown_cost, abs=0.02)
    assert costs[2] < costs[3] < costs[4] < config.suspect_cost + 0.05
    assert costs[5] == costs[6] == math.inf
    assert cost_map.lethal.sum() == 2 and cost_map.t_ns == 7
    np.testing.assert_allclose(cost_map.hazard_probability[75, columns], probabilities, atol=1e-6)
    assert cost_map.cost.dtype == np.float32 and cost_map.hazard_probability.dtype == np.float32


def test_cost_falls_off_with_distance_from_a_hazard() -> None:
    config = CostConfig(inflation_radius_m=3.0, inflation_cost=5.0)
    log_odds = np.full(WINDOW.shape, logit(0.1), dtype=np.float32)  # seen clear: cost 0
    log_odds[75, 300] = 5.0
    cost_map = build_cost_map(WINDOW, log_odds, None, config, t_ns=0)
    assert cost_map.lethal[75, 300] and cost_map.lethal.sum() == 1
    profile = cost_map.cost[75, 301:330]  # moving east, 0.2 m a cell
    assert np.all(np.diff(profile) <= 0)
    expected = np.maximum(0.0, 5.0 * (1 - 0.2 * np.arange(1, 30) / 3.0))
    np.testing.assert_allclose(profile, expected, atol=0.05)
    assert np.all(cost_map.cost[75, 316:] == 0.0) and np.all(cost_map.cost[:, :280] == 0.0)
    # The same along a diagonal: distance is Euclidean.
    diagonal = cost_map.cost[75 + np.arange(1, 10), 300 + np.arange(1, 10)]
    np.testing.assert_allclose(diagonal, 5.0 * (1 - 0.2 * math.sqrt(2) * np.arange(1, 10) / 3.0), atol=0.1)


def test_lethal_radius_makes_the_neighbourhood_lethal() -> None:
    config = CostConfig(lethal_radius_m=0.6, inflation_radius_m=2.0)
    log_odds = np.zeros(WINDOW.shape, dtype=np.float32)
    log_odds[50, 100] = 5.0
    cost_map = build_cost_map(WINDOW, log_odds, None, config, t_ns=0)
    rows, cols = np.nonzero(cost_map.lethal)
    assert np.hypot(rows - 50, cols - 100).max() == pytest.approx(3.0)  # 0.6 m = 3 cells
    assert np.all(np.isinf(cost_map.cost[cost_map.lethal]))
    assert cost_map.cost[50, 104] == pytest.approx(1.0 + 5.0 * (1 - (0.8 - 0.6) / 1.4), abs=0.05)


def test_lane_borders_add_cost_outside_the_lane_but_never_lethal() -> None:
    fusion = parked(100.0, 50.0, 0.3)
    left = LaneBorder(side=1, c0_m=2.0, c1=0.0, c2_per_m=0.0, x_min_m=2.0, x_max_m=30.0, confidence=0.9)
    right = LaneBorder(side=-1, c0_m=-2.0, c1=0.0, c2_per_m=0.0, x_min_m=2.0, x_max_m=30.0, confidence=0.9)
    assert fusion.add_lane_borders(0, LaneBorders(Sensor.ESVS, (left, right)))
    cost_map = fusion.cost_map()
    config = fusion.cost_config

    def cost_at(x: float, y: float) -> float:
        row, col = cost_map.window.cell_of(*enu_of(100.0, 50.0, 0.3, x, y))
        return float(cost_map.cost[row, col])

    unknown = config.unknown_cost
    for y in (3.0, 4.5, -3.0, -4.5):  # outside, within the band
        assert cost_at(15.0, y) == pytest.approx(unknown + 0.9 * config.lane_cost, abs=0.05)
    for y in (0.0, 1.0, -1.0):
        assert cost_at(15.0, y) == pytest.approx(unknown, abs=0.05)
    assert cost_at(15.0, 8.0) == pytest.approx(unknown, abs=0.05)  # beyond the band: nothing known
    assert not cost_map.lethal.any()


def test_bad_lane_borders_are_skipped_and_counted() -> None:
    fusion = parked()
    sideways = LaneBorder(side=0, c0_m=2.0, c1=0.0, c2_per_m=0.0, x_min_m=2.0, x_max_m=30.0, confidence=0.9)
    backwards = LaneBorder(side=1, c0_m=2.0, c1=0.0, c2_per_m=0.0, x_min_m=30.0, x_max_m=2.0, confidence=0.9)
    assert fusion.add_lane_borders(0, LaneBorders(Sensor.ESVS, (sideways, backwards)))
    assert fusion.stats.bad_descriptor == 2
    assert not fusion.cost_map().cost.max() > fusion.cost_config.unknown_cost


def test_config_and_shapes_are_checked() -> None:
    with pytest.raises(ValueError):
        CostConfig(hazard_threshold=0.4)
    with pytest.raises(ValueError):
        CostConfig(lethal_radius_m=2.0, inflation_radius_m=1.0)
    with pytest.raises(ValueError):
        build_cost_map(WINDOW, np.zeros((10, 10), dtype=np.float32), None, CostConfig(), 0)
