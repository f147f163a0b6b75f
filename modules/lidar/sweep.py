"""Sweeping lidar: a scanner pitched down so that its plane meets the ground in a line across the
road ahead, the way Stanley's roof lidars saw a ditch long before the vehicle reached it.

The vertical lidars see the ground along two lines 1 m apart, out to 25 m; a wash across the road
shows up in them, but not where it ends. A scan line across the road does: a beam that falls into
a ditch comes back from its far wall, below the plane the vehicle stands on, and the beams on
either side of the ditch come back from level ground. With beams 0.5 deg apart a ditch's end is
placed within 0.15 m at 35 m, where stereo is uncertain by metres.

The returns are simulated in modules/sim/lidar/sweep.py.

Description. Each return is level (within ``step_m`` of the plane), low or high. Consecutive
returns of a kind make a stretch (low and high ones at most ``max_piece_m`` across), sent as a
box in the vehicle frame:

- level: the box around its returns;
- low: from where the beams met the plane to where they came back: they passed above the ground
  all that way, so the ground there is lower than the plane (by step_m from 0.7 m on; the drop
  that took it lower begins at the plane or nearer, the way a ditch's near wall does). Beams off
  to the side drift sideways as they go, so a low run is cut into slabs across the x axis, each
  covering only the beams low in it (at most ``max_slant_m`` of drift per slab);
- high: around its returns (what lies behind is hidden), cut into pieces at most ``max_depth_m``
  deep: a box around a face seen at a slant reaches past its ends by up to its depth, and a
  rock's side of a passage 2.7 m wide came out 0.3-0.6 m wider with one box per face.

Low and high stretches reach half a beam spacing beyond their outermost returns, at those
returns' own distance; level ones stop at their outermost return: hazards grow, level ground
shrinks, as everywhere in the map.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from protocol.messages import GroundStretch, GroundSweep

LEVEL, LOW, HIGH = 0, -1, 1
MAX_SLABS = 16  # a low run's boxes at most (a 2 m run 30 deg off to the side needs about 7)


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


def describe_sweep(
    returns: SweepReturns,
    mount: SweepMount,
    sensor: int,
    step_m: float = 0.04,
    max_piece_m: float = 2.0,
    max_depth_m: float = 0.25,
    max_slant_m: float = 0.2,
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
    stretches: list[GroundStretch] = []
    for run in runs:
        if kind[run.start] == LOW:
            stretches += _low_slabs(b[run], met[run], x[run], float(z[run].min()), mount, half, max_slant_m)
        else:
            stretches.append(_stretch(run, int(kind[run.start]), x, y, z, reach))
    return GroundSweep(sensor, tuple(stretches))


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
    run: slice, kind: int, x: np.ndarray, y: np.ndarray, z: np.ndarray, reach: tuple[np.ndarray, np.ndarray]
) -> GroundStretch:
    """The box of the level or high returns ``run`` (consecutive beams of one kind)."""
    if kind == LEVEL:
        return GroundStretch(float(x[run].min()), float(x[run].max()), float(y[run].min()), float(y[run].max()), 0.0)
    right, left = float(reach[0][run].min()), float(reach[1][run].max())
    return GroundStretch(float(x[run].min()), float(x[run].max()), right, left, float(z[run].max()))


def _low_slabs(
    bearings: np.ndarray,
    met: np.ndarray,
    x: np.ndarray,
    depth_m: float,
    mount: SweepMount,
    half_rad: float,
    max_slant_m: float,
) -> list[GroundStretch]:
    """A low run's ground, each beam's from where it met the plane to where it came back, as
    boxes cut across the vehicle's x axis. A beam at a slant drifts sideways as it goes: one box
    from the nearest meeting to the farthest return covered ground beside every beam (a ditch
    seen 30 deg off to the side came out a metre wider at its end). Each slab spans at most
    ``max_slant_m`` of that drift and covers, across its depth, the beams low there, each to
    half a beam spacing either side."""
    near, far = float(met.min()), float(x.max())
    drift_m = float(np.max(np.abs(np.tan(bearings)) * (x - met)))
    edges = np.linspace(near, far, min(MAX_SLABS, max(1, math.ceil(drift_m / max_slant_m))) + 1)
    right_tan, left_tan = np.tan(bearings - half_rad), np.tan(bearings + half_rad)
    slabs = []
    for start, end in itertools.pairwise(edges.tolist()):
        low = (met <= end) & (x >= start)  # the beams low somewhere in this slab
        # Each beam's lateral position is linear in x: its extremes are at its span's ends in the slab.
        ends = np.stack((np.maximum(start, met[low]), np.minimum(end, x[low]))) - mount.x_m
        right = mount.y_m + float(np.min(ends * right_tan[low]))
        left = mount.y_m + float(np.max(ends * left_tan[low]))
        slabs.append(GroundStretch(start, end, right, left, depth_m))
    return slabs
