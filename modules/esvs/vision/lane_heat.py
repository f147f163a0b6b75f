"""Lane-border evidence: Kratos' per-pixel filters fused into a bird's-eye heat map.

The filters, on the left grey image (RASCAL's cameras are monochrome, so Kratos' white/yellow
colour filters become one brightness filter):

* width: a pulse filter. A pixel scores by how much brighter it is than both pixels one
  marking-width to its left and right, where the width in pixels is what ``marking_width_m``
  measures on flat ground at that row's range: a painted line or a bright border strip of that
  width answers, wide bright patches (the same brightness on both sides) and edges do not;
* brightness: the pixel is at least ``min_brightness`` grey levels above its row's mean;
* obstacle: pixels that are obstacle points, or whose stereo point stands above the ground, score
  nothing (a bright car panel is not paint).

The scores are then warped onto flat ground (z = 0 in the vehicle frame) with one homography into
a grid of ``cell_x_m`` x ``cell_y_m`` cells: row i is x = x_min + i * cell_x, column j is
y = y_max - j * cell_y (left at column 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from modules.esvs.geometry import StereoRig


@dataclass(frozen=True)
class HeatParams:
    marking_width_m: float = 0.45  # RASCAL's road edges: windrows of lighter soil (the simulated cameras' too)
    min_contrast: float = 20.0  # grey levels above both sides for a pixel to count at all
    full_contrast: float = 48.0  # ... and for full score
    min_brightness: float = 20.0  # above the row mean
    max_ground_height_m: float = 0.25  # a stereo point higher than this is not on the ground
    x_min_m: float = 11.6  # heat map extent, VEHICLE frame: 10 m ahead of the cameras (1.6 m ahead of the origin)...
    x_max_m: float = 51.6  # ...to 50 m, past the fit range, for the greedy extension
    y_half_width_m: float = 10.0
    cell_x_m: float = 0.5
    cell_y_m: float = 0.1

    def __post_init__(self) -> None:
        if not 0 < self.min_contrast < self.full_contrast:
            raise ValueError("need 0 < min_contrast < full_contrast")
        if not self.x_min_m < self.x_max_m or min(self.cell_x_m, self.cell_y_m, self.marking_width_m) <= 0:
            raise ValueError("need x_min_m < x_max_m and positive cell sizes and marking width")


@dataclass(frozen=True)
class HeatMap:
    heat: np.ndarray  # (x cells, y cells) float32 0..1
    params: HeatParams

    def x_of(self, row: np.ndarray) -> np.ndarray:
        return self.params.x_min_m + row * self.params.cell_x_m

    def y_of(self, column: np.ndarray) -> np.ndarray:
        return self.params.y_half_width_m - column * self.params.cell_y_m

    def column_of(self, y: np.ndarray) -> np.ndarray:
        return (self.params.y_half_width_m - y) / self.params.cell_y_m


def grid_shape(params: HeatParams) -> tuple[int, int]:
    rows = round((params.x_max_m - params.x_min_m) / params.cell_x_m) + 1
    return rows, round(2 * params.y_half_width_m / params.cell_y_m) + 1


@lru_cache(maxsize=16)
def pulse_indices(rig: StereoRig, top: int, bottom: int, marking_width_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Flat band indices of the pixels one marking width left and right of each band pixel (the
    pixel itself where that falls off the image or the row shows no ground)."""
    rows = np.arange(top, bottom)
    # Camera depth of the flat ground seen at each row (inf at and above the horizon).
    tilt = np.radians(rig.pitch_down_deg)
    slope = (rows - rig.cy_px) / rig.focal_px  # ray y / z in the camera
    down = np.sin(tilt) * 1.0 + np.cos(tilt) * slope  # ray's downward component per unit camera z
    with np.errstate(divide="ignore"):
        depth = np.where(down > 1e-9, rig.mount_height_m / np.where(down > 1e-9, down, 1.0), np.inf)
    offset = np.where(np.isfinite(depth), np.ceil(rig.focal_px * marking_width_m / depth) + 1, 0).astype(np.int64)
    width = rig.width_px
    columns = np.arange(width)
    index = (rows - top)[:, None] * width + columns[None, :]
    left = np.where(columns[None, :] - offset[:, None] >= 0, index - offset[:, None], index)
    right = np.where(columns[None, :] + offset[:, None] < width, index + offset[:, None], index)
    return left.ravel(), right.ravel()


@lru_cache(maxsize=16)
def grid_to_band(rig: StereoRig, top: int, params: HeatParams) -> np.ndarray:
    """Homography from heat-map cells (column j, row i) to band pixels (column, row - top)."""
    cell = np.array(
        [[0.0, params.cell_x_m, params.x_min_m], [-params.cell_y_m, 0.0, params.y_half_width_m], [0.0, 0.0, 1.0]]
    )
    rotation_t = rig.camera_to_vehicle_rotation.T
    # Ground point g = (x, y, 0): camera point = R^T (g - c) = R^T[:, :2] (x, y) - R^T c.
    ground_to_camera = np.column_stack([rotation_t[:, 0], rotation_t[:, 1], -rotation_t @ rig.left_camera_position])
    camera = rig.camera_matrix.copy()
    camera[1, 2] -= top
    return camera @ ground_to_camera @ cell


def pixel_scores(
    image: np.ndarray,
    rig: StereoRig,
    top: int,
    params: HeatParams,
    not_ground: np.ndarray | None = None,
) -> np.ndarray:
    """Per-pixel lane score 0..1 on the band ``image`` (grey uint8 rows ``top``...)."""
    left, right = pulse_indices(rig, top, top + image.shape[0], params.marking_width_m)
    flat = image.ravel()
    # Saturating uint8 differences: a pixel darker than a side scores 0 either way.
    contrast = cv2.min(cv2.subtract(flat, flat.take(left)), cv2.subtract(flat, flat.take(right))).reshape(image.shape)
    # Integer pixels: at least mean + min_brightness is at least its ceiling (int16: it may pass 255).
    bright_from = np.ceil(image.mean(axis=1, keepdims=True) + params.min_brightness).astype(np.int16)
    dim = image < bright_from
    contrast[dim if not_ground is None else dim | not_ground] = 0
    return cv2.LUT(contrast, _score_table(params.min_contrast, params.full_contrast))


@lru_cache(maxsize=16)
def _score_table(min_contrast: float, full_contrast: float) -> np.ndarray:
    """float32 score of each uint8 contrast: 0 up to ``min_contrast``, rising to 1 at ``full_contrast``."""
    contrast = np.arange(256, dtype=np.float32)
    return np.clip((contrast - min_contrast) / (full_contrast - min_contrast), 0.0, 1.0)


def heat_map(score: np.ndarray, rig: StereoRig, top: int, params: HeatParams) -> HeatMap:
    """The per-pixel scores warped onto the ground grid."""
    rows, columns = grid_shape(params)
    warped = cv2.warpPerspective(
        score,
        grid_to_band(rig, top, params),
        (columns, rows),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )
    return HeatMap(warped, params)


def off_ground(z: np.ndarray, obstacle_mask: np.ndarray, params: HeatParams) -> np.ndarray:
    """Kratos' obstacle filter: obstacle points and points standing above the ground."""
    return obstacle_mask | (z > params.max_ground_height_m)
