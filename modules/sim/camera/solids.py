"""Pixel rays against the scenario's upright obstacles: boxes (slab test in the box's own frame)
and cylinders (quadratic for the side, plane for the top), vectorised over the pixels.

Obstacles are given in the vehicle frame (``to_vehicle_frame``), like the rays. A solid reaches
from ``base_m`` below the ground up to its height, so it stays closed where a ditch lowers the
terrain around it; the ground occludes whatever part lies underground.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from modules.sim.world import Shape, WorldObstacle

Array = NDArray[np.float64]

_PARALLEL_EPS = 1e-12
_BEHIND_M = 1e-6
# Surface-coordinate offsets so opposite faces and the top do not show the same patch of texture.
_FACE_OFFSET_M = (0.37, 1.13, 0.71, 1.79, 0.53)


def to_vehicle_frame(obstacle: WorldObstacle, east: float, north: float, yaw: float) -> WorldObstacle:
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = obstacle.east_m - east, obstacle.north_m - north
    return replace(obstacle, east_m=c * dx + s * dy, north_m=-s * dx + c * dy, yaw_rad=obstacle.yaw_rad - yaw)


def corners(obstacle: WorldObstacle, base_m: float) -> Array:
    """(8, 3) corners of a box containing the solid (a cylinder's is its bounding square prism)."""
    if obstacle.shape is Shape.CYLINDER:
        c, s, half_u, half_v = 1.0, 0.0, obstacle.radius_m, obstacle.radius_m
    else:
        c, s = math.cos(obstacle.yaw_rad), math.sin(obstacle.yaw_rad)
        half_u, half_v = obstacle.length_m / 2, obstacle.width_m / 2
    out = []
    for u in (-half_u, half_u):
        for v in (-half_v, half_v):
            for z in (-base_m, obstacle.height_m):
                out.append((obstacle.east_m + c * u - s * v, obstacle.north_m + s * u + c * v, z))
    return np.array(out)


@dataclass(frozen=True)
class SolidHits:
    depth: Array  # (n,) ray parameter (= depth) of the entry point; inf where missed
    surface_x: Array  # (n,) texture coordinates on the surface, metres
    surface_y: Array
    normal: Array  # (n, 3) outward normal, vehicle frame


def solid_hits(obstacle: WorldObstacle, origin: Array, direction: Array, base_m: float) -> SolidHits:
    """Entry hits of rays ``origin + t * direction`` ((n, 3), vehicle frame) with ``obstacle``
    (vehicle frame)."""
    if obstacle.shape is Shape.CYLINDER:
        return _cylinder(obstacle, origin, direction, base_m)
    return _box(obstacle, origin, direction, base_m)


def _box(box: WorldObstacle, origin: Array, direction: Array, base_m: float) -> SolidHits:
    c, s = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
    rel_x, rel_y = origin[0] - box.east_m, origin[1] - box.north_m
    start = (rel_x * c + rel_y * s, -rel_x * s + rel_y * c, origin[2])
    dx, dy, dz = direction[:, 0], direction[:, 1], direction[:, 2]
    local = (dx * c + dy * s, -dx * s + dy * c, dz)
    bounds = ((-box.length_m / 2, box.length_m / 2), (-box.width_m / 2, box.width_m / 2), (-base_m, box.height_m))
    nears, fars = [], []
    for o, d, (low, high) in zip(start, local, bounds, strict=True):
        d = np.where(np.abs(d) < _PARALLEL_EPS, _PARALLEL_EPS, d)
        t1, t2 = (low - o) / d, (high - o) / d
        nears.append(np.minimum(t1, t2))
        fars.append(np.maximum(t1, t2))
    near = np.stack(nears)
    face = np.argmax(near, axis=0)  # the slab entered last is the face the ray comes through
    t_near = near.max(axis=0)
    t_far = np.minimum(np.minimum(fars[0], fars[1]), fars[2])
    hit = (t_near <= t_far) & (t_near > _BEHIND_M)
    depth = np.where(hit, t_near, np.inf)
    px, py, pz = (o + t_near * d for o, d in zip(start, local, strict=True))
    # Side faces carry (along the face, height), the top (length, width) coordinates.
    on_x, on_y = face == 0, face == 1
    side_sign = np.where(on_x, np.sign(px), np.where(on_y, np.sign(py), 0.0))
    offset = np.choose(np.where(face == 2, 4, face + 2 * (side_sign > 0)), _FACE_OFFSET_M)
    surface_x = np.where(on_x, py, px) + offset
    surface_y = np.where(face == 2, py, pz)
    n_local_x = np.where(on_x, side_sign, 0.0)
    n_local_y = np.where(on_y, side_sign, 0.0)
    normal = np.column_stack((c * n_local_x - s * n_local_y, s * n_local_x + c * n_local_y, (face == 2).astype(float)))
    return SolidHits(depth, surface_x, surface_y, normal)


def _cylinder(cylinder: WorldObstacle, origin: Array, direction: Array, base_m: float) -> SolidHits:
    r = cylinder.radius_m
    rel_x, rel_y = origin[0] - cylinder.east_m, origin[1] - cylinder.north_m
    dx, dy, dz = direction[:, 0], direction[:, 1], direction[:, 2]
    a = np.maximum(dx * dx + dy * dy, _PARALLEL_EPS)
    b = rel_x * dx + rel_y * dy
    disc = b * b - a * (rel_x * rel_x + rel_y * rel_y - r * r)
    t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    z_side = origin[2] + t_side * dz
    side = (disc >= 0) & (t_side > _BEHIND_M) & (z_side >= -base_m) & (z_side <= cylinder.height_m)
    falling = np.where(dz < -_PARALLEL_EPS, -dz, np.nan)
    t_top = (origin[2] - cylinder.height_m) / falling
    top_x, top_y = rel_x + t_top * dx, rel_y + t_top * dy
    with np.errstate(invalid="ignore"):
        top = (t_top > _BEHIND_M) & (top_x * top_x + top_y * top_y <= r * r)
    depth = np.minimum(np.where(side, t_side, np.inf), np.where(top, t_top, np.inf))
    on_top = top & ~(side & (t_side <= t_top))
    t = np.where(on_top, t_top, t_side)
    hx, hy = rel_x + t * dx, rel_y + t * dy
    # Texture coordinates in the cylinder's own (world-anchored) frame, so they do not turn with
    # the vehicle: to_vehicle_frame leaves a cylinder's yaw as minus the vehicle's.
    c, s = math.cos(cylinder.yaw_rad), math.sin(cylinder.yaw_rad)
    own_x, own_y = hx * c + hy * s, -hx * s + hy * c
    surface_x = np.where(on_top, own_x + _FACE_OFFSET_M[4], np.arctan2(own_y, own_x) * r)
    surface_y = np.where(on_top, own_y, origin[2] + t * dz)
    radial = np.hypot(hx, hy)
    radial = np.where(radial > 0, radial, 1.0)
    normal = np.column_stack(
        (np.where(on_top, 0.0, hx / radial), np.where(on_top, 0.0, hy / radial), on_top.astype(float))
    )
    return SolidHits(depth, surface_x, surface_y, normal)
