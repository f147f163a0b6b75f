"""The corridor as the planner's hard boundary, fast enough for a planning cycle.

`brain.corridor.Corridor` measures every point against every segment of the course; a planning
cycle only ever looks at a few hundred metres. `LocalCorridor` hands out a `Corridor` of just
the segments whose bands can reach a box (the clearance of a point inside the box is the same:
a band that cannot reach the box cannot be the largest clearance of a point in the corridor), and
rasterises the corridor onto a grid window for the search, one segment at a time over that
segment's own bounding box.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from brain.corridor import Corridor
from brain.grid import GridWindow

Box = tuple[float, float, float, float]  # min east, min north, max east, max north


class LocalCorridor:
    """Sub-corridors of ``corridor`` around boxes, the last few cached by their segment set."""

    def __init__(self, corridor: Corridor, cache_size: int = 4) -> None:
        self.corridor = corridor
        start, end, radius = corridor.start_m, corridor.end_m, corridor.half_width_m
        self._low = np.minimum(start, end) - radius[:, None]
        self._high = np.maximum(start, end) + radius[:, None]
        self._cache: dict[tuple[int, ...], Corridor] = {}
        self._cache_size = cache_size

    def segments_near(self, box: Box) -> NDArray[np.intp]:
        """Indices of the segments whose band's bounding box meets ``box``."""
        low_e, low_n, high_e, high_n = box
        meets = (
            (self._low[:, 0] <= high_e)
            & (self._high[:, 0] >= low_e)
            & (self._low[:, 1] <= high_n)
            & (self._high[:, 1] >= low_n)
        )
        return np.flatnonzero(meets)

    def near(self, box: Box) -> Corridor | None:
        """The corridor's segments that can reach ``box``; None when none can (the box is outside)."""
        index = self.segments_near(box)
        if len(index) == 0:
            return None
        key = tuple(index.tolist())
        cached = self._cache.get(key)
        if cached is None:
            c = self.corridor
            cached = Corridor(c.start_m[index], c.end_m[index], c.half_width_m[index])
            if len(self._cache) >= self._cache_size:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = cached
        return cached

    def distance_to_edge(self, east_m: NDArray[np.float64], north_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """`Corridor.distance_to_edge` for points, computed on the segments near them; points
        that no band can reach get -inf (they are outside, by more than any threshold of ours)."""
        east, north = np.broadcast_arrays(np.asarray(east_m, dtype=float), np.asarray(north_m, dtype=float))
        if east.size == 0:
            return np.empty(east.shape)
        local = self.near((float(east.min()), float(north.min()), float(east.max()), float(north.max())))
        if local is None:
            return np.full(east.shape, -np.inf)
        return np.asarray(local.distance_to_edge(east, north), dtype=float).reshape(east.shape)

    def mask(self, window: GridWindow, clearance_m: float) -> NDArray[np.bool_]:
        """Cells whose centre is at least ``clearance_m`` (>= 0) inside the corridor."""
        return self.depth(window) >= clearance_m

    def depth(self, window: GridWindow) -> NDArray[np.float64]:
        """`distance_to_edge` at every cell centre of ``window`` inside the corridor, -inf at
        those outside (a lower bound, as the search's Lipschitz bounds need), one segment's
        bounding box at a time."""
        res = window.resolution_m
        out = np.full(window.shape, -np.inf)
        box = (
            window.origin_east_m,
            window.origin_north_m,
            window.origin_east_m + window.cols * res,
            window.origin_north_m + window.rows * res,
        )
        c = self.corridor
        for i in self.segments_near(box):
            reach = float(c.half_width_m[i])
            (e0, n0), (e1, n1) = c.start_m[i], c.end_m[i]
            col_lo = max(0, int(np.floor((min(e0, e1) - reach - window.origin_east_m) / res)))
            col_hi = min(window.cols, int(np.ceil((max(e0, e1) + reach - window.origin_east_m) / res)) + 1)
            row_lo = max(0, int(np.floor((min(n0, n1) - reach - window.origin_north_m) / res)))
            row_hi = min(window.rows, int(np.ceil((max(n0, n1) + reach - window.origin_north_m) / res)) + 1)
            if col_lo >= col_hi or row_lo >= row_hi:
                continue
            # Cell centres relative to the segment start: separable, so rows and columns stay 1-D.
            rel_e = window.origin_east_m + (np.arange(col_lo, col_hi) + 0.5) * res - e0
            rel_n = window.origin_north_m + (np.arange(row_lo, row_hi) + 0.5) * res - n0
            de, dn = e1 - e0, n1 - n0
            length2 = de * de + dn * dn
            along = rel_n[:, None] * dn + rel_e[None, :] * de
            if length2 > 0:
                along /= length2
                np.clip(along, 0.0, 1.0, out=along)
            else:
                along[:] = 0.0
            inside = reach - np.hypot(rel_e[None, :] - along * de, rel_n[:, None] - along * dn)
            inside[inside < 0.0] = -np.inf
            block = out[row_lo:row_hi, col_lo:col_hi]
            np.maximum(block, inside, out=block)
        return out
