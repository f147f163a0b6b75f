"""Where pixel rays meet terrain changed by ditches, berms and drop-offs.

The height model is the vertical lidars' (modules.lidar.profile.ground_height), so both sensors
see one terrain. That model is piecewise linear inside each hazard's strip (flat floor or crest,
straight walls) and zero outside, so the hits are exact, with no marching:

- a ray that can meet only one hazard (nearly all of them) is solved piece by piece: a linear
  equation per wall or floor, plus the steps where it enters or leaves the strip;
- a ray that two hazards may both touch samples its height above the terrain at every kink and
  strip edge of all of them (each edge twice, just before and after, as the strip's sides are
  steps) and interpolates at the first sign change.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from itertools import pairwise

import numpy as np
from numpy.typing import NDArray

from modules.sim.terrain import CLIFF_SLOPE, WALL_SLOPE, ground_height
from modules.sim.world import HazardKind, TerrainHazard

Array = NDArray[np.float64]

_EDGE_EPS_M = 1e-4  # samples either side of a step; a hit on a step lands within this of it
_NORMAL_STEP_M = 0.05  # finite-difference step for the terrain normal (shading only)


def to_vehicle_frame(hazard: TerrainHazard, east: float, north: float, yaw: float) -> TerrainHazard:
    """The same hazard with its position and heading in the vehicle frame of a pose: the height
    model only depends on positions relative to the strip, so it works in any frame."""
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = hazard.east_m - east, hazard.north_m - north
    return replace(hazard, east_m=c * dx + s * dy, north_m=-s * dx + c * dy, yaw_rad=hazard.yaw_rad - yaw)


def height_range(hazard: TerrainHazard) -> tuple[float, float]:
    """Lowest and highest terrain the hazard makes."""
    if hazard.kind is HazardKind.BERM:
        return 0.0, hazard.magnitude_m
    return -hazard.magnitude_m, 0.0


def corners(hazard: TerrainHazard) -> Array:
    """(8, 3) corners of the box the hazard's terrain fits in (any frame the hazard is given in)."""
    c, s = math.cos(hazard.yaw_rad), math.sin(hazard.yaw_rad)
    low, high = height_range(hazard)
    out = []
    for u in (-hazard.length_m / 2, hazard.length_m / 2):
        for v in (-hazard.width_m / 2, hazard.width_m / 2):
            for z in (low, high):
                out.append((hazard.east_m + c * u - s * v, hazard.north_m + s * u + c * v, z))
    return np.array(out)


def _kinks(hazard: TerrainHazard) -> list[float]:
    """Strip coordinates u where the height profile bends or steps (as in ground_height)."""
    half = hazard.length_m / 2
    if hazard.kind is HazardKind.DROP_OFF:
        run = min(hazard.magnitude_m / CLIFF_SLOPE, half / 2)
        return [-half, -half + run, half]
    run = min(hazard.magnitude_m / WALL_SLOPE, half / 2)
    return [-half, -half + run, half - run, half]


def may_hit(hazard: TerrainHazard, origin: Array, direction: Array, flat_depth: Array) -> NDArray[np.bool_]:
    """Rays ((n, 3), vehicle frame) that can meet this hazard's terrain before the flat ground:
    those whose ground track between the height of its top and the flat hit (``flat_depth``)
    crosses the strip. Everything else sees flat ground, so only these need ``terrain_hits``."""
    dz = direction[:, 2]
    down = dz < -1e-12
    falling = np.where(down, -dz, 1.0)
    t_a = np.maximum((origin[2] - height_range(hazard)[1]) / falling, 0.0)
    t_b = np.where(down, flat_depth, -np.inf)
    c, s = math.cos(hazard.yaw_rad), math.sin(hazard.yaw_rad)
    rel_x, rel_y = origin[0] - hazard.east_m, origin[1] - hazard.north_m
    starts = (rel_x * c + rel_y * s, -rel_x * s + rel_y * c)
    steps = (direction[:, 0] * c + direction[:, 1] * s, -direction[:, 0] * s + direction[:, 1] * c)
    for start, step, half in zip(starts, steps, (hazard.length_m / 2, hazard.width_m / 2), strict=True):
        step = np.where(np.abs(step) < 1e-12, 1e-12, step)
        t1, t2 = (-half - start) / step, (half - start) / step
        t_a = np.maximum(t_a, np.minimum(t1, t2))
        t_b = np.minimum(t_b, np.maximum(t1, t2))
    # A ditch's segment is a single point (its top is the ground): allow for rounding.
    return t_a <= t_b + 1e-6


@dataclass(frozen=True)
class TerrainHits:
    depth: Array  # (n,) ray parameter (= depth) of the first terrain hit; inf where none
    in_hazard: NDArray[np.bool_]  # the hit lies inside a hazard's strip
    normal: Array  # (n, 3) terrain normal at the hit (vehicle frame)


def terrain_hits(
    hazards: list[TerrainHazard], origin: Array, direction: Array, far_m: float, flat_depth: Array
) -> TerrainHits:
    """First hits of rays ``origin + t * direction`` ((n, 3), vehicle frame) with the terrain the
    ``hazards`` (vehicle frame) make on the z = 0 plane; ``flat_depth`` is each ray's hit on the
    plane itself (inf where it has none)."""
    n = len(direction)
    depth = np.asarray(flat_depth, dtype=float).copy()
    in_hazard = np.zeros(n, dtype=bool)
    normal = np.zeros((n, 3))
    normal[:, 2] = 1.0
    flags = np.array([may_hit(h, origin, direction, depth) for h in hazards]).reshape(len(hazards), n)
    # Where strips overlap their heights add, so a ray over one of them needs the general path.
    shared = _overlapping(hazards)
    general = (flags.sum(axis=0) >= 2) | flags[shared].any(axis=0)
    for hazard, flagged in zip(hazards, flags, strict=True):
        index = np.flatnonzero(flagged & ~general)
        if index.size:
            depth[index], in_hazard[index], normal[index] = _single_hits(hazard, origin, direction[index])
    index = np.flatnonzero(general)
    if index.size:
        depth[index], in_hazard[index], normal[index] = _sampled_hits(hazards, origin, direction[index])
    depth[depth > far_m] = np.inf
    in_hazard &= np.isfinite(depth)
    return TerrainHits(depth, in_hazard, normal)


def _single_hits(hazard: TerrainHazard, origin: Array, direction: Array) -> tuple[Array, NDArray[np.bool_], Array]:
    """Exact hits with one hazard's terrain: (depth, inside its strip, normal)."""
    n = len(direction)
    c, s = math.cos(hazard.yaw_rad), math.sin(hazard.yaw_rad)
    axes = (np.array([c, s, 0.0]), np.array([-s, c, 0.0]))  # across (u) and along (v) the strip
    rel_x, rel_y = origin[0] - hazard.east_m, origin[1] - hazard.north_m
    u0, v0, oz = rel_x * c + rel_y * s, -rel_x * s + rel_y * c, origin[2]
    dx, dy, dz = direction[:, 0], direction[:, 1], direction[:, 2]
    du, dv = _nudged(dx * c + dy * s), _nudged(-dx * s + dy * c)
    near, far = [], []
    for start, step, half in ((u0, du, hazard.length_m / 2), (v0, dv, hazard.width_m / 2)):
        t1, t2 = (-half - start) / step, (half - start) / step
        near.append(np.minimum(t1, t2))
        far.append(np.maximum(t1, t2))
    t_in, t_out = np.maximum(near[0], near[1]), np.minimum(far[0], far[1])
    through = (t_in <= t_out) & (t_out > 0.0)
    t_in = np.maximum(t_in, 0.0)
    down = dz < -1e-12
    with np.errstate(divide="ignore"):
        flat = np.where(down, oz / -np.where(down, dz, -1.0), np.inf)
    # Outside the strip the ground is the plane.
    best = np.where(through & (flat >= t_in) & (flat <= t_out), np.inf, flat)
    normal = np.zeros((n, 3))
    normal[:, 2] = 1.0
    inside = np.zeros(n, dtype=bool)

    def take(hit: NDArray[np.bool_], t: Array, surface: Array) -> None:
        nonlocal best
        best = np.where(hit, t, best)
        normal[hit] = surface if surface.ndim == 1 else surface[hit]
        inside[hit] = True

    # Entering through a side below the strip's terrain: the ray meets the step's face.
    t_enter = t_in + 1e-6
    height = ground_height([hazard], origin[0] + t_enter * dx, origin[1] + t_enter * dy)
    across = near[0] >= near[1]
    faces = (
        -np.where(across, np.sign(du), 0.0)[:, None] * axes[0] - np.where(across, 0.0, np.sign(dv))[:, None] * axes[1]
    )
    take(through & (oz + t_enter * dz < height) & (t_in < best), t_in, faces)
    # Each wall and floor is linear across the strip: h = slope * u + offset on [a, b].
    kinks = _kinks(hazard)
    for a, b in pairwise(kinks):
        ua, ub = a + 1e-6 * (b - a), b - 1e-6 * (b - a)
        ha, hb = ground_height(
            [hazard], hazard.east_m + c * np.array([ua, ub]), hazard.north_m + s * np.array([ua, ub])
        )
        slope = (hb - ha) / (ub - ua)
        offset = ha - slope * ua
        ta, tb = (a - u0) / du, (b - u0) / du
        low, high = np.maximum(np.minimum(ta, tb), t_in), np.minimum(np.maximum(ta, tb), t_out)
        with np.errstate(divide="ignore", invalid="ignore"):
            root = (oz - slope * u0 - offset) / (slope * du - dz)
        hit = through & (root >= low - 1e-9) & (root <= high + 1e-9) & (root < best)
        surface = np.array([-slope * c, -slope * s, 1.0])
        take(hit, root, surface / np.linalg.norm(surface))
    # Leaving the strip below the plane: the ray meets the face of the step back up.
    across = far[0] <= far[1]
    faces = (
        -np.where(across, np.sign(du), 0.0)[:, None] * axes[0] - np.where(across, 0.0, np.sign(dv))[:, None] * axes[1]
    )
    take(through & (best > t_out) & (oz + t_out * dz < 0.0), t_out, faces)
    return best, inside, normal


def _overlapping(hazards: list[TerrainHazard]) -> NDArray[np.bool_]:
    """Which hazards' strips may overlap another's (their bounding circles do)."""
    shared = np.zeros(len(hazards), dtype=bool)
    for i, one in enumerate(hazards):
        for j in range(i + 1, len(hazards)):
            other = hazards[j]
            reach = (math.hypot(one.length_m, one.width_m) + math.hypot(other.length_m, other.width_m)) / 2
            if math.hypot(one.east_m - other.east_m, one.north_m - other.north_m) <= reach:
                shared[i] = shared[j] = True
    return shared


def _nudged(step: Array) -> Array:
    """Direction components this close to zero are nudged off it, so slab tests never divide
    zero by zero; the nudge moves a hit by far less than a nanometre."""
    return np.where(np.abs(step) < 1e-12, 1e-12, step)


def _sampled_hits(
    hazards: list[TerrainHazard], origin: Array, direction: Array
) -> tuple[Array, NDArray[np.bool_], Array]:
    """Hits with several hazards' summed terrain: (depth, inside a strip, normal)."""
    n = len(direction)
    dx, dy, dz = direction[:, 0], direction[:, 1], direction[:, 2]
    # Overlapping hazards add, so the terrain lies between the sums of their extremes.
    low = sum(height_range(h)[0] for h in hazards)
    high = sum(height_range(h)[1] for h in hazards)
    down = dz < -1e-12
    falling = np.where(down, -dz, 1.0)
    t_start = np.maximum((origin[2] - high) / falling, 0.0)  # the ray is above every hazard before
    t_end = (origin[2] - low) / falling  # ... and below every hazard after
    samples = [t_start, t_end]
    for hazard in hazards:
        c, s = math.cos(hazard.yaw_rad), math.sin(hazard.yaw_rad)
        rel_x, rel_y = origin[0] - hazard.east_m, origin[1] - hazard.north_m
        u0, v0 = rel_x * c + rel_y * s, -rel_x * s + rel_y * c
        du, dv = _nudged(dx * c + dy * s), _nudged(-dx * s + dy * c)
        crossings = [(k - u0) / du for k in _kinks(hazard)]
        crossings += [(side - v0) / dv for side in (-hazard.width_m / 2, hazard.width_m / 2)]
        for t in crossings:
            samples += [t - _EDGE_EPS_M, t + _EDGE_EPS_M]
    t = np.clip(np.column_stack(samples), t_start[:, None], t_end[:, None])
    t.sort(axis=1)
    x = origin[0] + t * dx[:, None]
    y = origin[1] + t * dy[:, None]
    above = origin[2] + t * dz[:, None] - ground_height(hazards, x, y)
    # The ray ends below the lowest terrain, so a crossing always exists for descending rays.
    first = np.argmax(above <= 0.0, axis=1)
    rows = np.arange(n)
    before = np.maximum(first - 1, 0)
    a0, a1 = above[rows, before], above[rows, first]
    t0, t1 = t[rows, before], t[rows, first]
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where(first > 0, a0 / (a0 - a1), 0.0)
    depth = np.where(down, t0 + np.nan_to_num(fraction) * (t1 - t0), np.inf)
    hit = np.isfinite(depth)
    hx = np.where(hit, origin[0] + depth * dx, 0.0)
    hy = np.where(hit, origin[1] + depth * dy, 0.0)
    return depth, _inside_any(hazards, hx, hy) & hit, _normals(hazards, hx, hy)


def _inside_any(hazards: list[TerrainHazard], x: Array, y: Array) -> NDArray[np.bool_]:
    inside = np.zeros(x.shape, dtype=bool)
    for hazard in hazards:
        c, s = math.cos(hazard.yaw_rad), math.sin(hazard.yaw_rad)
        rx, ry = x - hazard.east_m, y - hazard.north_m
        # A hit on a strip's end wall lies on its edge, to within the step sampling: allow that.
        slack = 2 * _EDGE_EPS_M
        inside |= (np.abs(rx * c + ry * s) <= hazard.length_m / 2 + slack) & (
            np.abs(-rx * s + ry * c) <= hazard.width_m / 2 + slack
        )
    return inside


def _normals(hazards: list[TerrainHazard], x: Array, y: Array) -> Array:
    step = _NORMAL_STEP_M
    slope_x = (ground_height(hazards, x + step, y) - ground_height(hazards, x - step, y)) / (2 * step)
    slope_y = (ground_height(hazards, x, y + step) - ground_height(hazards, x, y - step)) / (2 * step)
    normal = np.column_stack((-slope_x, -slope_y, np.ones_like(x)))
    return normal / np.linalg.norm(normal, axis=1, keepdims=True)
