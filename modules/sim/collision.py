"""Collisions and clearances between the vehicle's footprint and the world's obstacles, in 2-D.

The footprint is an oriented rectangle. Boxes are tested exactly with the separating-axis theorem
(for two rectangles, the four edge normals are the only candidate axes) and cylinders as circles
against the rectangle. Touching counts as a collision. A bounding-circle test skips obstacles that
cannot reach the footprint, so the simulator can check every obstacle of a scenario each step.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

from brain.pose import PoseLike
from modules.sim.vehicle import VehicleParams
from modules.sim.world import Shape, WorldObstacle

# A rectangle as a plain tuple: centre east and north, cosine and sine of its yaw, half length
# along the yaw and half width across it. The hot paths unpack it in one step instead of paying
# for named attribute access; OrientedRect is the same layout with names.
_Rect = tuple[float, float, float, float, float, float]


class OrientedRect(NamedTuple):
    """A rectangle centred at (east_m, north_m), ``half_length_m`` along its yaw and ``half_width_m``
    across it; the cosine and sine of the yaw are kept because every test uses them."""

    east_m: float
    north_m: float
    cos_yaw: float
    sin_yaw: float
    half_length_m: float
    half_width_m: float

    @classmethod
    def at(cls, east_m: float, north_m: float, yaw_rad: float, length_m: float, width_m: float) -> OrientedRect:
        """The rectangle of full ``length_m`` x ``width_m`` centred at a point, rotated by ``yaw_rad``."""
        return cls(east_m, north_m, math.cos(yaw_rad), math.sin(yaw_rad), 0.5 * length_m, 0.5 * width_m)

    def radius_m(self) -> float:
        """Radius of the circle around the centre through the corners."""
        return math.hypot(self.half_length_m, self.half_width_m)

    def corners(self) -> tuple[tuple[float, float], ...]:
        """The four corners in ENU, counter-clockwise from front left."""
        return _corners(self)


def footprint(pose: PoseLike, params: VehicleParams) -> OrientedRect:
    """The vehicle's outline at ``pose`` (the pose is the rear axle; the outline's centre is ahead of it)."""
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    ahead_m = 0.5 * params.length_m - params.rear_overhang_m
    return OrientedRect(
        pose.east_m + ahead_m * c, pose.north_m + ahead_m * s, c, s, 0.5 * params.length_m, 0.5 * params.width_m
    )


def obstacle_rect(obstacle: WorldObstacle) -> OrientedRect:
    """A box obstacle's outline."""
    return OrientedRect._make(_box(obstacle))


def collides(pose: PoseLike, obstacles: Sequence[WorldObstacle], params: VehicleParams) -> WorldObstacle | None:
    """The first obstacle (in sequence order) the vehicle's footprint at ``pose`` touches or overlaps."""
    rect = footprint(pose, params)
    east_m, north_m, _, _, half_length_m, half_width_m = rect
    reach_m = math.hypot(half_length_m, half_width_m)
    for obstacle in obstacles:
        d_east = obstacle.east_m - east_m
        d_north = obstacle.north_m - north_m
        # Prefilter on a circle that contains the obstacle whatever its shape: radius plus half
        # length plus half width bounds both a cylinder and a box's half diagonal, and costs a
        # fraction of WorldObstacle.footprint_radius_m(), which most of the time ends in "far away".
        limit = reach_m + obstacle.radius_m + 0.5 * (obstacle.length_m + obstacle.width_m)
        if d_east * d_east + d_north * d_north > limit * limit:
            continue
        if overlaps(rect, obstacle):
            return obstacle
    return None


def clearance_m(pose: PoseLike, obstacle: WorldObstacle, params: VehicleParams) -> float:
    """Distance between the vehicle's footprint at ``pose`` and ``obstacle``; 0 when they touch or overlap."""
    return distance_m(footprint(pose, params), obstacle)


def overlaps(rect: OrientedRect, obstacle: WorldObstacle) -> bool:
    """Whether ``rect`` touches or overlaps the obstacle's footprint (exact, no prefilter)."""
    if obstacle.shape is Shape.CYLINDER:
        radius_m = obstacle.radius_m
        return _point_distance_sq(rect, obstacle.east_m, obstacle.north_m) <= radius_m * radius_m
    return _rects_overlap(rect, _box(obstacle))


def distance_m(rect: OrientedRect, obstacle: WorldObstacle) -> float:
    """Distance between ``rect`` and the obstacle's footprint; 0 when they touch or overlap."""
    if obstacle.shape is Shape.CYLINDER:
        centre_m = math.sqrt(_point_distance_sq(rect, obstacle.east_m, obstacle.north_m))
        return max(0.0, centre_m - obstacle.radius_m)
    return _rects_distance_m(rect, _box(obstacle))


def rects_overlap(a: OrientedRect, b: OrientedRect) -> bool:
    """Separating-axis test of two oriented rectangles; touching counts as overlapping."""
    return _rects_overlap(a, b)


def rects_distance_m(a: OrientedRect, b: OrientedRect) -> float:
    """Distance between two oriented rectangles; 0 when they touch or overlap."""
    return _rects_distance_m(a, b)


def _box(obstacle: WorldObstacle) -> _Rect:
    yaw = obstacle.yaw_rad
    return (
        obstacle.east_m,
        obstacle.north_m,
        math.cos(yaw),
        math.sin(yaw),
        0.5 * obstacle.length_m,
        0.5 * obstacle.width_m,
    )


def _rects_overlap(a: _Rect, b: _Rect) -> bool:
    a_east, a_north, ca, sa, a_half_length, a_half_width = a
    b_east, b_north, cb, sb, b_half_length, b_half_width = b
    d_east, d_north = b_east - a_east, b_north - a_north
    # |cos| and |sin| of the relative yaw project one rectangle's half extents onto the other's axes.
    cos_rel = abs(ca * cb + sa * sb)
    sin_rel = abs(ca * sb - sa * cb)
    # The four edge normals are the only candidate separating axes of two rectangles.
    if abs(d_east * ca + d_north * sa) > a_half_length + b_half_length * cos_rel + b_half_width * sin_rel:
        return False
    if abs(d_north * ca - d_east * sa) > a_half_width + b_half_length * sin_rel + b_half_width * cos_rel:
        return False
    if abs(d_east * cb + d_north * sb) > b_half_length + a_half_length * cos_rel + a_half_width * sin_rel:
        return False
    return abs(d_north * cb - d_east * sb) <= b_half_width + a_half_length * sin_rel + a_half_width * cos_rel


def _rects_distance_m(a: _Rect, b: _Rect) -> float:
    if _rects_overlap(a, b):
        return 0.0
    # Two disjoint convex polygons are closest at a corner of one and the outline of the other.
    nearest_sq = min(
        min(_point_distance_sq(b, east, north) for east, north in _corners(a)),
        min(_point_distance_sq(a, east, north) for east, north in _corners(b)),
    )
    return math.sqrt(nearest_sq)


def _corners(rect: _Rect) -> tuple[tuple[float, float], ...]:
    east_m, north_m, c, s, half_length_m, half_width_m = rect
    corners = []
    for along, across in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        x, y = along * half_length_m, across * half_width_m
        corners.append((east_m + x * c - y * s, north_m + x * s + y * c))
    return tuple(corners)


def _point_distance_sq(rect: _Rect, east_m: float, north_m: float) -> float:
    """Squared distance from a point to the rectangle (0 inside)."""
    centre_east, centre_north, c, s, half_length_m, half_width_m = rect
    d_east, d_north = east_m - centre_east, north_m - centre_north
    along = abs(d_east * c + d_north * s) - half_length_m
    across = abs(d_north * c - d_east * s) - half_width_m
    along = along if along > 0.0 else 0.0
    across = across if across > 0.0 else 0.0
    return along * along + across * across
