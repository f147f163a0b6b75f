"""Synthetic courses, fused-map grids and exact geometry for the planner tests.

The grids stand in for fusion's output: a `GridWindow` with float32 ``hazard_probability`` and
``cost`` arrays of its shape, ``inf`` marking lethal cells.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from brain.corridor import Course
from brain.grid import GridWindow
from brain.vehicle import VehicleGeometry
from protocol.messages import Path
from tests.brain.rddf_samples import waypoints_at


@dataclass(frozen=True)
class Pose:
    east_m: float
    north_m: float
    yaw_rad: float = 0.0
    speed_mps: float = 0.0


def straight_course(length_m: float = 400.0, half_width_m: float = 9.144, speed_mph: float = 25.0) -> Course:
    """A course due east from the origin; 9.144 m is a 30 ft lateral offset."""
    return Course(waypoints_at([(0.0, 0.0), (length_m, 0.0)], offset_ft=half_width_m / 0.3048, speed_mph=speed_mph))


def course_through(points: Sequence[tuple[float, float]], half_width_m: float, speed_mph: float = 25.0) -> Course:
    return Course(waypoints_at(points, offset_ft=half_width_m / 0.3048, speed_mph=speed_mph))


class Map:
    """A grid window with its two layers, and helpers to stamp obstacles into them."""

    def __init__(self, window: GridWindow) -> None:
        self.window = window
        self.hazard = np.zeros(window.shape, dtype=np.float32)
        self.cost = np.zeros(window.shape, dtype=np.float32)
        self.east, self.north = window.cell_centres()

    @classmethod
    def around(cls, east_m: float, north_m: float, width_m: float, height_m: float, res: float = 0.2) -> Map:
        return cls(GridWindow.centred(east_m, north_m, width_m, height_m, res))

    def box(self, east0: float, north0: float, east1: float, north1: float) -> Map:
        """Lethal cells whose centres lie in the box."""
        inside = (self.east >= east0) & (self.east <= east1) & (self.north >= north0) & (self.north <= north1)
        return self._lethal(inside)

    def disc(self, east: float, north: float, radius: float) -> Map:
        return self._lethal(np.hypot(self.east - east, self.north - north) <= radius)

    def clear_box(self, east0: float, north0: float, east1: float, north1: float) -> Map:
        inside = (self.east >= east0) & (self.east <= east1) & (self.north >= north0) & (self.north <= north1)
        self.cost[inside] = 0.0
        self.hazard[inside] = 0.0
        return self

    def _lethal(self, mask: np.ndarray) -> Map:
        self.cost[mask] = np.inf
        self.hazard[mask] = 1.0
        return self

    def lethal_centres(self) -> np.ndarray:
        lethal = np.isposinf(self.cost)
        return np.column_stack([self.east[lethal], self.north[lethal]])


def path_points(path: Path) -> np.ndarray:
    """(N, 3) east, north, speed of a protocol Path."""
    return np.array([(p.east_m, p.north_m, p.speed_mps) for p in path.points], dtype=float)


def polyline_distance(points: np.ndarray, targets: np.ndarray) -> float:
    """Exact least distance from the polyline through ``points`` (N x 2) to any target point (M x 2)."""
    if len(targets) == 0:
        return np.inf
    if len(points) == 1:
        return float(np.min(np.hypot(*(targets - points[0]).T)))
    start, end = points[:-1], points[1:]
    best = np.inf
    for chunk in np.array_split(targets, max(1, len(targets) // 2000 + 1)):
        direction = end - start
        length2 = np.maximum(np.einsum("ij,ij->i", direction, direction), 1e-18)
        rel = chunk[:, None, :] - start[None, :, :]
        t = np.clip(np.einsum("mkj,kj->mk", rel, direction) / length2, 0.0, 1.0)
        gap = rel - t[..., None] * direction[None]
        best = min(best, float(np.sqrt(np.min(np.einsum("mkj,mkj->mk", gap, gap)))))
    return best


def densified(points: np.ndarray, spacing_m: float = 0.05) -> np.ndarray:
    """Points along the polyline no further apart than ``spacing_m`` (vertices included)."""
    out = [points[:1]]
    for a, b in itertools.pairwise(points):
        count = max(1, int(np.ceil(np.hypot(*(b - a)) / spacing_m)))
        out.append(a + np.linspace(0.0, 1.0, count + 1)[1:, None] * (b - a))
    return np.vstack(out)


def body_poses(points: np.ndarray, vehicle: VehicleGeometry, spacing_m: float = 0.05) -> np.ndarray:
    """Rear-axle poses (east, north, heading; K x 3) along the polyline every ``spacing_m``,
    heading along the segment each lies on: the stretch whose whole body the path answers for,
    from a rear overhang after its start (the vehicle stands there already) to a nose before its
    end (beyond, the nose check at a stop answers)."""
    poses = []
    along = 0.0
    for a, b in itertools.pairwise(np.asarray(points, dtype=float)):
        length = float(np.hypot(*(b - a)))
        if length <= 1e-9:
            continue
        heading = float(np.arctan2(b[1] - a[1], b[0] - a[0]))
        count = max(1, int(np.ceil(length / spacing_m)))
        for t in np.linspace(0.0, 1.0, count + 1)[:-1]:
            poses.append((*(a + t * (b - a)), heading, along + t * length))
        along += length
    table = np.asarray(poses).reshape(-1, 4)
    held = (table[:, 3] >= vehicle.rear_overhang_m) & (table[:, 3] <= along - vehicle.front_m)
    return table[held, :3]


def body_distance(poses: np.ndarray, targets: np.ndarray, vehicle: VehicleGeometry) -> float:
    """Exact least distance from the vehicle's rectangle at any of ``poses`` to any target point."""
    if len(poses) == 0 or len(targets) == 0:
        return np.inf
    best = np.inf
    for pose in poses:
        rel = targets - pose[:2]
        cos, sin = np.cos(pose[2]), np.sin(pose[2])
        x = rel[:, 0] * cos + rel[:, 1] * sin
        y = -rel[:, 0] * sin + rel[:, 1] * cos
        dx = np.maximum(np.maximum(-vehicle.rear_overhang_m - x, x - vehicle.front_m), 0.0)
        dy = np.maximum(np.abs(y) - vehicle.half_width_m, 0.0)
        best = min(best, float(np.min(np.hypot(dx, dy))))
    return best


def body_outline(poses: np.ndarray, vehicle: VehicleGeometry, spacing_m: float = 0.05) -> np.ndarray:
    """Points round the vehicle's rectangle at every pose (M x 2), corners included."""
    x0, x1, w = -vehicle.rear_overhang_m, vehicle.front_m, vehicle.half_width_m
    corners = np.array([[x0, -w], [x1, -w], [x1, w], [x0, w], [x0, -w]])
    outline = densified(corners, spacing_m)
    cos, sin = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    east = poses[:, 0:1] + outline[None, :, 0] * cos - outline[None, :, 1] * sin
    north = poses[:, 1:2] + outline[None, :, 0] * sin + outline[None, :, 1] * cos
    return np.column_stack([east.ravel(), north.ravel()])
