"""One planning cycle's view of the fused map: lethal cells, clearances and footprint costs.

Fusion hands over a `GridWindow` with two float arrays of its shape: ``hazard_probability``
(0..1) and ``cost`` (>= 0, ``inf`` for lethal cells). From them this builds, once per cycle:

* the clearance field: the exact Euclidean distance from every cell centre to the nearest lethal
  cell centre (OpenCV's exact distance transform), padded by one ring of cells outside the window;
* the footprint-mean cost: the capped cost averaged over a square as wide as the vehicle's swept
  tube (a box filter, i.e. an integral image), Kratos' footprint-summed cost divided by its area
  so weights do not depend on the resolution;
* the same clearance to "caution" cells (lethal, or hazard probability at or above a threshold),
  which only the speed profile uses: exact too, since it decides how fast the vehicle passes
  things and a coarser grid's pessimism (half a metre at 0.4 m cells) slows it by metres per second.

Outside the window nothing is known: no lethal cells, no cost.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from brain.grid import GridWindow

FloatArray = NDArray[np.float64]


class HazardField:
    """Derived layers of one map; queries take ENU points (arrays of any matching shape)."""

    def __init__(
        self,
        window: GridWindow,
        hazard_probability: ArrayLike,
        cost: ArrayLike,
        footprint_m: float,
        cost_cap: float,
        caution_probability: float,
    ) -> None:
        hazard = np.asarray(hazard_probability)
        cost_array = np.asarray(cost)
        for name, array in (("hazard_probability", hazard), ("cost", cost_array)):
            if array.shape != window.shape:
                raise ValueError(f"{name} has shape {array.shape}, the grid window {window.shape}")
            if not np.issubdtype(array.dtype, np.floating):
                raise ValueError(f"{name} must be a float array, got {array.dtype}")
        if np.isnan(hazard).any() or hazard.min() < 0.0 or hazard.max() > 1.0:
            raise ValueError("hazard_probability must lie in [0, 1] (no NaN)")
        if np.isnan(cost_array).any() or cost_array.min() < 0.0:
            raise ValueError("cost must be >= 0 (inf for lethal cells, no NaN)")
        if not (footprint_m > 0 and cost_cap > 0 and 0 < caution_probability <= 1):
            raise ValueError("footprint, cost cap and caution probability must be positive")
        self.window = window
        self.lethal = np.isposinf(cost_array)
        self.any_lethal = bool(self.lethal.any())
        res = window.resolution_m
        # Ring of free cells around the window, so the field is exact one cell beyond it too.
        padded = np.pad(self.lethal, 1, constant_values=False)
        self.clearance_m = _distance_to(padded, res)
        capped = np.minimum(cost_array, cost_cap).astype(np.float32)
        side = 2 * round(footprint_m / res) + 1
        self.footprint_cost = cv2.boxFilter(
            capped, ddepth=-1, ksize=(side, side), normalize=True, borderType=cv2.BORDER_CONSTANT
        )
        # Caution cells are the lethal ones plus the likely hazards; where there are no others
        # (most of a drive), their distance field is the clearance field: one transform, not two.
        likely = hazard >= caution_probability
        self.any_caution = self.any_lethal or bool(likely.any())
        if (likely & ~self.lethal).any():
            self._caution_m = _distance_to(np.pad(self.lethal | likely, 1, constant_values=False), res)
        else:
            self._caution_m = self.clearance_m

    def clearance_bound(self, east_m: ArrayLike, north_m: ArrayLike) -> FloatArray:
        """A lower bound on each point's distance to the nearest lethal cell centre.

        The distance function is 1-Lipschitz, so each of the four cell centres around a point gives
        ``field(q) - |p - q|``; the best of them is exact at centres and loses at most a
        cell diagonal between them. Beyond the padded ring, the distance to the box of all cell
        centres bounds it.
        """
        if not self.any_lethal:
            return np.full(np.broadcast(np.asarray(east_m), np.asarray(north_m)).shape, np.inf)
        return _bound(self.clearance_m, self.window, east_m, north_m)

    def cost_at(self, east_m: ArrayLike, north_m: ArrayLike) -> FloatArray:
        """Footprint-mean cost of the cells containing the points (0 outside the window)."""
        row, col = self.window.cell_of(east_m, north_m)
        inside = self.window.inside(row, col)
        value = self.footprint_cost[np.clip(row, 0, self.window.rows - 1), np.clip(col, 0, self.window.cols - 1)]
        return np.where(inside, value, 0.0)

    def caution_clearance(self, east_m: ArrayLike, north_m: ArrayLike) -> FloatArray:
        """A lower bound on the distance to the nearest caution cell centre (inf when there is none),
        as `clearance_bound` is to lethal ones."""
        if not self.any_caution:
            return np.full(np.broadcast(np.asarray(east_m), np.asarray(north_m)).shape, np.inf)
        return _bound(self._caution_m, self.window, east_m, north_m)


def _bound(field_m: NDArray[np.float32], w: GridWindow, east_m: ArrayLike, north_m: ArrayLike) -> FloatArray:
    """`HazardField.clearance_bound` on a distance field padded by one ring of cells around ``w``."""
    east, north = np.broadcast_arrays(np.asarray(east_m, dtype=float), np.asarray(north_m, dtype=float))
    res = w.resolution_m
    # Fractional index into the padded field, whose cell (1, 1) is the window's cell (0, 0).
    u = (east - w.origin_east_m) / res + 0.5
    v = (north - w.origin_north_m) / res + 0.5
    col = np.floor(u)
    row = np.floor(v)
    fu, fv = u - col, v - row
    rows, cols = field_m.shape
    block = (row >= 0) & (row < rows - 1) & (col >= 0) & (col < cols - 1)  # all four centres in the field
    flat = np.where(block, row * cols + col, 0).astype(np.intp)
    field = field_m.ravel()
    best = field[flat] - res * np.hypot(fu, fv)
    np.maximum(best, field[flat + 1] - res * np.hypot(1.0 - fu, fv), out=best)
    np.maximum(best, field[flat + cols] - res * np.hypot(fu, 1.0 - fv), out=best)
    np.maximum(best, field[flat + cols + 1] - res * np.hypot(1.0 - fu, 1.0 - fv), out=best)
    outside = _distance_outside(w, east, north)
    return np.where(block, np.maximum(best, outside), outside)


def _distance_outside(window: GridWindow, east: FloatArray, north: FloatArray) -> FloatArray:
    """Distance from points to the box of all cell centres (0 inside it): no cell is nearer."""
    half = window.resolution_m / 2.0
    low_e, low_n = window.origin_east_m + half, window.origin_north_m + half
    high_e = window.origin_east_m + window.cols * window.resolution_m - half
    high_n = window.origin_north_m + window.rows * window.resolution_m - half
    de = np.maximum(np.maximum(low_e - east, east - high_e), 0.0)
    dn = np.maximum(np.maximum(low_n - north, north - high_n), 0.0)
    return np.hypot(de, dn)


def _distance_to(mask: NDArray[np.bool_], resolution_m: float) -> NDArray[np.float32]:
    """Metres from every cell centre to the nearest True cell centre (inf when there is none)."""
    if not mask.any():
        return np.full(mask.shape, np.inf, dtype=np.float32)
    free = np.ascontiguousarray(~mask, dtype=np.uint8)
    return cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * np.float32(resolution_m)
