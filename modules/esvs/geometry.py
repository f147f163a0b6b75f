"""The ESVS stereo rig: RASCAL's camera geometry and the transforms between its frames.

Two cameras 656 x 490 px, 0.30 m apart, 1.5 m above the ground, horizontal field of view
41.26 deg, pitched down so the ground from 10 m to 35 m ahead is in view (RASCAL section III).
Images are rectified: both cameras share intrinsics and orientation, the right one displaced by
the baseline along the left camera's x axis, so a ground point at depth Z has disparity f*B/Z.

Frames: VEHICLE is x forward, y left, z up from the rear-axle centre on the ground (as every
message); CAMERA is the left camera's optical frame, x right, y down, z along the optical axis.
The renderer (simulated cameras) and the vision pipeline both use this one definition.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class StereoRig:
    width_px: int = 656
    height_px: int = 490
    baseline_m: float = 0.30
    hfov_deg: float = 41.26
    mount_height_m: float = 1.5
    mount_forward_m: float = 1.6  # ahead of the rear axle, above the windscreen
    pitch_down_deg: float = 6.0  # puts 10 m at row ~284 and 35 m at row ~191 of 490

    @cached_property
    def focal_px(self) -> float:
        return (self.width_px / 2) / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def cx_px(self) -> float:
        return (self.width_px - 1) / 2

    @property
    def cy_px(self) -> float:
        return (self.height_px - 1) / 2

    @cached_property
    def camera_matrix(self) -> FloatArray:
        """The 3x3 intrinsic matrix K shared by both rectified cameras."""
        f = self.focal_px
        return np.array([[f, 0.0, self.cx_px], [0.0, f, self.cy_px], [0.0, 0.0, 1.0]])

    @cached_property
    def q_matrix(self) -> FloatArray:
        """OpenCV's 4x4 reprojection matrix (cv2.reprojectImageTo3D) for this rectified pair:
        (u, v, disparity, 1) -> homogeneous CAMERA-frame point."""
        f, b = self.focal_px, self.baseline_m
        return np.array(
            [[1.0, 0.0, 0.0, -self.cx_px], [0.0, 1.0, 0.0, -self.cy_px], [0.0, 0.0, 0.0, f], [0.0, 0.0, 1.0 / b, 0.0]]
        )

    @cached_property
    def camera_to_vehicle_rotation(self) -> FloatArray:
        """Columns are the CAMERA axes (x right, y down, z optical) expressed in VEHICLE axes."""
        p = math.radians(self.pitch_down_deg)
        x_cam = [0.0, -1.0, 0.0]  # right = -y_vehicle
        y_cam = [-math.sin(p), 0.0, -math.cos(p)]  # down, tilted back by the pitch
        z_cam = [math.cos(p), 0.0, -math.sin(p)]  # forward, tilted down by the pitch
        return np.array([x_cam, y_cam, z_cam]).T

    @property
    def left_camera_position(self) -> FloatArray:
        """Left camera centre in VEHICLE coordinates."""
        return np.array([self.mount_forward_m, self.baseline_m / 2, self.mount_height_m])

    @property
    def right_camera_position(self) -> FloatArray:
        return np.array([self.mount_forward_m, -self.baseline_m / 2, self.mount_height_m])

    def camera_to_vehicle(self, points_camera: FloatArray) -> FloatArray:
        """(..., 3) left-CAMERA points to VEHICLE points."""
        return points_camera @ self.camera_to_vehicle_rotation.T + self.left_camera_position

    def vehicle_to_camera(self, points_vehicle: FloatArray, right: bool = False) -> FloatArray:
        """(..., 3) VEHICLE points to the left (or right) camera's optical frame."""
        centre = self.right_camera_position if right else self.left_camera_position
        return (points_vehicle - centre) @ self.camera_to_vehicle_rotation

    def project(self, points_vehicle: FloatArray, right: bool = False) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Pixel column, row and depth (along the optical axis) of VEHICLE points; points
        behind the camera get depth <= 0 and meaningless pixels."""
        cam = self.vehicle_to_camera(np.asarray(points_vehicle, dtype=float), right)
        depth = cam[..., 2]
        safe = np.where(depth > 1e-9, depth, 1e-9)
        u = self.focal_px * cam[..., 0] / safe + self.cx_px
        v = self.focal_px * cam[..., 1] / safe + self.cy_px
        return u, v, depth

    def disparity_px(self, depth_m: FloatArray) -> FloatArray:
        return self.focal_px * self.baseline_m / np.asarray(depth_m, dtype=float)

    def ground_row(self, forward_m: float) -> float:
        """Image row where flat ground ``forward_m`` ahead of the vehicle origin appears."""
        _, v, _ = self.project(np.array([forward_m, 0.0, 0.0]))
        return float(v)

    def horizon_row(self) -> float:
        """Image row of the horizon (points at infinity on level ground)."""
        return self.cy_px - self.focal_px * math.tan(math.radians(self.pitch_down_deg))


RASCAL_RIG = StereoRig()
