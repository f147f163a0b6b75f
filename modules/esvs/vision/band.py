"""The image rows the real-time pipeline looks at, and their pixels in 3D.

RASCAL's ESVS covers ground 10-35 m ahead of the cameras (section III). Only the rows showing that
ground, and obstacles standing on it up to a height, are matched: at 656 px wide this cuts the
matching cost to about 40 % of the full frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from modules.esvs.geometry import StereoRig
from modules.esvs.vision.disparity import MatcherParams, compute_disparity


@dataclass(frozen=True)
class BandParams:
    near_m: float = 10.0  # ground range covered, ahead of the cameras
    far_m: float = 35.0
    obstacle_height_m: float = 2.0  # obstacles up to this tall fit in the band from near_m outwards
    margin_px: int = 4  # extra rows above and below: the matcher's block overlaps the edges

    def __post_init__(self) -> None:
        if not 0 < self.near_m < self.far_m:
            raise ValueError(f"need 0 < near_m < far_m, got {self.near_m}, {self.far_m}")
        if self.obstacle_height_m < 0 or self.margin_px < 0:
            raise ValueError("obstacle_height_m and margin_px must not be negative")


@dataclass(frozen=True)
class Band:
    top: int  # first row
    bottom: int  # one past the last row

    @property
    def rows(self) -> int:
        return self.bottom - self.top


def band_rows(rig: StereoRig, params: BandParams) -> Band:
    """Rows from the top of an ``obstacle_height_m`` obstacle at the nearest range down to the
    ground at the nearest range (the near top is the highest image point of all: a given height
    climbs in the image as it comes closer), clipped to the image."""
    forward = rig.mount_forward_m
    _, ground_near, _ = rig.project(np.array([forward + params.near_m, 0.0, 0.0]))
    tops = []
    for distance in (params.near_m, params.far_m):
        _, row, _ = rig.project(np.array([forward + distance, 0.0, params.obstacle_height_m]))
        tops.append(float(row))
    _, ground_far, _ = rig.project(np.array([forward + params.far_m, 0.0, 0.0]))
    top = math.floor(min(*tops, float(ground_far))) - params.margin_px
    bottom = math.ceil(float(ground_near)) + 1 + params.margin_px
    return Band(max(0, top), min(rig.height_px, bottom))


def band_disparity(left: np.ndarray, right: np.ndarray, band: Band, params: MatcherParams) -> np.ndarray:
    """Disparity of the band's rows of a whole pair, matched with the rows the matcher leaves
    without a match at the edges of its input added above and below, where the image has them."""
    pad = params.border_rows
    top, bottom = max(0, band.top - pad), min(left.shape[0], band.bottom + pad)
    disparity = compute_disparity(left[top:bottom], right[top:bottom], params)
    return disparity[band.top - top : band.bottom - top]


@lru_cache(maxsize=16)
def band_to_vehicle(rig: StereoRig, top: int) -> np.ndarray:
    """4x4 matrix taking (column, row in the band, disparity, 1) to homogeneous VEHICLE points:
    the rig's Q matrix, shifted to the band's first row, followed by camera_to_vehicle."""
    shift = np.eye(4)
    shift[1, 3] = top  # band row -> image row
    to_vehicle = np.eye(4)
    to_vehicle[:3, :3] = rig.camera_to_vehicle_rotation
    to_vehicle[:3, 3] = rig.left_camera_position
    return to_vehicle @ rig.q_matrix @ shift


@lru_cache(maxsize=16)
def band_rays(rig: StereoRig, top: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``band_to_vehicle`` solved ahead, its homogeneous coordinate being disparity / baseline alone
    (rectified, one cx): VEHICLE coordinate i of the pixel at (column u, band row v) is
    (per_column[i, u] + rows[i, 0] * v + rows[i, 1]) / disparity + offset[i]. Separable, so no
    per-pixel table has to come back into the cache each frame."""
    matrix = band_to_vehicle(rig, top)
    scale = matrix[3, 2]
    if np.any(matrix[3, [0, 1, 3]]) or scale == 0:
        raise ValueError("the rig's Q matrix must make the homogeneous coordinate proportional to disparity")
    per_column = np.outer(matrix[:3, 0], np.arange(rig.width_px)) / scale
    rows = matrix[:3, [1, 3]] / scale
    return per_column.astype(np.float32), rows, matrix[:3, 2] / scale


def vehicle_points(disparity: np.ndarray, rig: StereoRig, top: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """VEHICLE x, y, z (float32 planes, NaN where the disparity is) of every band pixel."""
    per_column, rows, offset = band_rays(rig, top)
    band_row = np.arange(disparity.shape[0])[:, None]
    inverse = np.reciprocal(disparity, dtype=np.float32)
    planes = []
    for i in range(3):
        plane = per_column[i] + (rows[i, 0] * band_row + rows[i, 1]).astype(np.float32)
        plane *= inverse
        plane += np.float32(offset[i])
        planes.append(plane)
    x, y, z = planes
    return x, y, z


@lru_cache(maxsize=16)
def ground_lookup(rig: StereoRig, top: int, bottom: int) -> tuple[np.ndarray, np.ndarray]:
    """VEHICLE x, y where each band pixel's ray meets flat ground (z = 0); NaN above the horizon."""
    rows, cols = np.mgrid[top:bottom, 0 : rig.width_px].astype(np.float64)
    rays = np.stack([(cols - rig.cx_px) / rig.focal_px, (rows - rig.cy_px) / rig.focal_px, np.ones_like(cols)], -1)
    rays = rays @ rig.camera_to_vehicle_rotation.T
    origin = rig.left_camera_position
    down = rays[..., 2] < -1e-9
    t = np.where(down, -origin[2] / np.where(down, rays[..., 2], -1.0), np.nan)
    return (origin[0] + t * rays[..., 0]).astype(np.float32), (origin[1] + t * rays[..., 1]).astype(np.float32)
