"""Kratos' Algorithm 1 on hand-made point sets: walls are obstacles, ground and ramps are not."""

from __future__ import annotations

import numpy as np
import pytest

from modules.esvs.vision.obstacle_points import (
    ObstaclePointParams,
    compatible,
    depth_edges,
    obstacle_points,
    window_rows,
)

ROWS, COLUMNS = 60, 8
BASELINE_M = 0.3
STEP_M = 0.02  # each row climbs 2 cm on a vertical surface: 50 rows per metre...
DISPARITY = 50 * BASELINE_M  # ...which is what this disparity says (rows per metre = d / B)


def planes(x_of_up: np.ndarray, y_of_up: np.ndarray, z_of_up: np.ndarray) -> tuple[np.ndarray, ...]:
    """Every column alike; ``*_of_up`` give each row's point, indexed by rows above the bottom."""
    up = np.arange(ROWS)[::-1]
    make = lambda values: np.repeat(np.asarray(values, np.float32)[up][:, None], COLUMNS, axis=1)  # noqa: E731
    return make(x_of_up), make(y_of_up), make(z_of_up), np.full((ROWS, COLUMNS), DISPARITY, np.float32)


UP = np.arange(ROWS)


def test_a_vertical_wall_is_obstacle_points() -> None:
    x, y, z, d = planes(np.full(ROWS, 10.0), np.zeros(ROWS), UP * STEP_M)
    mask = obstacle_points(x, y, z, d, BASELINE_M)
    assert mask.all()


def test_flat_ground_is_not() -> None:
    x, y, z, d = planes(10.0 + UP * 0.1, np.zeros(ROWS), np.zeros(ROWS))
    assert not obstacle_points(x, y, z, d, BASELINE_M).any()


def test_a_45_degree_ramp_is_not() -> None:
    # Rising 0.3-0.5 m also means moving 0.3-0.5 m away: more than the 0.3 m depth tolerance.
    x, y, z, d = planes(10.0 + UP * STEP_M, np.zeros(ROWS), UP * STEP_M)
    assert not obstacle_points(x, y, z, d, BASELINE_M).any()


def test_a_step_lower_than_the_minimum_height_is_not() -> None:
    # A 0.2 m kerb at 10 m, ground beyond it: nothing is 0.3 m above anything within 0.3 m depth.
    kerb = UP < 10
    x = np.where(kerb, 10.0, 10.0 + (UP - 10) * 0.1)
    z = np.where(kerb, UP * STEP_M, 0.2)
    x, y, z, d = planes(x, np.zeros(ROWS), z)
    assert not obstacle_points(x, y, z, d, BASELINE_M).any()


def test_a_wall_leaning_sideways_passes_only_steeper_than_the_minimum_angle() -> None:
    steep = planes(np.full(ROWS, 10.0), UP * STEP_M * 0.1, UP * STEP_M)  # 84 deg
    shallow = planes(np.full(ROWS, 10.0), UP * STEP_M * 0.5, UP * STEP_M)  # 63 deg
    assert obstacle_points(*steep, BASELINE_M).all()
    assert not obstacle_points(*shallow, BASELINE_M).any()


def test_pixels_without_disparity_are_never_obstacles() -> None:
    x, y, z, d = planes(np.full(ROWS, 10.0), np.zeros(ROWS), UP * STEP_M)
    d[:, 3] = np.nan
    for plane in (x, y, z):
        plane[:, 5] = np.nan
    mask = obstacle_points(x, y, z, d, BASELINE_M)
    assert not mask[:, 3].any() and not mask[:, 5].any()
    assert mask[:, [0, 1, 2, 4, 6, 7]].all()


def test_far_pixels_are_not_tried() -> None:
    x, y, z, d = planes(np.full(ROWS, 10.0), np.zeros(ROWS), UP * STEP_M)
    assert not obstacle_points(x, y, z, d, BASELINE_M, min_disparity_px=DISPARITY + 1).any()


def test_window_rows_span_the_height_window_at_the_pixels_range() -> None:
    params = ObstaclePointParams(samples=4)
    rows = window_rows(np.array([15.0, 30.0]), BASELINE_M, params)
    # 15 px disparity: 50 rows per metre, so 0.3-0.5 m is rows 15-25 above.
    np.testing.assert_array_equal(rows[:, 0], [16, 19, 21, 24])
    # 30 px: twice as close, twice the rows.
    assert np.all(np.abs(rows[:, 1] - 2 * rows[:, 0]) <= 1) and np.all(np.diff(rows[:, 1]) > 0)


def test_compatible_is_kratos_test_exactly() -> None:
    params = ObstaclePointParams()
    p = (np.zeros(6), np.zeros(6), np.zeros(6))
    q = (
        np.array([0.1, 0.35, 0.0, 0.0, 0.0, 0.0]),  # depth differences
        np.array([0.0, 0.0, 0.0, 0.0, 0.1, 0.05]),  # lateral
        np.array([0.4, 0.4, 0.25, 0.55, 0.4, 0.4]),  # height
    )
    np.testing.assert_array_equal(compatible(p, q, params), [True, False, False, False, False, True])


def brute_force(x: np.ndarray, y: np.ndarray, z: np.ndarray, params: ObstaclePointParams) -> np.ndarray:
    """Algorithm 1 as written: every P against every Q above it in its column."""
    mask = np.zeros(x.shape, bool)
    for column in range(x.shape[1]):
        for p in range(x.shape[0]):
            for q in range(p):
                pair = compatible(
                    (x[p, column], y[p, column], z[p, column]), (x[q, column], y[q, column], z[q, column]), params
                )
                if pair:
                    mask[p, column] = mask[q, column] = True
    return mask


def test_sampling_the_window_finds_what_the_exhaustive_search_finds() -> None:
    rng = np.random.default_rng(4)
    # Ground, a 0.8 m wall on it, ground again beyond; stereo-like depth noise on everything.
    wall = (UP >= 12) & (UP < 52)
    x = np.where(UP < 12, 10.0 - (12 - UP) * 0.1, np.where(wall, 10.0, 14.0 + (UP - 52) * 0.3))
    z = np.where(wall, (UP - 12) * STEP_M, np.where(UP < 12, 0.0, 0.0))
    x, y, z, d = planes(x, np.zeros(ROWS), z)
    x = x + rng.normal(0, 0.05, x.shape).astype(np.float32)
    params = ObstaclePointParams()
    fast = obstacle_points(x, y, z, d, BASELINE_M, params)
    slow = brute_force(x, y, z, params)
    assert not (fast & ~slow).any()  # everything flagged is flagged by the exhaustive search
    assert (fast & slow).sum() >= 0.9 * slow.sum()  # and it misses little
    # The exhaustive search flags the wall, and the ground at its foot (within the depth tolerance,
    # plus 3 sigma of the noise).
    at_foot = (UP < 12) & (10.0 - (12 - UP) * 0.1 > 10.0 - 0.3 - 0.15)
    assert slow[wall[::-1]].all()
    assert not slow[~(wall | at_foot)[::-1]].any()


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError):
        ObstaclePointParams(min_height_diff_m=0.5, max_height_diff_m=0.3)
    with pytest.raises(ValueError):
        obstacle_points(np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((2, 3)), np.zeros((2, 2)), BASELINE_M)


def test_depth_edges_are_where_disparity_jumps_sideways() -> None:
    disparity = np.tile(np.r_[np.full(10, 20.0), np.full(10, 12.0)], (3, 1)).astype(np.float32)
    disparity[:, 3] += 0.5  # texture noise is no edge
    edges = depth_edges(disparity, 3, 1.0)
    assert edges[:, 7:13].all()  # within 3 columns of the jump
    assert not edges[:, :7].any() and not edges[:, 13:].any()
    assert not depth_edges(disparity, 0, 1.0).any()


def test_the_smeared_edge_between_two_walls_is_not_obstacle_points() -> None:
    x, y, z, d = planes(np.full(ROWS, 10.0), np.zeros(ROWS), UP * STEP_M)
    d[:, 4:] = DISPARITY - 3.0  # a farther wall from column 4 on
    params = ObstaclePointParams(edge_span_px=2)
    mask = obstacle_points(x, y, z, d, BASELINE_M, params)
    assert not mask[:, 2:6].any()
    assert mask[:, [0, 1, 6, 7]].all()
