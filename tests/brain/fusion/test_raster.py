"""Rasterising polygons onto the window: overlapping polygons of one message cover their overlap."""

from __future__ import annotations

import numpy as np

from brain.fusion.raster import Stamp
from brain.grid import GridWindow

WINDOW = GridWindow(origin_east_m=0.0, origin_north_m=0.0, resolution_m=0.2, rows=50, cols=50)


def square(east: float, north: float, half: float) -> np.ndarray:
    return np.array(
        [
            [east - half, north - half],
            [east + half, north - half],
            [east + half, north + half],
            [east - half, north + half],
        ]
    )


def test_overlapping_polygons_of_one_fill_leave_no_hole() -> None:
    # Two detections of one rock, 1 m boxes 0.4 m apart: the overlap is the rock's middle.
    stamp = Stamp(WINDOW)
    stamp.fill(np.stack([square(4.8, 5.0, 0.5), square(5.2, 5.0, 0.5)]), 1.5)
    layer = np.zeros(WINDOW.shape, dtype=np.float32)
    stamp.add_to(layer, -2.0, 4.0)
    east, north = WINDOW.cell_centres()
    covered = (np.abs(east - 5.0) <= 0.8) & (np.abs(north - 5.0) <= 0.4)
    assert np.all(layer[covered] == 1.5)
    assert np.count_nonzero(layer) <= 8 * 6  # and no more than the cells the union touches
