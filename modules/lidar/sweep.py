"""Sweeping lidar: a scanner pitched down so that its plane meets the ground in a line across the
road ahead, the way Stanley's roof lidars saw a ditch long before the vehicle reached it.

The vertical lidars see the ground along two lines 1 m apart, out to 25 m; a wash across the road
shows up in them, but not where it ends. A scan line across the road does: a beam that falls into
a ditch comes back from its far wall, below the plane the vehicle stands on, and the beams on
either side of the ditch come back from level ground. With beams 0.5 deg apart a ditch's end is
placed within 0.15 m at 35 m, where stereo is uncertain by metres.

Geometry. The beams lie at horizontal bearings ``resolution_rad`` apart over ``half_fov_rad``
each side of straight ahead. The scan plane meets flat ground in the line ``ground_m`` ahead of
the sensor, so beam i reaches flat ground at r_i = ground_m / cos(b_i) and falls z_m / r_i per
metre of horizontal travel. Each beam's first hit is the nearest of: an obstacle's footprint
entered below its top (``raycast.descending_ray_ranges``), the terrain hazards (the ground sampled
along the beam across their bounding circles, ``profile.first_hits``), and flat ground at r_i.
Range noise lies along the beam. The vehicle is level on the plane z = 0, as for the vertical
lidars (SimTruth has no attitude): on a real vehicle the pitch from the INS would be taken out.

Description. Each return is level (within ``step_m`` of the plane), low or high. Consecutive
returns of a kind make a stretch (low and high ones at most ``max_piece_m`` across), sent as a
box in the vehicle frame:

- level: the box around its returns;
- low: from where the beams met the plane to where they came back: they passed above the ground
  all that way, so the ground there is lower than the plane (by step_m from 0.7 m on; the drop
  that took it lower begins at the plane or nearer, the way a ditch's near wall does);
- high: around its returns (what lies behind is hidden), cut into pieces at most ``max_depth_m``
  deep: a box around a face seen at a slant reaches past its ends by up to its depth, and a
  rock's side of a passage 2.7 m wide came out 0.3-0.6 m wider with one box per face.

Low and high stretches reach half a beam spacing beyond their outermost returns, at those
returns' own distance; level ones stop at their outermost return: hazards grow, level ground
shrinks, as everywhere in the map.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from brain.pose import Pose
from modules.lidar.profile import GROUND_STEP_M, first_hits, ground_height
from modules.lidar.raycast import Scene, descending_ray_ranges
from modules.sim.world import TerrainHazard
from protocol.messages import GroundStretch, GroundSweep

LEVEL, LOW, HIGH = 0, -1, 1
MAX_SAMPLES = 2000  # ground samples per beam across the hazards' circles (0.05 m over 100 m)


@dataclass(frozen=True)
class SweepMount:
    """A sweeping lidar: its position in the vehicle frame (x forward, from the rear axle; it
    looks along +x), and where its plane meets flat ground."""

    x_m: float = 1.8
    y_m: float = 0.0
    z_m: float = 2.0  # on the roof rack
    ground_m: float = 35.0  # flat-ground distance ahead of the sensor of the scan line
    half_fov_rad: float = math.radians(30.0)  # +-20 m of ground line at 35 m
    resolution_rad: float = math.radians(0.5)
    max_range_m: float = 80.0
    range_noise_std_m: float = 0.01

    def bearings_rad(self) -> np.ndarray:
        """Beam bearings in the vehicle frame, right to left."""
        count = round(2 * self.half_fov_rad / self.resolution_rad) + 1
        return np.linspace(-self.half_fov_rad, self.half_fov_rad, count)

    def flat_ranges_m(self, bearings_rad: np.ndarray) -> np.ndarray:
        """Horizontal distance at which each beam meets flat ground."""
        return self.ground_m / np.cos(bearings_rad)


SWEEP_MOUNT = SweepMount()


class SweepReturns(NamedTuple):
    """One sweep's returns in the vehicle frame; nan where a beam came back from nothing in range."""

    bearings_rad: np.ndarray
    distance_m: np.ndarray  # horizontal, from the sensor along the beam
    height_m: np.ndarray  # of the point hit, relative to the plane the vehicle stands on
    slopes: np.ndarray  # each beam's fall per metre of horizontal travel


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


def describe_sweep(
    returns: SweepReturns,
    mount: SweepMount,
    sensor: int,
    step_m: float = 0.04,
    max_piece_m: float = 2.0,
    max_depth_m: float = 0.25,
) -> GroundSweep:
    """The returns as level, low and high stretches (module docstring), right to left."""
    b, t, z = returns.bearings_rad, returns.distance_m, returns.height_m
    x = mount.x_m + t * np.cos(b)
    y = mount.y_m + t * np.sin(b)
    # Half a beam spacing to each side, at the return's own distance: how far a hazard between
    # this beam and the next may reach unseen.
    half = mount.resolution_rad / 2
    reach = (mount.y_m + t * np.sin(b - half), mount.y_m + t * np.sin(b + half))
    kind = np.where(z < -step_m, LOW, np.where(z > step_m, HIGH, LEVEL))
    # Where a low beam met the plane: the ground beyond lay below it, so the drop began nearer.
    met = mount.x_m + mount.z_m / returns.slopes * np.cos(b)
    runs = _runs(np.isfinite(t), kind, x.tolist(), y.tolist(), max_piece_m, max_depth_m)
    return GroundSweep(sensor, tuple(_stretch(run, int(kind[run.start]), x, y, z, met, reach) for run in runs))


def _runs(
    valid: np.ndarray, kind: np.ndarray, x: list[float], y: list[float], max_piece_m: float, max_depth_m: float
) -> list[slice]:
    """Consecutive valid beams of one kind, right to left; low and high runs cut into pieces
    at most ``max_piece_m`` across, high ones also at most ``max_depth_m`` deep (each piece
    starts a new one where it would grow wider or deeper)."""
    edges = np.flatnonzero((np.diff(valid) != 0) | (np.diff(kind) != 0)) + 1
    bounds = [0, *edges.tolist(), len(valid)]
    runs = []
    for start, stop in itertools.pairwise(bounds):
        if not valid[start]:
            continue
        if kind[start] == LEVEL:
            runs.append(slice(start, stop))
            continue
        depth = max_depth_m if kind[start] == HIGH else math.inf
        piece, near, far = start, x[start], x[start]
        for beam in range(start + 1, stop):
            near, far = min(near, x[beam]), max(far, x[beam])
            if y[beam] - y[piece] > max_piece_m or far - near > depth:
                runs.append(slice(piece, beam))
                piece, near, far = beam, x[beam], x[beam]
        runs.append(slice(piece, stop))
    return runs


def _stretch(
    run: slice,
    kind: int,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    met: np.ndarray,
    reach: tuple[np.ndarray, np.ndarray],
) -> GroundStretch:
    """The box of the returns ``run`` (consecutive beams of one kind)."""
    if kind == LEVEL:
        return GroundStretch(float(x[run].min()), float(x[run].max()), float(y[run].min()), float(y[run].max()), 0.0)
    right, left = float(reach[0][run].min()), float(reach[1][run].max())
    if kind == LOW:
        return GroundStretch(float(met[run].min()), float(x[run].max()), right, left, float(z[run].min()))
    return GroundStretch(float(x[run].min()), float(x[run].max()), right, left, float(z[run].max()))
