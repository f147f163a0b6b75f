"""Lane filters, heat map geometry, RANSAC parabolas and greedy extension, on hand-made inputs."""

from __future__ import annotations

import numpy as np
import pytest

from modules.esvs.geometry import RASCAL_RIG
from modules.esvs.vision.lane_fit import FitParams, fit_borders
from modules.esvs.vision.lane_heat import HeatMap, HeatParams, grid_shape, grid_to_band, heat_map, pixel_scores

HEAT = HeatParams()


def draw(curves: list[tuple[float, float, float, float, float]], rng: np.random.Generator, noise: float = 0.0):
    """A heat map with lines y = c0 + c1 x + c2 x^2 for x in [x0, x1], and random hot cells."""
    heat = np.zeros(grid_shape(HEAT), np.float32)
    empty = HeatMap(heat, HEAT)
    rows = np.arange(heat.shape[0])
    for c0, c1, c2, x0, x1 in curves:
        xs = empty.x_of(rows)
        inside = (xs >= x0) & (xs <= x1)
        columns = np.rint(empty.column_of(c0 + c1 * xs + c2 * xs * xs)).astype(int)
        ok = inside & (columns >= 0) & (columns < heat.shape[1])
        heat[rows[ok], columns[ok]] = 1.0
    heat[rng.random(heat.shape) < noise] = 1.0
    return HeatMap(heat, HEAT)


def test_a_parabola_is_recovered_among_noise() -> None:
    heat = draw([(-2.5, 0.05, 0.002, 0, 100)], np.random.default_rng(1), noise=0.005)
    (border,) = fit_borders(heat)
    assert border.side == -1
    xs = np.linspace(15, 35, 9)
    fitted = border.c0_m + border.c1 * xs + border.c2_per_m * xs * xs
    np.testing.assert_allclose(fitted, -2.5 + 0.05 * xs + 0.002 * xs * xs, atol=0.06)
    assert border.x_min_m == pytest.approx(HEAT.x_min_m, abs=0.6)
    assert border.confidence > 0.9


def test_two_borders_come_left_first() -> None:
    heat = draw([(-2.0, 0.0, 0.001, 0, 100), (2.0, 0.0, 0.001, 0, 100)], np.random.default_rng(2))
    left, right = fit_borders(heat)
    assert (left.side, right.side) == (1, -1)
    assert left.c0_m == pytest.approx(2.0, abs=0.1) and right.c0_m == pytest.approx(-2.0, abs=0.1)


def test_greedy_extension_follows_the_line_past_the_fit_range() -> None:
    # Straight within the fit range, bending beyond it: the trail follows the bend to its end.
    heat = np.zeros(grid_shape(HEAT), np.float32)
    grid = HeatMap(heat, HEAT)
    for row in range(heat.shape[0]):
        x = float(grid.x_of(row))
        if x > 46.0:
            break
        y = 3.0 + 0.02 * max(x - 36.6, 0.0) ** 2
        heat[row, round(float(grid.column_of(y)))] = 1.0
    (border,) = fit_borders(grid)
    assert border.x_max_m == pytest.approx(46.0, abs=0.6)
    plain = fit_borders(grid, FitParams(extend=False))
    assert plain[0].x_max_m == pytest.approx(FitParams().fit_x_max_m, abs=0.6)


def test_noise_alone_gives_no_border() -> None:
    heat = draw([], np.random.default_rng(3), noise=0.01)
    assert fit_borders(heat) == ()


def test_a_short_dash_is_not_a_border() -> None:
    heat = draw([(1.5, 0.0, 0.0, 20.0, 22.0)], np.random.default_rng(4))
    assert fit_borders(heat) == ()


def test_the_pulse_filter_answers_a_stripe_of_the_marking_width_only() -> None:
    rig = RASCAL_RIG
    top, bottom = 250, 260
    depth = rig.mount_height_m / np.sin(np.radians(rig.pitch_down_deg) + np.arctan((255 - rig.cy_px) / rig.focal_px))
    width_px = round(rig.focal_px * HEAT.marking_width_m / depth)  # about 9 px at 15 m
    image = np.full((bottom - top, rig.width_px), 100, np.uint8)
    image[:, 200 : 200 + width_px] = 200  # a marking
    image[:, 400 : 400 + 8 * width_px] = 200  # a bright patch far wider than a marking
    image[:, 600:] = 200  # an edge
    score = pixel_scores(image, rig, top, HEAT)
    assert score[:, 200 : 200 + width_px].min() == 1.0
    assert score[:, 400 + 2 * width_px : 400 + 6 * width_px].max() == 0.0
    assert score[:, 560:].max() == 0.0
    not_ground = np.zeros_like(score, dtype=bool)
    not_ground[:, :300] = True
    assert pixel_scores(image, rig, top, HEAT, not_ground)[:, 200 : 200 + width_px].max() == 0.0


def test_heat_cells_map_to_where_the_ground_appears() -> None:
    rig = RASCAL_RIG
    top = 100
    homography = grid_to_band(rig, top, HEAT)
    grid = HeatMap(np.zeros(grid_shape(HEAT), np.float32), HEAT)
    row, column = 30, 40
    x, y = float(grid.x_of(row)), float(grid.y_of(column))
    u, v, _ = rig.project(np.array([x, y, 0.0]))
    pixel = homography @ np.array([column, row, 1.0])
    np.testing.assert_allclose(pixel[:2] / pixel[2], [float(u), float(v) - top], atol=1e-6)
    # A scored pixel lands in that cell.
    score = np.zeros((300, rig.width_px), np.float32)
    score[round(float(v)) - top, round(float(u))] = 1.0
    warped = heat_map(score, rig, top, HEAT).heat
    assert np.unravel_index(np.argmax(warped), warped.shape) == (row, column)


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ValueError):
        HeatParams(min_contrast=50.0, full_contrast=40.0)
    with pytest.raises(ValueError):
        FitParams(min_rows=2)
