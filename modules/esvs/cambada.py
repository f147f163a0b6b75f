"""The vision pipeline split in two for CAMBADA mode: obstacle detection and lane detection, each
runnable on its own frame copy in its own process, with its own period and priority.

Both halves are the vision pipeline's own stages (``vision.pipeline``: ``stereo``, then
``describe_obstacles`` or ``find_lane_borders``), so each returns what the whole pipeline would
for the same pair. Lane detection keeps the pipeline's stereo filter (points above the ground
and obstacle points score no lane evidence), so it matches the band too: it costs a second
disparity computation, which buys the two processes their independence (neither waits for nor
trusts the other's results).
"""

from __future__ import annotations

import numpy as np

from modules.esvs.geometry import StereoRig
from modules.esvs.vision.pipeline import VisionParams, describe_obstacles, find_lane_borders, stereo
from protocol.messages import LaneBorders, ObstacleList


def detect_obstacles(
    left: np.ndarray, right: np.ndarray, rig: StereoRig, params: VisionParams
) -> tuple[ObstacleList, dict[str, float]]:
    """Obstacle descriptors (VEHICLE frame) in one pair, and the stage timings."""
    timings: dict[str, float] = {}
    obstacles = describe_obstacles(stereo(left, right, rig, params, timings), params, timings)
    return obstacles, timings


def detect_lanes(
    left: np.ndarray, right: np.ndarray, rig: StereoRig, params: VisionParams
) -> tuple[LaneBorders, dict[str, float]]:
    """Lane borders (VEHICLE frame) in one pair, and the stage timings."""
    timings: dict[str, float] = {}
    borders, _heat = find_lane_borders(stereo(left, right, rig, params, timings), rig, params, timings)
    return borders, timings
