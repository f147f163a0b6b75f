"""Smoothing a searched path: shortcuts, then rounded corners, on the search's own free cells.

A lattice path zig-zags in 45-degree steps. Shortcutting keeps, from each kept point, the
furthest later point that a straight segment reaches over free cells (a galloping search, so a
long path costs a few vectorised checks per kept point rather than one per pair). The result
hugs the obstacles at its corners; each corner is then cut by the longest of a few chords that
still stays on free cells, twice, which rounds the corners where there is room and leaves them
where there is not.

A segment counts as clear when samples no further apart than a cell all lie in cells whose whole
3 x 3 neighbourhood is free: every point of the segment is then within half a cell of a sample,
so in a free cell. Free cells are the search's (clear of lethal cells and the corridor's edge by
the gate's margins plus the slack of any point in the cell), so whatever this accepts passes
`PathGate`, at any sampling; the planner gates the result once more all the same.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from brain.grid import GridWindow

FloatArray = NDArray[np.float64]

CUTS_M = (2.0, 1.0, 0.5)  # corner chords tried, longest first
ROUNDS = 2


class FreeCells:
    """Segment tests over a window's free-cell mask."""

    def __init__(self, window: GridWindow, free: NDArray[np.bool_]) -> None:
        if free.shape != window.shape:
            raise ValueError("the free mask must have the window's shape")
        self.window = window
        kernel = np.ones((3, 3), dtype=np.uint8)
        # Outside the window counts as not free: a searched path never leaves it.
        eroded = cv2.erode(free.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        self._safe = eroded.astype(bool).ravel()

    def clear(self, start: FloatArray, end: FloatArray) -> NDArray[np.bool_]:
        """For each segment start[i] -> end[i] (M x 2 each), whether every point of it is on a free cell."""
        start = np.asarray(start, dtype=float).reshape(-1, 2)
        end = np.asarray(end, dtype=float).reshape(-1, 2)
        if len(start) == 0:
            return np.zeros(0, dtype=bool)
        w = self.window
        delta = end - start
        length = np.hypot(delta[:, 0], delta[:, 1])
        # Every segment gets as many samples as the longest needs: regular arrays, no bookkeeping.
        count = int(np.ceil(length.max() / w.resolution_m)) + 1
        t = np.linspace(0.0, 1.0, count)
        col = np.floor((start[:, :1] + t * delta[:, :1] - w.origin_east_m) / w.resolution_m).astype(np.intp)
        row = np.floor((start[:, 1:] + t * delta[:, 1:] - w.origin_north_m) / w.resolution_m).astype(np.intp)
        inside = (row >= 0) & (row < w.rows) & (col >= 0) & (col < w.cols)
        safe = inside & self._safe[np.where(inside, row * w.cols + col, 0)]
        return safe.all(axis=1)


def smooth(points: FloatArray, cells: FreeCells) -> FloatArray:
    """A smoother polyline over free cells from the same start to the same end (N x 2)."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(points) < 3:
        return points
    path = shortcut(points, cells)
    for _ in range(ROUNDS):
        path = round_corners(path, cells)
    return path


def shortcut(points: FloatArray, cells: FreeCells) -> FloatArray:
    """Greedy string pulling: from each kept point jump to the furthest point found reachable.

    Two vectorised checks per kept point: the points 1, 2, 4, 8, ... ahead and the last one;
    then every point between the furthest good probe and the first bad one. A step to the very
    next point is always taken, so an input whose own segments are not clear comes back whole.
    """
    kept = [0]
    last = len(points) - 1
    while kept[-1] < last:
        i = kept[-1]
        probes = np.unique(np.minimum(i + 2 ** np.arange(math.floor(math.log2(last - i)) + 2), last))
        ok = _clear_from(cells, points[i], points[probes])
        if ok.all():
            kept.append(last)
            continue
        first_bad = int(np.argmin(ok))
        good = int(probes[first_bad - 1]) if first_bad > 0 else i + 1
        between = np.arange(good + 1, int(probes[first_bad]))
        if len(between):
            passing = between[_clear_from(cells, points[i], points[between])]
            if len(passing):
                good = int(passing[-1])
        kept.append(good)
    return points[kept]


def round_corners(points: FloatArray, cells: FreeCells) -> FloatArray:
    """Each interior vertex replaced by the two ends of the longest clear chord across it."""
    if len(points) < 3:
        return points
    before = points[:-2] - points[1:-1]
    after = points[2:] - points[1:-1]
    len_before = np.hypot(before[:, 0], before[:, 1])
    len_after = np.hypot(after[:, 0], after[:, 1])
    # Each neighbouring segment gives at most 45% of itself to a corner, so chords never overlap.
    limit = 0.45 * np.minimum(len_before, len_after)
    corners = len(points) - 2
    cuts = np.minimum(np.asarray(CUTS_M)[None, :], limit[:, None])  # (corners, tries)
    unit_before = before / np.maximum(len_before, 1e-12)[:, None]
    unit_after = after / np.maximum(len_after, 1e-12)[:, None]
    start = points[1:-1, None, :] + cuts[..., None] * unit_before[:, None, :]
    end = points[1:-1, None, :] + cuts[..., None] * unit_after[:, None, :]
    ok = cells.clear(start.reshape(-1, 2), end.reshape(-1, 2)).reshape(corners, len(CUTS_M))
    ok &= cuts > 1e-3
    out = [points[0]]
    for k in range(corners):
        passing = np.flatnonzero(ok[k])
        if len(passing):
            out.extend([start[k, passing[0]], end[k, passing[0]]])
        else:
            out.append(points[k + 1])
    out.append(points[-1])
    return np.asarray(out)


def _clear_from(cells: FreeCells, start: FloatArray, ends: FloatArray) -> NDArray[np.bool_]:
    return cells.clear(np.broadcast_to(start, ends.shape), ends)
