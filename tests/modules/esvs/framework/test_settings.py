"""ESVS settings: checked at start and on every ConfigUpdate; only live keys change at run time."""

from __future__ import annotations

import pytest

from modules.esvs.settings import LIVE_KEYS, EsvsConfig, check_config, updated, vision_params
from modules.esvs.vision import VisionParams
from rascal.runtime.config import ConfigError


def test_the_defaults_are_valid_and_match_rascal() -> None:
    config = EsvsConfig()
    check_config(config)
    assert config.round_period_s == 0.1 and config.mode == "monolithic"
    assert config.obstacle_priority > config.lane_priority
    assert config.round_priority > max(config.obstacle_priority, config.vision_priority)


@pytest.mark.parametrize(
    ("changes", "complaint"),
    [
        ({"mode": "fast"}, "mode"),
        ({"round_period_s": 0.02}, "round_period_s"),
        ({"round_period_s": 2.0}, "round_period_s"),
        ({"hang_rounds": 0.5}, "hang_rounds"),
        ({"sched": "rr"}, "policy"),
        ({"lane_priority": 0}, "lane_priority"),
        ({"lane_every_rounds": 0}, "lanes period"),
        ({"lane_offset_s": 0.25}, "lanes offset"),
        ({"max_range_m": 5.0}, "max_range_m"),
        ({"min_obstacle_points": 0}, "min_obstacle_points"),
        ({"lane_hot": 1.0}, "lane_hot"),
    ],
)
def test_bad_settings_are_named(changes: dict, complaint: str) -> None:
    with pytest.raises(ValueError, match=complaint):
        check_config(EsvsConfig(**changes))


def test_live_updates_are_parsed_and_checked() -> None:
    config = EsvsConfig()
    faster = updated(config, "round_period_s", "0.033")
    assert faster.round_period_s == 0.033 and config.round_period_s == 0.1
    assert updated(config, "min_obstacle_points", "40").min_obstacle_points == 40
    with pytest.raises(ValueError, match="round_period_s"):
        updated(config, "round_period_s", "0.01")
    with pytest.raises(ConfigError, match="cannot read"):
        updated(config, "lane_hot", "hot")
    with pytest.raises(ConfigError, match="restart"):
        updated(config, "mode", "cambada")
    with pytest.raises(ConfigError, match="unknown key"):
        updated(config, "gain", "2")
    # A shorter round must still leave the lane worker's offset inside its period.
    with pytest.raises(ValueError, match="lanes offset"):
        updated(EsvsConfig(lane_offset_s=0.15), "round_period_s", "0.05")
    assert set(EsvsConfig.__dataclass_fields__) >= LIVE_KEYS


def test_vision_parameters_follow_the_settings() -> None:
    params = vision_params(EsvsConfig(max_range_m=30.0, min_obstacle_points=10, lane_hot=0.5))
    assert (params.max_range_m, params.clusters.min_points, params.fit.hot) == (30.0, 10, 0.5)
    assert vision_params(EsvsConfig()) == VisionParams()  # the defaults are the vision package's
