"""Geometry of the brain's rolling bird's-eye grid: a window of square cells in the local ENU frame.

The fused hazard map, the cost layer and the planner's search all share one :class:`GridWindow`,
so a cell index means the same place to each of them. Row 0 is the southern edge, column 0 the
western edge (the layout MapSnapshot carries on the wire). The window rolls with the vehicle in
whole cells, so re-centring never resamples evidence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

Cell = TypeVar("Cell", bound=np.generic)  # a layer keeps its dtype when it rolls


class Sides(NamedTuple):
    """One flag per edge of a window, in the order its arrays are padded: rows, then columns."""

    south: bool = False
    north: bool = False
    west: bool = False
    east: bool = False


@dataclass(frozen=True)
class GridWindow:
    """``rows`` x ``cols`` cells of ``resolution_m``; cell (r, c) covers east
    [origin_east_m + c*res, +res) and north [origin_north_m + r*res, +res)."""

    origin_east_m: float
    origin_north_m: float
    resolution_m: float
    rows: int
    cols: int

    def __post_init__(self) -> None:
        if not self.resolution_m > 0 or self.rows <= 0 or self.cols <= 0:
            raise ValueError(f"grid needs a positive resolution and size, got {self}")

    @classmethod
    def centred(cls, east_m: float, north_m: float, width_m: float, height_m: float, resolution_m: float) -> GridWindow:
        """A window of about ``width_m`` (east) x ``height_m`` (north) around a point, its origin
        snapped to the cell lattice (multiples of the resolution) so windows rolled from each other
        share cell boundaries."""
        cols = max(1, round(width_m / resolution_m))
        rows = max(1, round(height_m / resolution_m))
        origin_east = math.floor((east_m - width_m / 2) / resolution_m) * resolution_m
        origin_north = math.floor((north_m - height_m / 2) / resolution_m) * resolution_m
        return cls(origin_east, origin_north, resolution_m, rows, cols)

    @property
    def shape(self) -> tuple[int, int]:
        return self.rows, self.cols

    def cell_of(self, east_m: ArrayLike, north_m: ArrayLike) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """(row, col) of the cells containing the points; may lie outside the window (see inside)."""
        col = np.floor((np.asarray(east_m, dtype=float) - self.origin_east_m) / self.resolution_m).astype(np.intp)
        row = np.floor((np.asarray(north_m, dtype=float) - self.origin_north_m) / self.resolution_m).astype(np.intp)
        return row, col

    def inside(self, row: ArrayLike, col: ArrayLike) -> NDArray[np.bool_]:
        row, col = np.asarray(row), np.asarray(col)
        return (row >= 0) & (row < self.rows) & (col >= 0) & (col < self.cols)

    def centre_of(self, row: ArrayLike, col: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """ENU (east, north) of cell centres."""
        east = self.origin_east_m + (np.asarray(col, dtype=float) + 0.5) * self.resolution_m
        north = self.origin_north_m + (np.asarray(row, dtype=float) + 0.5) * self.resolution_m
        return east, north

    def cell_centres(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """East and north of every cell centre, each of shape (rows, cols)."""
        rows, cols = np.mgrid[0 : self.rows, 0 : self.cols]
        return self.centre_of(rows, cols)

    def crop(self, low_east_m: float, low_north_m: float, high_east_m: float, high_north_m: float) -> Crop | None:
        """The cells meeting a box, as a window of their own on this one's lattice (None when no
        cell does); its cut edges are those inside this window."""
        (row_lo, row_hi), (col_lo, col_hi) = self.cell_of([low_east_m, high_east_m], [low_north_m, high_north_m])
        rows = slice(max(int(row_lo), 0), min(int(row_hi) + 1, self.rows))
        cols = slice(max(int(col_lo), 0), min(int(col_hi) + 1, self.cols))
        if rows.start >= rows.stop or cols.start >= cols.stop:
            return None
        res = self.resolution_m
        window = GridWindow(
            self.origin_east_m + cols.start * res,
            self.origin_north_m + rows.start * res,
            res,
            rows.stop - rows.start,
            cols.stop - cols.start,
        )
        cut = Sides(rows.start > 0, rows.stop < self.rows, cols.start > 0, cols.stop < self.cols)
        return Crop(window, rows, cols, cut)

    def shift_to(self, other: GridWindow) -> tuple[int, int]:
        """Whole-cell offset (d_row, d_col) of ``other``'s origin from this one's; both windows
        must share resolution and lattice."""
        if other.resolution_m != self.resolution_m:
            raise ValueError("windows with different resolutions do not share cells")
        d_col = (other.origin_east_m - self.origin_east_m) / self.resolution_m
        d_row = (other.origin_north_m - self.origin_north_m) / self.resolution_m
        if abs(d_col - round(d_col)) > 1e-6 or abs(d_row - round(d_row)) > 1e-6:
            raise ValueError("windows are not on the same cell lattice")
        return round(d_row), round(d_col)


class Crop(NamedTuple):
    """Part of a window: the part as a window, its rows and columns there, and which edges were cut."""

    window: GridWindow
    rows: slice
    cols: slice
    cut: Sides


def roll_into(values: NDArray[Cell], old: GridWindow, new: GridWindow, fill: float) -> NDArray[Cell]:
    """``values`` laid out on ``old`` moved onto ``new``: cells both windows cover keep their
    value, cells new to the window get ``fill``."""
    d_row, d_col = old.shift_to(new)
    out = np.full(new.shape, fill, dtype=values.dtype)
    # Overlap in old-window indices: new cell (r, c) is old cell (r + d_row, c + d_col).
    r0, r1 = max(0, -d_row), min(new.rows, old.rows - d_row)
    c0, c1 = max(0, -d_col), min(new.cols, old.cols - d_col)
    if r0 < r1 and c0 < c1:
        out[r0:r1, c0:c1] = values[r0 + d_row : r1 + d_row, c0 + d_col : c1 + d_col]
    return out
