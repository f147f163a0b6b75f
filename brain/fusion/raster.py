"""Geometry to cells: frames, sensor views with shadows, and polygons rasterised onto the window.

Everything a descriptor says is turned into polygons in ENU (an obstacle's footprint, a strip of
ground, the region a sensor saw clear) and filled with ``cv2.fillPoly`` in fixed-point
coordinates. cv2 fills every cell whose centre lies within about half a cell of the polygon,
so rasterising errs on the side of covering: footprints cover at least the cells they touch,
and clear views are cut short by a margin of at least a cell so they never reach what they saw.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray

from brain.fusion.sensors import SensorModel
from brain.grid import GridWindow
from brain.pose import Pose

FloatArray = NDArray[np.float64]

_SHIFT = 8  # fixed-point bits of the vertex coordinates handed to cv2
_SCALE = 1 << _SHIFT
_FAR_CELLS = 1 << 20  # vertices are clamped this far outside the window: fixed point stays in int32


class Frame2D(NamedTuple):
    """A planar rigid frame in ENU: origin and the yaw of its x axis."""

    east_m: float
    north_m: float
    yaw_rad: float

    def to_enu(self, points: FloatArray) -> FloatArray:
        """(..., 2) points in this frame to ENU."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return points @ np.array(((c, s), (-s, c))) + (self.east_m, self.north_m)

    def from_enu(self, points: FloatArray) -> FloatArray:
        """(..., 2) ENU points to this frame."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return (points - (self.east_m, self.north_m)) @ np.array(((c, -s), (s, c)))


def vehicle_frame(pose: Pose) -> Frame2D:
    return Frame2D(pose.east_m, pose.north_m, pose.yaw_rad)


def sensor_frame(pose: Pose, model: SensorModel) -> Frame2D:
    """The sensor's frame in ENU when the vehicle is at ``pose``."""
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    return Frame2D(
        pose.east_m + c * model.x_m - s * model.y_m,
        pose.north_m + s * model.x_m + c * model.y_m,
        pose.yaw_rad + model.yaw_rad,
    )


def rectangles(centres: FloatArray, half_extents: FloatArray, yaw_rad: FloatArray) -> FloatArray:
    """(n, 4, 2) corners of oriented rectangles, counter-clockwise."""
    signs = np.array(((1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0)))
    local = signs[None, :, :] * half_extents[:, None, :]
    c, s = np.cos(yaw_rad)[:, None], np.sin(yaw_rad)[:, None]
    x, y = local[..., 0], local[..., 1]
    return np.stack((centres[:, None, 0] + c * x - s * y, centres[:, None, 1] + s * x + c * y), axis=-1)


class _ViewBins(NamedTuple):
    edges: FloatArray  # (bins + 1,) bearing bin edges across the field of view
    outer: FloatArray  # (2 * bins, 2) unit vectors of the outline's vertices, two per bin
    inner: FloatArray  # the inner edge: the arc at min_range_m, reversed, or the sensor itself


@functools.lru_cache(maxsize=64)
def _view_bins(model: SensorModel, bin_rad: float) -> _ViewBins:
    bins = max(1, math.ceil(model.fov_rad / bin_rad - 1e-9))
    edges = np.linspace(-model.fov_rad / 2, model.fov_rad / 2, bins + 1)
    angles = np.repeat(edges, 2)[1:-1]
    outer = np.column_stack((np.cos(angles), np.sin(angles)))
    if model.min_range_m > 0:
        inner = model.min_range_m * np.column_stack((np.cos(edges[::-1]), np.sin(edges[::-1])))
    else:
        inner = np.zeros((1, 2))
    return _ViewBins(edges, outer, inner)


def view_polygon(
    model: SensorModel, blocker_xy: FloatArray, blocker_radius: FloatArray, bin_rad: float, margin_m: float
) -> FloatArray:
    """(m, 2) sensor-frame polygon of what the sensor saw clear: its view sector, cut short in
    every bearing bin that a reported object (a circle of ``blocker_radius`` + ``margin_m``)
    overlaps, at that object's near edge. Beyond a reported object is its shadow, not clear."""
    table = _view_bins(model, bin_rad)
    edges = table.edges
    free = np.full(len(edges) - 1, model.max_range_m)
    if len(blocker_xy):
        distance = np.hypot(blocker_xy[:, 0], blocker_xy[:, 1])
        reach = blocker_radius + margin_m
        near = np.maximum(distance - reach, 0.0)
        blocking = near < model.max_range_m
        if blocking.any():
            distance, reach, near = distance[blocking], reach[blocking], near[blocking]
            outside = distance > reach
            half = np.where(outside, np.arcsin(np.clip(reach / np.maximum(distance, 1e-9), 0.0, 1.0)), math.pi)
            bearing = np.arctan2(blocker_xy[blocking, 1], blocker_xy[blocking, 0])
            low, high = edges[:-1][None, :], edges[1:][None, :]
            hits = ~outside[:, None] | ((high > (bearing - half)[:, None]) & (low < (bearing + half)[:, None]))
            if model.fov_rad > math.pi:  # a wide view may meet an interval that straddles the +-pi cut
                for turn in (-2 * math.pi, 2 * math.pi):
                    hits |= (high > (bearing - half + turn)[:, None]) & (low < (bearing + half + turn)[:, None])
            free = np.minimum(free, np.where(hits, near[:, None], np.inf).min(axis=0))
    free = np.maximum(free, model.min_range_m)
    # Two vertices per bin (its edges at its free range) draw the shadows as steps.
    return np.concatenate((table.outer * np.repeat(free, 2)[:, None], table.inner))


def strips(x_from_m: FloatArray, x_to_m: FloatArray, y_m: float, half_width_m: float) -> FloatArray:
    """(n, 4, 2) corners of strips x_from..x_to at y +- half_width (vehicle frame)."""
    x_from, x_to = np.asarray(x_from_m, dtype=float), np.asarray(x_to_m, dtype=float)
    return boxes(x_from, x_to, np.full(x_from.shape, y_m - half_width_m), np.full(x_from.shape, y_m + half_width_m))


def boxes(x_from_m: FloatArray, x_to_m: FloatArray, y_from_m: FloatArray, y_to_m: FloatArray) -> FloatArray:
    """(n, 4, 2) corners of axis-aligned boxes x_from..x_to by y_from..y_to (vehicle frame)."""
    corners = ((x_from_m, y_from_m), (x_to_m, y_from_m), (x_to_m, y_to_m), (x_from_m, y_to_m))
    return np.stack([np.column_stack(corner) for corner in corners], axis=1).reshape(-1, 4, 2)


def slanted_boxes(
    x_from_m: FloatArray,
    x_to_m: FloatArray,
    y_from_m: FloatArray,
    y_to_m: FloatArray,
    back_m: float,
    ahead_m: float,
    slope: FloatArray,
) -> FloatArray:
    """(n, 8, 2) outlines of boxes (vehicle frame) reaching ``back_m`` behind and ``ahead_m``
    beyond their x ends along their beams: sideways by ``slope`` (dy/dx) per metre, the way the
    beam that saw the box moves across the ground. Extended square instead, a box seen 30 deg off
    to the side would reach 0.35 m beside what the beam crossed for every 0.6 m of depth."""
    back_x, ahead_x = x_from_m - back_m, x_to_m + ahead_m
    back_y, ahead_y = -back_m * slope, ahead_m * slope
    corners = (
        (back_x, y_from_m + back_y),
        (x_from_m, y_from_m),
        (x_to_m, y_from_m),
        (ahead_x, y_from_m + ahead_y),
        (ahead_x, y_to_m + ahead_y),
        (x_to_m, y_to_m),
        (x_from_m, y_to_m),
        (back_x, y_to_m + back_y),
    )
    return np.stack([np.column_stack(corner) for corner in corners], axis=1).reshape(-1, 8, 2)


class Stamp:
    """One message's changes to a layer: polygons filled with values into a float32 scratch that is
    zero elsewhere, then added to the layer in one pass over the box they touched.

    One pass per message replaces a handful of calls per descriptor (each call into numpy or cv2
    costs microseconds however small its array). Within a message later fills overwrite earlier
    ones, so a cell counts once per message, with the last value drawn on it."""

    def __init__(self, window: GridWindow) -> None:
        self.window = window
        self._scratch = np.zeros(window.shape, dtype=np.float32)
        self._origin = np.array((window.origin_east_m, window.origin_north_m))
        self._box = [window.rows, 0, window.cols, 0]  # rows [0]:[1], columns [2]:[3] touched since clear

    @property
    def box(self) -> tuple[slice, slice] | None:
        r0, r1, c0, c1 = self._box
        return (slice(r0, r1), slice(c0, c1)) if r0 < r1 and c0 < c1 else None

    def fill(self, polygons: FloatArray, value: float) -> None:
        """Fill (n, k, 2) ENU polygons with ``value``."""
        self.fill_each(polygons, np.full(len(polygons), value))

    def fill_each(self, polygons: FloatArray, values: FloatArray) -> None:
        """Fill (n, k, 2) ENU polygons, each with its own value and in its own cv2 call: given
        several at once, cv2.fillPoly fills by crossings, so where two overlap it leaves a hole."""
        if not len(polygons):
            return
        cells = self._cells(polygons)
        low, high = cells.min(axis=1), cells.max(axis=1)
        if not -_FAR_CELLS <= low.min() <= high.max() <= _FAR_CELLS:
            np.clip(cells, -_FAR_CELLS, _FAR_CELLS, out=cells)
        fixed = self._fixed(cells)
        low, high = low.tolist(), high.tolist()
        for index, value in enumerate(values.tolist()):
            (x0, y0), (x1, y1) = low[index], high[index]
            if self._touch(x0, x1, y0, y1):
                cv2.fillPoly(self._scratch, [fixed[index]], value, cv2.LINE_8, _SHIFT)

    def add_to(self, layer: NDArray[np.float32], low: float, high: float) -> None:
        """``layer`` += the stamp, clamped to [low, high]; then clear the stamp."""
        box = self.box
        if box is None:
            return
        cells = layer[box]
        cv2.add(cells, self._scratch[box], dst=cells)
        np.clip(cells, low, high, out=cells)
        self.clear()

    def add_capped_to(self, layer: NDArray[np.float32], cap: float) -> None:
        """``layer`` += the stamp, but raising no cell above ``cap`` (nor lowering one already
        above it); then clear the stamp."""
        box = self.box
        if box is None:
            return
        cells = layer[box]
        ceiling = np.maximum(cells, np.float32(cap))
        cv2.add(cells, self._scratch[box], dst=cells)
        np.minimum(cells, ceiling, out=cells)
        self.clear()

    def touched(self) -> tuple[tuple[slice, slice], NDArray[np.bool_]] | None:
        """The box touched and, in it, which cells were filled with a positive value."""
        box = self.box
        return None if box is None else (box, self._scratch[box] > 0)

    def clear(self) -> None:
        box = self.box
        if box is not None:
            self._scratch[box] = 0.0
        self._box = [self.window.rows, 0, self.window.cols, 0]

    def _touch(self, x0: float, x1: float, y0: float, y1: float) -> bool:
        """Extend the touched box by a polygon spanning continuous cell coordinates x0..x1
        (columns) and y0..y1 (rows), with cv2 rounding to the nearest cell; False when it misses
        the window or is not finite."""
        if not math.isfinite(x0 + x1 + y0 + y1):
            return False  # a polygon with NaN corners covers nothing
        r0, r1 = max(0, math.floor(y0)), min(self.window.rows, math.ceil(y1) + 2)
        c0, c1 = max(0, math.floor(x0)), min(self.window.cols, math.ceil(x1) + 2)
        if r0 >= r1 or c0 >= c1:
            return False
        box = self._box
        box[0], box[1], box[2], box[3] = min(box[0], r0), max(box[1], r1), min(box[2], c0), max(box[3], c1)
        return True

    def _cells(self, points: FloatArray) -> FloatArray:
        """ENU points to continuous cell coordinates (x = column, y = row) with cv2's convention
        that integer coordinates are pixel centres: cell (r, c) has its centre at (c + 0.5, r + 0.5).
        Callers clamp coordinates beyond +-_FAR_CELLS, which would overflow cv2's fixed point."""
        cells = np.asarray(points) - self._origin
        cells *= 1.0 / self.window.resolution_m
        cells -= 0.5
        return cells

    @staticmethod
    def _fixed(cells: FloatArray) -> NDArray[np.int32]:
        return np.rint(cells * _SCALE).astype(np.int32)
