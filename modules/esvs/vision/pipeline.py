"""One stereo frame in, obstacle and lane-border descriptors out: ``process(left, right, rig)``.

Stages (each timed in ``Stats.timings_s``):

1. ``disparity``: block matching on the rows of the 10-35 m band only;
2. ``reproject``: every matched pixel to VEHICLE x, y, z (the rig's Q matrix, then
   camera_to_vehicle);
3. ``obstacle_points``: Kratos' Algorithm 1 (pairs of points nearly one above the other);
4. ``obstacles``: points grouped into Obstacle descriptors;
5. ``lane_heat``: lane filters on the left image, warped into a bird's-eye heat map;
6. ``lane_fit``: RANSAC parabolas and greedy extension into LaneBorder descriptors.

Pure: no bus, no clock other than the stage timer, no state between calls except caches of
per-rig lookup tables and one matcher object per thread.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from modules.esvs.geometry import RASCAL_RIG, StereoRig
from modules.esvs.vision.band import Band, BandParams, band_disparity, band_rows, vehicle_points
from modules.esvs.vision.clusters import ClusterParams, describe
from modules.esvs.vision.disparity import REALTIME, MatcherParams
from modules.esvs.vision.lane_fit import FitParams, fit_borders
from modules.esvs.vision.lane_heat import HeatMap, HeatParams, heat_map, off_ground, pixel_scores
from modules.esvs.vision.obstacle_points import ObstaclePointParams, obstacle_points
from protocol.messages import Frame, LaneBorders, ObstacleList, Sensor

STAGES = ("disparity", "reproject", "obstacle_points", "obstacles", "lane_heat", "lane_fit")


@dataclass(frozen=True)
class VisionParams:
    band: BandParams = field(default_factory=BandParams)
    matcher: MatcherParams = REALTIME
    points: ObstaclePointParams = field(default_factory=ObstaclePointParams)
    max_range_m: float = 40.0  # obstacle points are sought up to this far ahead of the cameras
    clusters: ClusterParams = field(default_factory=ClusterParams)
    heat: HeatParams = field(default_factory=HeatParams)
    fit: FitParams = field(default_factory=FitParams)


@dataclass(frozen=True)
class Stats:
    timings_s: dict[str, float]  # per stage, in STAGES order
    band: Band
    matched: float  # share of band pixels with a disparity
    obstacle_points: int
    lane_cells: int  # hot cells in the heat map

    @property
    def total_s(self) -> float:
        return sum(self.timings_s.values())


def check_pair(left: np.ndarray, right: np.ndarray, rig: StereoRig) -> None:
    """Raise ValueError unless both images are grey uint8 of the rig's size."""
    expected = (rig.height_px, rig.width_px)
    for name, image in (("left", left), ("right", right)):
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.shape != expected:
            shape = getattr(image, "shape", None)
            dtype = getattr(image, "dtype", type(image).__name__)
            raise ValueError(f"{name} image must be grey uint8 {expected}, got {shape} {dtype}")


class Stereo(NamedTuple):
    """What both kinds of detection start from: the band, its rows of the left image, its
    disparity, the matched pixels' VEHICLE points, and which of them are obstacle points."""

    band: Band
    band_left: np.ndarray
    disparity: np.ndarray
    xyz: tuple[np.ndarray, np.ndarray, np.ndarray]
    mask: np.ndarray


def stereo(
    left: np.ndarray, right: np.ndarray, rig: StereoRig, params: VisionParams, timings: dict[str, float]
) -> Stereo:
    """Stages ``disparity``, ``reproject`` and ``obstacle_points`` (timed into ``timings``)."""
    check_pair(left, right, rig)
    left, right = np.ascontiguousarray(left), np.ascontiguousarray(right)  # no copy when they are
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


def describe_obstacles(seen: Stereo, params: VisionParams, timings: dict[str, float]) -> ObstacleList:
    """Stage ``obstacles``: the obstacle points grouped into descriptors (VEHICLE frame)."""
    start = time.perf_counter()
    max_disparity = params.matcher.min_disparity + params.matcher.num_disparities
    obstacles = describe(seen.mask, seen.disparity, seen.xyz, max_disparity, params.clusters)
    timings["obstacles"] = time.perf_counter() - start
    return ObstacleList(sensor=Sensor.ESVS, frame=Frame.VEHICLE, obstacles=obstacles)


def find_lane_borders(
    seen: Stereo, rig: StereoRig, params: VisionParams, timings: dict[str, float]
) -> tuple[LaneBorders, HeatMap]:
    """Stages ``lane_heat`` and ``lane_fit``: lane borders (VEHICLE frame) and the heat map they
    were fitted to. Points above the ground and obstacle points score no lane evidence."""
    clock = time.perf_counter
    start = clock()
    scores = pixel_scores(
        seen.band_left, rig, seen.band.top, params.heat, off_ground(seen.xyz[2], seen.mask, params.heat)
    )
    heat = heat_map(scores, rig, seen.band.top, params.heat)
    timings["lane_heat"], start = clock() - start, clock()
    borders = fit_borders(heat, params.fit)
    timings["lane_fit"] = clock() - start
    return LaneBorders(sensor=Sensor.ESVS, borders=borders), heat


def process(
    left: np.ndarray, right: np.ndarray, rig: StereoRig = RASCAL_RIG, params: VisionParams | None = None
) -> tuple[ObstacleList, LaneBorders, Stats]:
    """Obstacles and lane borders (VEHICLE frame) seen in one rectified grey stereo pair."""
    params = params or VisionParams()
    timings: dict[str, float] = {}
    seen = stereo(left, right, rig, params, timings)
    obstacles = describe_obstacles(seen, params, timings)
    borders, heat = find_lane_borders(seen, rig, params, timings)
    stats = Stats(
        timings_s=timings,
        band=seen.band,
        matched=float(np.isfinite(seen.disparity).mean()),
        obstacle_points=int(seen.mask.sum()),
        lane_cells=int((heat.heat >= params.fit.hot).sum()),
    )
    return obstacles, borders, stats
