"""Obstacle points -> descriptors, on hand-made point sets."""

from __future__ import annotations

import numpy as np
import pytest

from modules.esvs.vision.clusters import ClusterParams, cluster_labels, describe

ROWS, COLUMNS = 100, 200
FB = 261.4  # focal * baseline of the RASCAL rig, px * m


def surface(mask: np.ndarray, rng: np.random.Generator, patches: list[tuple[slice, slice, float, float, float]]):
    """Planes of disparity and VEHICLE x, y, z with fronto-parallel patches (rows, columns,
    range x, lateral centre y, height) and 1/16 px disparity noise."""
    disparity = np.full((ROWS, COLUMNS), np.nan, np.float32)
    x, y, z = (np.full((ROWS, COLUMNS), np.nan, np.float32) for _ in range(3))
    for rows, columns, range_m, centre_m, height_m in patches:
        block = (rows, columns)
        shape = disparity[block].shape
        d = FB / range_m + rng.normal(0, 1 / 16, shape)
        disparity[block] = d
        x[block] = FB / d
        y[block] = centre_m + np.linspace(0.5, -0.5, shape[1])[None, :]
        z[block] = np.linspace(height_m, 0.0, shape[0])[:, None]
        mask[block] = True
    return disparity, (x, y, z)


def test_two_separate_surfaces_become_two_obstacles_nearest_first() -> None:
    rng = np.random.default_rng(1)
    mask = np.zeros((ROWS, COLUMNS), bool)
    disparity, xyz = surface(
        mask, rng, [(slice(40, 90), slice(20, 60), 20.0, 1.0, 1.0), (slice(50, 70), slice(120, 160), 12.0, -2.0, 0.8)]
    )
    obstacles = describe(mask, disparity, xyz, 32)
    assert len(obstacles) == 2
    near, far = obstacles
    assert near.range_m < far.range_m
    assert near.x_m == pytest.approx(12.0, abs=0.2) and near.y_m == pytest.approx(-2.0, abs=0.05)
    assert far.x_m == pytest.approx(20.0, abs=0.5) and far.y_m == pytest.approx(1.0, abs=0.05)
    assert near.width_m == pytest.approx(1.0, abs=0.1) and near.height_m == pytest.approx(0.8, abs=0.05)
    assert all(o.yaw_rad == 0.0 and 0.0 < o.confidence <= 1.0 for o in obstacles)


def test_surfaces_side_by_side_at_different_ranges_stay_apart() -> None:
    # Adjacent columns, but 2 px apart in disparity: a post in front of a wall.
    rng = np.random.default_rng(2)
    mask = np.zeros((ROWS, COLUMNS), bool)
    patches = [(slice(40, 90), slice(40, 80), 13.0, 0.0, 1.0), (slice(40, 90), slice(80, 120), 16.0, -1.0, 1.0)]
    disparity, xyz = surface(mask, rng, patches)
    assert len(describe(mask, disparity, xyz, 32)) == 2


def test_scattered_points_are_noise() -> None:
    rng = np.random.default_rng(3)
    mask = rng.random((ROWS, COLUMNS)) < 0.002
    disparity = rng.uniform(5, 30, (ROWS, COLUMNS)).astype(np.float32)
    xyz = tuple(rng.normal(size=(ROWS, COLUMNS)).astype(np.float32) for _ in range(3))
    assert describe(mask, disparity, xyz, 32) == ()


def test_confidence_grows_with_points_and_falls_with_spread() -> None:
    rng = np.random.default_rng(5)
    results = []
    for rows in (slice(60, 66), slice(40, 90)):
        mask = np.zeros((ROWS, COLUMNS), bool)
        disparity, xyz = surface(mask, rng, [(rows, slice(50, 70), 15.0, 0.0, 1.0)])
        results.append(describe(mask, disparity, xyz, 32)[0].confidence)
    assert results[0] < results[1]
    mask = np.zeros((ROWS, COLUMNS), bool)
    disparity, xyz = surface(mask, rng, [(slice(40, 90), slice(50, 70), 15.0, 0.0, 1.0)])
    disparity[40:90, 50:70] += rng.uniform(-1.5, 1.5, (50, 20)).astype(np.float32)  # a ragged surface
    assert describe(mask, disparity, xyz, 32)[0].confidence < results[1]


def test_at_most_max_obstacles_are_kept_the_nearest() -> None:
    rng = np.random.default_rng(6)
    mask = np.zeros((ROWS, COLUMNS), bool)
    patches = [(slice(40, 60), slice(10 + 40 * i, 30 + 40 * i), 10.0 + 4 * i, 0.0, 1.0) for i in range(5)]
    disparity, xyz = surface(mask, rng, patches)
    kept = describe(mask, disparity, xyz, 32, ClusterParams(max_obstacles=3))
    assert [round(o.x_m) for o in kept] == [10, 14, 18]


def test_labels_group_by_column_and_disparity_cells() -> None:
    columns = np.array([0, 1, 2, 3, 100, 101, 102, 103])
    disparities = np.array([10.0, 10.1, 10.2, 10.0, 10.0, 10.1, 10.2, 10.0])
    labels = cluster_labels(columns, disparities, 200, 32, ClusterParams(min_cell_points=2))
    assert labels[0] == labels[3] != 0 and labels[4] == labels[7] != 0 and labels[0] != labels[4]
