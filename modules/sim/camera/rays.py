"""Per-rig pixel rays, computed once: everything about flat ground that does not depend on the pose.

Each pixel's ray is expressed in the VEHICLE frame with a camera-frame z component of 1, so the
ray parameter of a hit *is* its depth along the optical axis and its disparity is f*B/t. Both
rectified cameras share these directions; only the centres differ (by the baseline along y).
With no roll, flat ground at a given depth fills whole image rows, so the flat-ground depth and
the texture level of detail are functions of the row alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from modules.esvs.geometry import StereoRig

Array = NDArray[np.float64]


@dataclass(frozen=True)
class RigRays:
    rig: StereoRig
    far_m: float
    direction: Array  # (H, W, 3) vehicle-frame ray directions, camera z = 1
    flat_depth: NDArray[np.float32]  # (H, W) depth of the flat-ground hit; inf where none within far_m
    flat_forward: Array  # (H, W) vehicle x of that hit (same for both cameras)
    flat_left: Array  # (H, W) vehicle y of that hit seen from the LEFT camera (right: minus the baseline)
    row_depth: Array  # (H,) flat-ground depth of each row (inf above the ground)
    first_ground_row: int  # top row with any flat-ground hit within far_m
    elevation_rad: Array  # (H, W) ray elevation above the horizontal (sky shading)
    # float32 copies of the flat-ground hits from first_ground_row down, per camera: texture
    # lookups run on these (single precision keeps a millimetre within a kilometre).
    ground_forward: NDArray[np.float32]
    ground_left_of: tuple[NDArray[np.float32], NDArray[np.float32]]  # (left camera, right camera)

    def camera_centre(self, right: bool) -> Array:
        rig = self.rig
        return rig.right_camera_position if right else rig.left_camera_position

    def ground_left(self, right: bool) -> NDArray[np.float32]:
        """Vehicle y of flat-ground hits from one camera (rows from first_ground_row down)."""
        return self.ground_left_of[int(right)]


@lru_cache(maxsize=8)
def rig_rays(rig: StereoRig, far_m: float) -> RigRays:
    """The rays of ``rig`` (cached per rig: a few MB, built in ~20 ms)."""
    f = rig.focal_px
    cols = (np.arange(rig.width_px) - rig.cx_px) / f
    rows = (np.arange(rig.height_px) - rig.cy_px) / f
    camera = np.empty((rig.height_px, rig.width_px, 3))
    camera[..., 0] = cols[None, :]
    camera[..., 1] = rows[:, None]
    camera[..., 2] = 1.0
    direction = camera @ rig.camera_to_vehicle_rotation.T
    height = rig.mount_height_m
    dz = direction[..., 2]
    with np.errstate(divide="ignore"):
        depth = np.where(dz < 0.0, height / -np.where(dz < 0.0, dz, -1.0), np.inf)
    depth[depth > far_m] = np.inf
    ground = np.isfinite(depth)
    forward = np.where(ground, rig.mount_forward_m + depth * direction[..., 0], np.nan)
    left = np.where(ground, rig.baseline_m / 2 + depth * direction[..., 1], np.nan)
    row_depth = depth[:, rig.width_px // 2].copy()
    ground_rows = np.flatnonzero(ground.any(axis=1))
    first = int(ground_rows[0]) if ground_rows.size else rig.height_px
    elevation = np.arctan2(dz, np.hypot(direction[..., 0], direction[..., 1]))
    depth = depth.astype(np.float32)  # what a render's depth buffer starts from
    ground_forward = forward[first:].astype(np.float32)
    ground_left = (left[first:].astype(np.float32), (left[first:] - rig.baseline_m).astype(np.float32))
    arrays = (direction, depth, forward, left, row_depth, elevation, ground_forward, *ground_left)
    for array in arrays:
        array.flags.writeable = False
    return RigRays(
        rig, far_m, direction, depth, forward, left, row_depth, first, elevation, ground_forward, ground_left
    )
