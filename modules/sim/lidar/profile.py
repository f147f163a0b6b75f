"""Vertical lidar, simulated: every beam's first hit on the terrain (modules/sim/terrain.py)."""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from brain.pose import Pose
from modules.lidar.profile import VerticalMount
from modules.sim.terrain import ground_height
from modules.sim.world import TerrainHazard
from protocol.messages import SurfaceProfile

GROUND_STEP_M = 0.05  # terrain sampling along the scan line; walls between samples are linear


def profile_scan(
    hazards: tuple[TerrainHazard, ...] | list[TerrainHazard],
    pose: Pose,
    mount: VerticalMount,
    sensor: int,
    rng: np.random.Generator | None = None,
    noise_scale: float = 1.0,
) -> SurfaceProfile:
    """One vertical sweep from ``mount`` on a vehicle at ``pose``: every beam's first ground hit,
    as forward distance and height in the vehicle frame. Beams that hit nothing within range are
    left out. Range noise (Gaussian, ``range_noise_std_m * noise_scale``, along the beam) is
    added when ``rng`` is given."""
    beams = _beams(mount)
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    base_e = pose.east_m + c * mount.x_m - s * mount.y_m
    base_n = pose.north_m + s * mount.x_m + c * mount.y_m
    near = _near_line(hazards, base_e, base_n, pose.yaw_rad, beams.reach_m)
    distance, height = _ground_hits(near, beams, (base_e, base_n, c, s), mount.z_m)
    hit = np.isfinite(distance) & (np.hypot(distance, mount.z_m - height) <= mount.max_range_m)
    distance, height, depressions = distance[hit], height[hit], beams.depressions_rad[hit]
    if rng is not None and mount.range_noise_std_m * noise_scale > 0:
        noise = rng.normal(0.0, mount.range_noise_std_m * noise_scale, distance.size)
        distance = distance + noise * np.cos(depressions)
        height = height - noise * np.sin(depressions)
    return SurfaceProfile(sensor, float(mount.y_m), tuple((mount.x_m + distance).tolist()), tuple(height.tolist()))


class _Beams(NamedTuple):
    """What a vertical mount's scan is on flat ground, worked out once per mount."""

    depressions_rad: np.ndarray
    slopes: np.ndarray  # fall per metre of each beam
    along_m: np.ndarray  # ground samples ahead of the sensor, GROUND_STEP_M apart
    reach_m: float
    flat_m: np.ndarray  # where each beam meets flat ground (inf: not within the samples)
    flat_index: np.ndarray  # the first sample at or past it


@functools.lru_cache(maxsize=16)
def _beams(mount: VerticalMount) -> _Beams:
    """The mount's beams and their hits on flat ground, found as on any terrain (first_hits on
    the samples around each crossing), so flat stretches give the same numbers either way."""
    depressions = mount.depressions_rad()
    slopes = np.tan(depressions)
    reach = mount.max_range_m * math.cos(depressions[-1])
    along = np.arange(0.0, reach + GROUND_STEP_M, GROUND_STEP_M)
    # Around the analytic crossing, two samples of margin each side for rounding.
    first = np.clip(np.ceil(mount.z_m / slopes / GROUND_STEP_M).astype(np.intp) - 2, 0, len(along) - 5)
    window = first[:, None] + np.arange(5)
    flat, _ = first_hits(along[window], np.zeros(window.shape), mount.z_m, slopes)
    below = mount.z_m - slopes[:, None] * along[window] <= 0.0
    index = np.where(below.any(axis=1), first + np.argmax(below, axis=1), len(along))
    for array in (depressions, slopes, along, flat, index):
        array.flags.writeable = False
    return _Beams(depressions, slopes, along, float(reach), flat, index)


def _ground_hits(
    near: list[TerrainHazard], beams: _Beams, line: tuple[float, float, float, float], height_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each beam's first hit (distance ahead of the sensor, height): on flat ground, except for
    the beams that reach the samples around ``near`` hazards above the ground, which are traced
    through those samples as :func:`first_hits` traces any terrain. ``line`` is the scan line's
    ENU start and direction (east, north, cos, sin)."""
    distance, height = beams.flat_m.copy(), np.zeros(len(beams.flat_m))
    if not near:
        return distance, height
    first, last = _sample_window(near, line, beams)
    rows = np.flatnonzero(beams.flat_index > first)
    if not rows.size:
        return distance, height
    east, north, c, s = line
    along = beams.along_m[first : last + 1]
    ground = ground_height(near, east + c * along, north + s * along)
    traced, traced_height = first_hits(along, ground, height_m, beams.slopes[rows])
    # Beyond the window the ground is flat again: a beam still above it meets it where it would
    # have anyway, unless the window already ran to the last sample.
    crossed = np.isfinite(traced) | (last == len(beams.along_m) - 1)
    distance[rows[crossed]], height[rows[crossed]] = traced[crossed], traced_height[crossed]
    return distance, height


def _sample_window(
    near: list[TerrainHazard], line: tuple[float, float, float, float], beams: _Beams
) -> tuple[int, int]:
    """First and last ground sample around the stretch of the scan line that the hazards'
    bounding circles cover, one flat sample of margin each side (the ground there is 0)."""
    east, north, c, s = line
    enter, leave = math.inf, -math.inf
    for hazard in near:
        dx, dy = hazard.east_m - east, hazard.north_m - north
        foot = dx * c + dy * s
        half_chord = math.sqrt(max(_radius(hazard) ** 2 - (dy * c - dx * s) ** 2, 0.0))
        enter, leave = min(enter, foot - half_chord), max(leave, foot + half_chord)
    count = len(beams.along_m)
    first = min(max(math.floor(enter / GROUND_STEP_M) - 1, 0), count - 1)
    last = min(max(math.ceil(leave / GROUND_STEP_M) + 1, first), count - 1)
    return first, last


def _radius(hazard: TerrainHazard) -> float:
    """The hazard strip's bounding circle."""
    return math.hypot(hazard.length_m, hazard.width_m) / 2


def _near_line(
    hazards: tuple[TerrainHazard, ...] | list[TerrainHazard], east: float, north: float, yaw: float, reach: float
) -> list[TerrainHazard]:
    """The hazards whose bounding circle touches the scan line's ground track."""
    c, s = math.cos(yaw), math.sin(yaw)
    near = []
    for hazard in hazards:
        dx, dy = hazard.east_m - east, hazard.north_m - north
        foot = min(max(dx * c + dy * s, 0.0), reach)
        if math.hypot(dx - foot * c, dy - foot * s) <= _radius(hazard):
            near.append(hazard)
    return near


def first_hits(
    along: np.ndarray, ground: np.ndarray, height_m: float, slopes: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Where each beam from ``height_m``, falling ``slopes[i]`` per metre, first meets the sampled
    ground, interpolating linearly between the samples that bracket the crossing; inf distance for
    a beam that never does. ``along`` and ``ground`` are the samples' distances and heights,
    (samples,) shared by every beam or (beams, samples) each its own."""
    slopes = np.asarray(slopes, dtype=float)
    shape = (len(slopes), np.shape(along)[-1])
    along, ground = np.broadcast_to(along, shape), np.broadcast_to(ground, shape)
    beam = height_m - slopes[:, None] * along  # (beams, samples) height of each beam
    below = beam <= ground
    first = np.argmax(below, axis=1)
    rows = np.arange(len(slopes))
    hits = below[rows, first] & (first > 0)
    k = np.where(hits, first, 1)
    # Gap between beam and ground before (>0) and at (<=0) the crossing sample.
    before = beam[rows, k - 1] - ground[rows, k - 1]
    after = beam[rows, k] - ground[rows, k]
    fraction = before / np.maximum(before - after, 1e-12)
    distance = along[rows, k - 1] + fraction * (along[rows, k] - along[rows, k - 1])
    height = ground[rows, k - 1] + fraction * (ground[rows, k] - ground[rows, k - 1])
    return np.where(hits, distance, np.inf), np.where(hits, height, np.nan)
