"""Sweeping lidar, simulated.

The beams lie at horizontal bearings ``resolution_rad`` apart over ``half_fov_rad`` each side of
straight ahead. The scan plane meets flat ground in the line ``ground_m`` ahead of the sensor, so
beam i reaches flat ground at r_i = ground_m / cos(b_i) and falls z_m / r_i per metre of
horizontal travel. Each beam's first hit is the nearest of: an obstacle's footprint entered below
its top (``raycast.descending_ray_ranges``), the terrain hazards (the ground sampled along the
beam across their bounding circles, ``profile.first_hits``), and flat ground at r_i. Range noise
lies along the beam. The vehicle is level on the plane z = 0, as for the vertical lidars
(SimTruth has no attitude): on a real vehicle the pitch from the INS would be taken out.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from brain.pose import Pose
from modules.lidar.sweep import SWEEP_MOUNT, SweepMount, SweepReturns
from modules.sim.lidar.profile import GROUND_STEP_M, first_hits
from modules.sim.lidar.raycast import Scene, descending_ray_ranges
from modules.sim.terrain import ground_height
from modules.sim.world import TerrainHazard

MAX_SAMPLES = 2000  # ground samples per beam across the hazards' circles (0.05 m over 100 m)


class _Beams(NamedTuple):
    """A mount's beams, worked out once per mount."""

    bearings_rad: np.ndarray
    flat_m: np.ndarray
    slopes: np.ndarray
    cos_depression: np.ndarray
    sin_depression: np.ndarray


@functools.lru_cache(maxsize=16)
def _beams(mount: SweepMount) -> _Beams:
    bearings = mount.bearings_rad()
    flat = mount.flat_ranges_m(bearings)
    slopes = mount.z_m / flat
    depression = np.arctan(slopes)
    beams = _Beams(bearings, flat, slopes, np.cos(depression), np.sin(depression))
    for array in beams:
        array.flags.writeable = False
    return beams


class _Circles(NamedTuple):
    """The hazards' bounding circles as arrays (ENU centres, radii), made once per hazard set."""

    east_m: np.ndarray
    north_m: np.ndarray
    radius_m: np.ndarray
    depth_bound_m: float  # no ground lies lower than this below the plane: all magnitudes summed


@functools.lru_cache(maxsize=16)
def _circles(hazards: tuple[TerrainHazard, ...]) -> _Circles:
    return _Circles(
        np.array([hazard.east_m for hazard in hazards], dtype=float),
        np.array([hazard.north_m for hazard in hazards], dtype=float),
        np.array([math.hypot(hazard.length_m, hazard.width_m) / 2 for hazard in hazards], dtype=float),
        sum(abs(hazard.magnitude_m) for hazard in hazards),
    )


def sweep_scan(
    hazards: tuple[TerrainHazard, ...] | list[TerrainHazard],
    scene: Scene,
    pose: Pose,
    mount: SweepMount = SWEEP_MOUNT,
    rng: np.random.Generator | None = None,
    noise_scale: float = 1.0,
) -> SweepReturns:
    """Every beam's first hit from ``mount`` on a vehicle at ``pose``."""
    beams = _beams(mount)
    bearings, flat, slopes = beams.bearings_rad, beams.flat_m, beams.slopes
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    origin = np.array((pose.east_m + c * mount.x_m - s * mount.y_m, pose.north_m + s * mount.x_m + c * mount.y_m))
    angles = pose.yaw_rad + bearings
    distance, height = flat.copy(), np.zeros_like(flat)
    if hazards:
        terrain_distance, terrain_height = _terrain_hits(tuple(hazards), origin, angles, mount.z_m, slopes, flat)
        sampled = np.isfinite(terrain_distance)
        distance[sampled], height[sampled] = terrain_distance[sampled], terrain_height[sampled]
    # An obstacle beyond every beam's ground hit cannot be nearer than it: look no farther.
    reach = min(mount.max_range_m, float(distance.max()))
    obstacle = descending_ray_ranges(origin, angles, mount.z_m, slopes, scene, reach)
    nearer = obstacle < distance
    distance[nearer] = obstacle[nearer]
    height[nearer] = mount.z_m - slopes[nearer] * obstacle[nearer]
    if rng is not None and mount.range_noise_std_m * noise_scale > 0:
        noise = rng.normal(0.0, mount.range_noise_std_m * noise_scale, len(bearings))
        distance = distance + noise * beams.cos_depression
        height = height - noise * beams.sin_depression
    out_of_range = np.hypot(distance, mount.z_m - height) > mount.max_range_m
    distance[out_of_range], height[out_of_range] = np.nan, np.nan
    return SweepReturns(bearings, distance, height, slopes)


def _terrain_hits(
    hazards: tuple[TerrainHazard, ...],
    origin: np.ndarray,
    angles_rad: np.ndarray,
    height_m: float,
    slopes: np.ndarray,
    flat_m: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Hits on the terrain hazards for the beams that cross one's bounding circle before they
    would meet flat ground beyond it (inf elsewhere: those beams meet flat ground at ``flat_m``)."""
    count = len(angles_rad)
    distance, height = np.full(count, np.inf), np.full(count, np.nan)
    circles = _circles(hazards)
    dx, dy = np.cos(angles_rad), np.sin(angles_rad)
    ox, oy = circles.east_m - origin[0], circles.north_m - origin[1]
    along = dx * ox[:, None] + dy * oy[:, None]  # (hazards, beams)
    disc = along**2 - (ox * ox + oy * oy - circles.radius_m**2)[:, None]
    root = np.sqrt(np.maximum(disc, 0.0))
    near_edge = np.maximum(along - root, 0.0)
    # Past the depth bound a beam is below any ground, so it hit something before: a circle
    # that begins there (with a metre for the sample spacing) cannot matter.
    reach = (height_m + circles.depth_bound_m) / slopes + 1.0
    crosses = (disc > 0) & (along + root > 0) & (near_edge < reach)
    if not crosses.any():
        return distance, height
    enter = np.where(crosses, near_edge, np.inf).min(axis=0)
    leave = np.where(crosses, along + root, -np.inf).max(axis=0)
    # A beam that has met flat ground before a hazard's circle never reaches it.
    rows = np.flatnonzero((leave > enter) & (enter < flat_m))
    if not len(rows):
        return distance, height
    crossed = [hazard for hazard, any_beam in zip(hazards, crosses.any(axis=1), strict=True) if any_beam]
    span = leave[rows] - enter[rows]
    samples = int(min(MAX_SAMPLES, math.ceil(float(span.max()) / GROUND_STEP_M) + 1))
    along = enter[rows, None] + span[:, None] * np.linspace(0.0, 1.0, samples)
    ground = ground_height(crossed, origin[0] + dx[rows, None] * along, origin[1] + dy[rows, None] * along)
    hit_distance, hit_height = first_hits(along, ground, height_m, slopes[rows])
    # A beam still above the ground where the circle ends goes on to flat ground (or already
    # came down in it, if it was below the plane at the circle's edge: the first sample).
    distance[rows], height[rows] = hit_distance, hit_height
    return distance, height
