"""A horizontal lidar's mount, its scan specification and one sweep of returns.

A SICK LMS-291-like scanner sweeps a horizontal plane at its mount height: 361 rays 0.5 deg apart
over 180 deg, 75 sweeps a second, returns up to 80 m with ~1 cm range noise. What it delivers is
a Scan: ranges along known bearings; cluster.py makes obstacle descriptors of them. In
simulation the ranges are ray-cast (modules/sim/lidar/raycast.py).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from brain.pose import Pose


@dataclass(frozen=True)
class Mount:
    """Where a lidar sits in the vehicle frame (x forward, y left, z up from the rear axle on the
    ground) and which way its boresight points (``yaw_rad`` counter-clockwise from x)."""

    x_m: float
    y_m: float
    z_m: float
    yaw_rad: float = 0.0

    def to_vehicle(self, points: np.ndarray) -> np.ndarray:
        """Sensor-frame (n, 2) points to vehicle-frame (n, 2) points."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        x, y = points[:, 0], points[:, 1]
        return np.column_stack((self.x_m + c * x - s * y, self.y_m + s * x + c * y))


@dataclass(frozen=True)
class ScanSpec:
    """What one scanner measures: field of view, angular step, range limit and noise."""

    fov_rad: float = math.pi
    resolution_rad: float = math.radians(0.5)
    scan_rate_hz: float = 75.0
    max_range_m: float = 80.0
    range_noise_std_m: float = 0.01

    @property
    def rays(self) -> int:
        """Rays per sweep, both edges of the field of view included (361 for a SICK)."""
        return round(self.fov_rad / self.resolution_rad) + 1

    def bearings_rad(self) -> np.ndarray:
        """Ray bearings in the sensor frame, right to left (SICK order), centred on the boresight
        (one read-only array per spec: every scan shares it)."""
        return _bearings(self.fov_rad, self.rays)


@functools.lru_cache(maxsize=16)
def _bearings(fov_rad: float, rays: int) -> np.ndarray:
    bearings = np.linspace(-fov_rad / 2, fov_rad / 2, rays)
    bearings.flags.writeable = False
    return bearings


# RASCAL's two horizontal SICKs sit at the front corners, each turned outward so that together
# they see around the corners as well as ahead.
HORIZONTAL_MOUNTS: dict[str, Mount] = {
    "lidar_h_left": Mount(x_m=1.8, y_m=0.4, z_m=0.7, yaw_rad=math.radians(15.0)),
    "lidar_h_right": Mount(x_m=1.8, y_m=-0.4, z_m=0.7, yaw_rad=math.radians(-15.0)),
}


@dataclass(frozen=True)
class Scan:
    """One sweep: ``ranges_m[i]`` along ``bearings_rad[i]`` (sensor frame), inf where no return."""

    mount: Mount
    spec: ScanSpec
    bearings_rad: np.ndarray
    ranges_m: np.ndarray

    @functools.cached_property
    def returns(self) -> np.ndarray:
        """Indices of the rays with a return (range noise never takes one away)."""
        return np.flatnonzero(np.isfinite(self.ranges_m))

    def points_sensor(self) -> tuple[np.ndarray, np.ndarray]:
        """(indices of the rays with a return, their (n, 2) points in the sensor frame)."""
        index = self.returns
        r, b = self.ranges_m[index], self.bearings_rad[index]
        return index, np.column_stack((r * np.cos(b), r * np.sin(b)))


def sensor_pose(pose: Pose, mount: Mount) -> tuple[np.ndarray, float]:
    """The sensor's ENU position and boresight yaw when the vehicle is at ``pose``."""
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    origin = np.array((pose.east_m + c * mount.x_m - s * mount.y_m, pose.north_m + s * mount.x_m + c * mount.y_m))
    return origin, pose.yaw_rad + mount.yaw_rad
