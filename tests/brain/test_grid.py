"""The shared grid window: cell lookup, centres and rolling evidence with the vehicle."""

from __future__ import annotations

import numpy as np
import pytest

from brain.grid import GridWindow, Sides, roll_into


def test_cells_and_centres_agree() -> None:
    window = GridWindow(10.0, -5.0, 0.2, rows=50, cols=100)
    row, col = window.cell_of([10.0, 10.19, 29.99, 9.99], [-5.0, -4.81, 4.99, 0.0])
    assert row.tolist() == [0, 0, 49, 25]
    assert col.tolist() == [0, 0, 99, -1]
    assert window.inside(row, col).tolist() == [True, True, True, False]
    east, north = window.centre_of(row[:3], col[:3])
    np.testing.assert_allclose(east, [10.1, 10.1, 29.9])
    np.testing.assert_allclose(north, [-4.9, -4.9, 4.9])
    grid_east, grid_north = window.cell_centres()
    assert grid_east.shape == grid_north.shape == window.shape
    assert (grid_east[0, 0], grid_north[0, 0]) == pytest.approx((10.1, -4.9))


def test_centred_windows_share_the_lattice_and_roll_evidence() -> None:
    old = GridWindow.centred(0.0, 0.0, 20.0, 10.0, 0.5)
    new = GridWindow.centred(3.3, -1.1, 20.0, 10.0, 0.5)
    assert old.shape == new.shape == (20, 40)
    values = np.zeros(old.shape, dtype=np.float32)
    row, col = old.cell_of(4.2, 1.3)
    values[row, col] = 0.9
    rolled = roll_into(values, old, new, fill=0.5)
    new_row, new_col = new.cell_of(4.2, 1.3)
    assert rolled[new_row, new_col] == pytest.approx(0.9)
    assert np.count_nonzero(rolled == np.float32(0.9)) == 1
    d_row, d_col = old.shift_to(new)
    assert np.all(rolled[:, new.cols - d_col :] == np.float32(0.5))  # columns new to the window
    assert d_row < 0 and np.all(rolled[:-d_row, :] == np.float32(0.5))


def test_windows_off_the_lattice_or_disjoint() -> None:
    a = GridWindow(0.0, 0.0, 0.2, 10, 10)
    with pytest.raises(ValueError, match="lattice"):
        a.shift_to(GridWindow(0.05, 0.0, 0.2, 10, 10))
    with pytest.raises(ValueError, match="resolution"):
        a.shift_to(GridWindow(0.0, 0.0, 0.5, 10, 10))
    far = GridWindow(100.0, 0.0, 0.2, 10, 10)
    assert np.all(roll_into(np.ones((10, 10)), a, far, fill=0.0) == 0.0)
    with pytest.raises(ValueError):
        GridWindow(0.0, 0.0, 0.0, 10, 10)


def test_a_crop_is_the_cells_meeting_a_box_on_the_same_lattice() -> None:
    window = GridWindow(10.0, -5.0, 0.2, rows=50, cols=100)
    crop = window.crop(12.05, -5.5, 15.0, 0.1)
    assert crop is not None
    assert (crop.rows, crop.cols) == (slice(0, 26), slice(10, 26))
    assert crop.window.shape == (26, 16)
    assert (crop.window.origin_east_m, crop.window.origin_north_m) == pytest.approx((12.0, -5.0))
    assert window.shift_to(crop.window) == (0, 10)
    assert crop.cut == Sides(south=False, north=True, west=True, east=True)  # the box overhangs the south edge
    values = np.arange(50 * 100).reshape(50, 100)
    row, col = crop.window.cell_of(14.3, -2.1)
    assert values[crop.rows, crop.cols][row, col] == values[window.cell_of(14.3, -2.1)]
    everything = window.crop(0.0, -10.0, 40.0, 10.0)
    assert everything is not None and everything.window == window and not any(everything.cut)
    assert window.crop(40.0, 0.0, 50.0, 1.0) is None
