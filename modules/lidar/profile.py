"""Vertical lidar: the ground profile ahead of the vehicle, and the hazards in it.

A scanner mounted high and turned to sweep a vertical plane along the vehicle's heading sees the
ground ahead as one line of returns: RASCAL tracked the surface this way. Beams step by 0.5 deg
between the depression that meets flat ground ``near_m`` ahead and the one that meets it
``far_m`` ahead; on flat ground their footprints thin out with range (0.15 m apart at 5 m,
0.56 m at 10 m, 2.2 m at 20 m), which bounds how precisely an edge can be placed.

Terrain is flat (height 0) except for the scenario's hazards. Each hazard is a strip: ``u`` runs
along its ``yaw_rad`` (the direction a vehicle crosses it) over ``length_m``, ``v`` across it over
``width_m``. Inside the strip:

- a ditch goes down by ``magnitude_m`` over 45 deg walls and comes back up;
- a berm goes up by ``magnitude_m`` over 45 deg walls and comes back down;
- a drop-off falls by ``magnitude_m`` at its near edge (u = -length/2) over a steep face
  (5:1) and stays down to the strip's far end. A drop-off is meant to be longer than the
  sensors reach; crossed the other way it is a step up.

Overlapping hazards add. The vehicle is assumed level on the plane z = 0 (SimTruth has no
attitude), so heights are relative to the ground under the vehicle.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from brain.pose import Pose
from modules.sim.world import HazardKind, TerrainHazard
from protocol.messages import SurfaceProfile

WALL_SLOPE = 1.0  # rise over run of ditch and berm walls (45 deg)
CLIFF_SLOPE = 5.0  # rise over run of a drop-off's face
GROUND_STEP_M = 0.05  # terrain sampling along the scan line; walls between samples are linear


@dataclass(frozen=True)
class VerticalMount:
    """A vertically scanning lidar: its position in the vehicle frame (it looks along +x) and
    the stretch of flat ground its beams cover."""

    x_m: float
    y_m: float
    z_m: float = 1.6
    near_m: float = 3.0  # flat-ground distance ahead of the sensor of the steepest beam
    far_m: float = 25.0  # ... of the shallowest beam
    resolution_rad: float = math.radians(0.5)
    max_range_m: float = 80.0
    range_noise_std_m: float = 0.01

    def depressions_rad(self) -> np.ndarray:
        """Beam angles below horizontal, steepest (nearest) first."""
        steep, shallow = math.atan2(self.z_m, self.near_m), math.atan2(self.z_m, self.far_m)
        count = int((steep - shallow) / self.resolution_rad + 1e-9) + 1
        return steep - self.resolution_rad * np.arange(count)


VERTICAL_MOUNTS: dict[str, VerticalMount] = {
    "lidar_v_left": VerticalMount(x_m=1.5, y_m=0.5),
    "lidar_v_right": VerticalMount(x_m=1.5, y_m=-0.5),
}


class Hazard(NamedTuple):
    """A stretch of a profile that is not level ground, in vehicle-frame forward distance."""

    kind: HazardKind
    start_range_m: float
    end_range_m: float
    magnitude_m: float  # depth of a ditch or drop-off, height of a berm


def ground_height(
    hazards: tuple[TerrainHazard, ...] | list[TerrainHazard], east: np.ndarray, north: np.ndarray
) -> np.ndarray:
    """Terrain height at ENU points (arrays of one shape), by the hazard model above."""
    height = np.zeros(np.shape(east))
    for hazard in hazards:
        dx, dy = east - hazard.east_m, north - hazard.north_m
        c, s = math.cos(hazard.yaw_rad), math.sin(hazard.yaw_rad)
        u, v = dx * c + dy * s, -dx * s + dy * c
        half = hazard.length_m / 2
        inside = (np.abs(u) <= half) & (np.abs(v) <= hazard.width_m / 2)
        if hazard.kind is HazardKind.DROP_OFF:
            run = min(hazard.magnitude_m / CLIFF_SLOPE, half / 2)
            shape = -np.clip((u + half) / run, 0.0, 1.0)
        else:
            run = min(hazard.magnitude_m / WALL_SLOPE, half / 2)
            sign = 1.0 if hazard.kind is HazardKind.BERM else -1.0
            shape = sign * np.clip((half - np.abs(u)) / run, 0.0, 1.0)
        height += np.where(inside, hazard.magnitude_m * shape, 0.0)
    return height


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


def detect_hazards(profile: SurfaceProfile, step_m: float = 0.15) -> list[Hazard]:
    """Non-level stretches of a profile: runs of returns more than ``step_m`` below (ditch or,
    when the ground never comes back up within the profile, drop-off) or above (berm) the
    vehicle's ground plane.

    A hazard starts half a sample spacing past the last level return before it: a wall facing
    away from the sensor is in shadow, so its edge lies somewhere before the next beam's footprint.
    It ends at the first level return after it, which for a berm means after the shadow behind
    its crest (where its far side is hidden: a conservative end). The magnitude is the deepest
    or highest return seen, a lower bound when part of the hazard is hidden; for a drop-off, the
    median of its returns (its floor)."""
    ranges = np.asarray(profile.ranges_m, dtype=float)
    heights = np.asarray(profile.heights_m, dtype=float)
    level = np.where(heights < -step_m, -1, np.where(heights > step_m, 1, 0))
    hazards = []
    i = 0
    while i < len(level):
        if level[i] == 0:
            i += 1
            continue
        j = i
        while j + 1 < len(level) and level[j + 1] == level[i]:
            j += 1
        hazards.append(_describe_run(ranges, heights, level, i, j))
        i = j + 1
    return hazards


def _describe_run(ranges: np.ndarray, heights: np.ndarray, level: np.ndarray, i: int, j: int) -> Hazard:
    """The hazard made of returns i..j (all below, or all above, the level band)."""
    if i == 0:
        start = float(ranges[0])
    else:
        spacing = ranges[i - 1] - ranges[i - 2] if i >= 2 else 0.0
        start = float(min(ranges[i - 1] + spacing / 2, ranges[i]))
    # Runs are maximal, so whatever follows a low run is higher ground: the ground came back up.
    comes_back = j + 1 < len(level)
    end = float(ranges[j + 1]) if comes_back else float(ranges[j])
    run = heights[i : j + 1]
    if level[i] > 0:
        return Hazard(HazardKind.BERM, start, end, float(run.max()))
    if comes_back:
        return Hazard(HazardKind.DITCH, start, end, float(-run.min()))
    return Hazard(HazardKind.DROP_OFF, start, end, float(-np.median(run)))
