"""The vision pipeline split in two for CAMBADA mode: obstacle detection and lane detection, each
runnable on its own frame copy in its own process, with its own period and priority.

Both halves call the vision package's stage functions exactly as ``vision.pipeline.process``
does, so each returns what the whole pipeline would for the same pair. Lane detection keeps the
pipeline's stereo filter (points above the ground and obstacle points score no lane evidence),
so it matches the band too: it costs a second disparity computation, which buys the two
processes their independence (neither waits for nor trusts the other's results).
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

from modules.esvs.geometry import StereoRig
from modules.esvs.vision.band import Band, band_disparity, band_rows, vehicle_points
from modules.esvs.vision.clusters import describe
from modules.esvs.vision.lane_fit import fit_borders
from modules.esvs.vision.lane_heat import heat_map, off_ground, pixel_scores
from modules.esvs.vision.obstacle_points import obstacle_points
from modules.esvs.vision.pipeline import VisionParams, check_pair
from protocol.messages import Frame, LaneBorders, ObstacleList, Sensor


class Stereo(NamedTuple):
    """What both halves need: the band, its disparity, VEHICLE points and obstacle points."""

    band: Band
    band_left: np.ndarray
    disparity: np.ndarray
    xyz: tuple[np.ndarray, np.ndarray, np.ndarray]
    mask: np.ndarray


def stereo(
    left: np.ndarray, right: np.ndarray, rig: StereoRig, params: VisionParams, timings: dict[str, float]
) -> Stereo:
    """Stages disparity, reproject and obstacle_points (timed into ``timings``)."""
    check_pair(left, right, rig)
    band = band_rows(rig, params.band)
    clock = time.perf_counter
    start = clock()
    band_left = left[band.top : band.bottom]
    disparity = band_disparity(left, right, band, params.matcher)
    timings["disparity"], start = clock() - start, clock()
    x, y, z = vehicle_points(disparity, rig, band.top)
    timings["reproject"], start = clock() - start, clock()
    nearest_disparity = rig.focal_px * rig.baseline_m / params.max_range_m
    mask = obstacle_points(x, y, z, disparity, rig.baseline_m, params.points, nearest_disparity)
    timings["obstacle_points"] = clock() - start
    return Stereo(band, band_left, disparity, (x, y, z), mask)


def detect_obstacles(
    left: np.ndarray, right: np.ndarray, rig: StereoRig, params: VisionParams
) -> tuple[ObstacleList, dict[str, float]]:
    """Obstacle descriptors (VEHICLE frame) in one pair, and the stage timings."""
    timings: dict[str, float] = {}
    seen = stereo(left, right, rig, params, timings)
    start = time.perf_counter()
    max_disparity = params.matcher.min_disparity + params.matcher.num_disparities
    obstacles = describe(seen.mask, seen.disparity, seen.xyz, max_disparity, params.clusters)
    timings["obstacles"] = time.perf_counter() - start
    return ObstacleList(sensor=Sensor.ESVS, frame=Frame.VEHICLE, obstacles=obstacles), timings


def detect_lanes(
    left: np.ndarray, right: np.ndarray, rig: StereoRig, params: VisionParams
) -> tuple[LaneBorders, dict[str, float]]:
    """Lane borders (VEHICLE frame) in one pair, and the stage timings."""
    timings: dict[str, float] = {}
    seen = stereo(left, right, rig, params, timings)
    clock = time.perf_counter
    start = clock()
    z = seen.xyz[2]
    scores = pixel_scores(seen.band_left, rig, seen.band.top, params.heat, off_ground(z, seen.mask, params.heat))
    heat = heat_map(scores, rig, seen.band.top, params.heat)
    timings["lane_heat"], start = clock() - start, clock()
    borders = fit_borders(heat, params.fit)
    timings["lane_fit"] = clock() - start
    return LaneBorders(sensor=Sensor.ESVS, borders=borders), timings
