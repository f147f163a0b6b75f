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

Outside the window nothing is known: no lethal cells, no cost. A window cut out of a larger map
(`GridWindow.crop`) can name its cut edges as ``walls``: what lies beyond them was not looked at,
so they count as a lethal ring just outside the window and nothing may pass near them (or beyond).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from brain.grid import GridWindow, Sides

FloatArray = NDArray[np.float64]
Box = tuple[float, float, float, float]  # min east, min north, max east, max north
Boxes = tuple[Box, ...]
NO_WALLS = Sides()


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
        walls: Sides = NO_WALLS,
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
        self.any_lethal = bool(self.lethal.any()) or any(walls)
        res = window.resolution_m
        # A ring of cells around the window (free, or lethal along walls), so the field is exact one
        # cell beyond it too.
        self.clearance_m = _distance_to(_ringed(self.lethal, walls), res)
        self._lethal_boxes = _marked_boxes(self.lethal, window, walls)
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
            self._caution_m = _distance_to(_ringed(self.lethal | likely, walls), res)
            self._caution_boxes = _marked_boxes(self.lethal | likely, window, walls)
        else:
            self._caution_m, self._caution_boxes = self.clearance_m, self._lethal_boxes

    def clearance_bound(self, east_m: ArrayLike, north_m: ArrayLike) -> FloatArray:
        """A lower bound on each point's distance to the nearest lethal cell centre.

        The distance function is 1-Lipschitz, so each of the four cell centres around a point gives
        ``field(q) - |p - q|``; the best of them is exact at centres and loses at most a
        cell diagonal between them. Beyond the padded ring, the distance to a box round all lethal
        cell centres (and one along each wall) bounds it.
        """
        if not self.any_lethal:
            return np.full(np.broadcast(np.asarray(east_m), np.asarray(north_m)).shape, np.inf)
        return _bound(self.clearance_m, self.window, self._lethal_boxes, east_m, north_m)

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
        return _bound(self._caution_m, self.window, self._caution_boxes, east_m, north_m)


def _bound(
    field_m: NDArray[np.float32], w: GridWindow, marked: Boxes, east_m: ArrayLike, north_m: ArrayLike
) -> FloatArray:
    """`HazardField.clearance_bound` on a distance field padded by one ring of cells around ``w``,
    whose marked cell centres lie in the boxes ``marked``."""
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
    beyond = ~block
    if beyond.any():  # most queries lie wholly inside: no box distances for them
        best[beyond] = _distance_to_boxes(marked, east[beyond], north[beyond])
    return best


def _marked_boxes(mask: NDArray[np.bool_], w: GridWindow, walls: Sides) -> Boxes:
    """Boxes holding every marked cell centre: one round the window's marked cells, and for each
    wall all that lies past its ring (the ring's centres half a cell outside the window): nothing
    past a wall is clear."""
    res, half, inf = w.resolution_m, w.resolution_m / 2.0, math.inf
    west, south = w.origin_east_m - half, w.origin_north_m - half
    east, north = w.origin_east_m + w.cols * res + half, w.origin_north_m + w.rows * res + half
    boxes: list[Box] = []
    if mask.any():
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        low_e, low_n = w.centre_of(rows[0], cols[0])
        high_e, high_n = w.centre_of(rows[-1], cols[-1])
        boxes.append((float(low_e), float(low_n), float(high_e), float(high_n)))
    past = ((west, -inf, east, south), (west, north, east, inf), (-inf, south, west, north), (east, south, inf, north))
    boxes.extend(box for walled, box in zip(walls, past, strict=True) if walled)
    return tuple(boxes)


def _distance_to_boxes(boxes: Boxes, east: FloatArray, north: FloatArray) -> FloatArray:
    """Distance from points to the nearest of the boxes (inf when there is none)."""
    distance = np.full(east.shape, np.inf)
    for low_e, low_n, high_e, high_n in boxes:
        de = np.maximum(np.maximum(low_e - east, east - high_e), 0.0)
        dn = np.maximum(np.maximum(low_n - north, north - high_n), 0.0)
        np.minimum(distance, np.hypot(de, dn), out=distance)
    return distance


def _ringed(mask: NDArray[np.bool_], walls: Sides) -> NDArray[np.bool_]:
    """``mask`` padded by one ring of cells: marked along walls, clear elsewhere."""
    padded = np.pad(mask, 1, constant_values=False)
    padded[0, :] |= walls.south
    padded[-1, :] |= walls.north
    padded[:, 0] |= walls.west
    padded[:, -1] |= walls.east
    return padded


def _distance_to(mask: NDArray[np.bool_], resolution_m: float) -> NDArray[np.float32]:
    """Metres from every cell centre to the nearest True cell centre (inf when there is none)."""
    if not mask.any():
        return np.full(mask.shape, np.inf, dtype=np.float32)
    free = np.ascontiguousarray(~mask, dtype=np.uint8)
    return cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * np.float32(resolution_m)
