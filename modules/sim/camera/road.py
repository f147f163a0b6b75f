"""Road edges on the ground: the scenario's lane borders drawn, per frame, into a bird's-eye
coverage image in the vehicle frame, which ground pixels then look up by where their ray lands.

A graded desert road is edged by windrows of loose, lighter soil; each lane border becomes such a
band, ``width_m`` wide. Drawing the few hundred metres of polyline near the vehicle costs far less
than measuring every ground pixel's distance to every segment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from modules.sim.camera.textures import remap_wrapped
from modules.sim.world import LaneBorderLine

_SHIFT = 3  # cv2 drawing with 1/8-pixel vertex precision
_MARGIN_M = 5.0


@dataclass(frozen=True)
class RoadDecal:
    """Coverage (0-255) of road-edge bands; pixel (row, col) is the vehicle-frame ground point
    (x0_m + col * resolution_m, y0_m - row * resolution_m). It spans only the bands' bounding
    box, so a road running ahead makes a narrow image, cheap to clear and to read."""

    image: NDArray[np.uint8]
    resolution_m: float
    x0_m: float
    y0_m: float

    def coverage(self, forward_m: NDArray[np.floating], left_m: NDArray[np.floating]) -> NDArray[np.uint8]:
        """Coverage 0-255 of a road-edge band at vehicle-frame ground points (any shape)."""
        scale = 1.0 / self.resolution_m
        return self.coverage_px(
            np.asarray(forward_m * scale, dtype=np.float32), np.asarray(left_m * scale, dtype=np.float32)
        )

    def coverage_px(self, forward_px: NDArray[np.float32], left_px: NDArray[np.float32]) -> NDArray[np.uint8]:
        """The same at points given in decal pixels (forward_m / resolution_m, left_m /
        resolution_m): for points fixed in the vehicle frame, such as a camera's view of flat
        ground, the caller computes those once and each frame only shifts them."""
        # cv2 draws a vertex at integer coordinates on that pixel's centre: no half-pixel shift.
        cols = forward_px - np.float32(self.x0_m / self.resolution_m)
        rows = np.float32(self.y0_m / self.resolution_m) - left_px
        return remap_wrapped(self.image, cols, rows, cv2.BORDER_CONSTANT)


def lane_arrays(lines: tuple[LaneBorderLine, ...]) -> tuple[NDArray[np.float64], ...]:
    """The lane borders as (n, 2) ENU arrays, built once per world."""
    return tuple(np.array(line.points_m, dtype=float).reshape(-1, 2) for line in lines if len(line.points_m) >= 2)


def draw_decal(
    lines: tuple[NDArray[np.float64], ...],
    east: float,
    north: float,
    yaw: float,
    range_m: float,
    half_width_m: float,
    resolution_m: float,
    band_width_m: float,
) -> RoadDecal | None:
    """The road-edge coverage for a vehicle at (east, north, yaw), over x in [0, range_m] and
    |y| <= half_width_m of the vehicle frame; None when no lane border passes there."""
    c, s = math.cos(yaw), math.sin(yaw)
    runs = []
    for points in lines:
        dx, dy = points[:, 0] - east, points[:, 1] - north
        x, y = c * dx + s * dy, -s * dx + c * dy
        keep = (x > -_MARGIN_M) & (x < range_m + _MARGIN_M) & (np.abs(y) < half_width_m + _MARGIN_M)
        index = np.flatnonzero(keep)
        # Split where the kept points are not consecutive: a line may leave the window and return.
        for run in np.split(index, np.flatnonzero(np.diff(index) > 1) + 1):
            if run.size >= 2:
                runs.append(np.column_stack((x[run], y[run])))
    if not runs:
        return None
    every = np.concatenate(runs)
    pad = band_width_m + 2 * resolution_m
    x0 = max(float(every[:, 0].min()) - pad, 0.0)
    x1 = min(float(every[:, 0].max()) + pad, range_m)
    y0 = min(float(every[:, 1].max()) + pad, half_width_m)
    y1 = max(float(every[:, 1].min()) - pad, -half_width_m)
    if x1 <= x0 or y0 <= y1:
        return None
    image = np.zeros((math.ceil((y0 - y1) / resolution_m) + 1, math.ceil((x1 - x0) / resolution_m) + 1), np.uint8)
    scale = (1 << _SHIFT) / resolution_m
    pixels = [np.rint(np.column_stack(((r[:, 0] - x0) * scale, (y0 - r[:, 1]) * scale))).astype(np.int32) for r in runs]
    thickness = max(1, round(band_width_m / resolution_m))
    cv2.polylines(image, pixels, False, 255, thickness, cv2.LINE_AA, _SHIFT)
    return RoadDecal(image, resolution_m, x0, y0)
