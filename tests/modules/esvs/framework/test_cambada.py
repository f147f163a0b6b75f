"""CAMBADA mode's two halves of the pipeline give exactly what the whole pipeline gives."""

from __future__ import annotations

from modules.esvs.cambada import detect_lanes, detect_obstacles
from modules.esvs.geometry import RASCAL_RIG
from modules.esvs.settings import EsvsConfig, vision_params
from modules.esvs.vision import process
from tests.modules.esvs.framework.workers import SCENE, scene_pair


def test_obstacle_and_lane_halves_match_the_whole_pipeline() -> None:
    left, right = scene_pair()
    params = vision_params(EsvsConfig())
    obstacles, lanes, _stats = process(left, right, RASCAL_RIG, params)
    alone_obstacles, obstacle_timings = detect_obstacles(left, right, RASCAL_RIG, params)
    alone_lanes, lane_timings = detect_lanes(left, right, RASCAL_RIG, params)
    assert len(obstacles.obstacles) == len(SCENE.boxes) and len(lanes.borders) == len(SCENE.stripes)
    assert alone_obstacles == obstacles
    assert alone_lanes == lanes
    assert set(obstacle_timings) == {"disparity", "reproject", "obstacle_points", "obstacles"}
    assert set(lane_timings) == {"disparity", "reproject", "obstacle_points", "lane_heat", "lane_fit"}


def test_parameters_reach_the_halves() -> None:
    left, right = scene_pair()
    strict = vision_params(EsvsConfig(min_obstacle_points=100_000, lane_hot=0.95))
    _obstacles, lanes, _stats = process(left, right, RASCAL_RIG, strict)
    assert detect_obstacles(left, right, RASCAL_RIG, strict)[0].obstacles == ()
    assert detect_lanes(left, right, RASCAL_RIG, strict)[0] == lanes
