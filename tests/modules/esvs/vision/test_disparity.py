"""The matcher: accurate on rendered ground and boxes, NaN where it has nothing to go on."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from modules.esvs.geometry import RASCAL_RIG
from modules.esvs.vision.band import BandParams, band_disparity, band_rows, vehicle_points
from modules.esvs.vision.disparity import REALTIME, MatcherParams, compute_disparity, fill_holes, matcher, texture
from tests.modules.esvs.vision.scenes import Box, Scene, rendered

SCENE = Scene(boxes=(Box(20.0, 1.0, 1.5, 1.0, 1.2),), seed=7)


def band_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    left, right, truth = rendered(SCENE)
    band = band_rows(RASCAL_RIG, BandParams())
    rows = slice(band.top, band.bottom)
    return left[rows], right[rows], truth[rows], band.top


def test_band_disparity_is_dense_and_accurate_within_range() -> None:
    left, right, truth = rendered(SCENE)
    band = band_rows(RASCAL_RIG, BandParams())
    disparity = band_disparity(left, right, band, REALTIME)
    truth = truth[band.top : band.bottom]
    # Pixels 8-40 m from the cameras, right of the columns no disparity can reach.
    fb = RASCAL_RIG.focal_px * RASCAL_RIG.baseline_m
    judged = (truth >= fb / 40) & (truth <= fb / 8)
    judged[:, : REALTIME.num_disparities] = False
    found = judged & np.isfinite(disparity)
    assert found.sum() >= 0.97 * judged.sum()
    error = np.abs(disparity[found] - truth[found])
    assert np.mean(error > 1.0) < 0.01
    assert np.median(error) < 0.15


@pytest.mark.parametrize("params", [REALTIME, MatcherParams(block_size=7, texture_threshold=1.0)], ids=["bm", "3way"])
def test_the_band_is_matched_to_its_edge_rows(params: MatcherParams) -> None:
    left, right, _truth = rendered(SCENE)
    band = band_rows(RASCAL_RIG, BandParams())
    disparity = band_disparity(left, right, band, params)
    assert disparity.shape == (band.rows, RASCAL_RIG.width_px)
    # The block matcher leaves its input's edge rows unmatched: the band borrows image rows for them.
    assert np.isfinite(disparity[-1]).mean() > 0.8  # ground 10 m ahead (the top rows are sky here)


def test_the_texture_check_removes_the_featureless_sky() -> None:
    left, right, truth, top = band_pair()
    # Sky pixels whose whole block is sky (the horizon row is the top of the ground).
    sky = truth == 0
    sky[int(RASCAL_RIG.horizon_row()) - top - 4 :] = False
    assert sky.sum() > 1000
    plain = compute_disparity(left, right, MatcherParams(block_size=7))
    checked = compute_disparity(left, right, REALTIME)
    assert np.isfinite(plain[sky]).mean() > 0.1  # the matcher alone matches sensor noise
    assert np.isfinite(checked[sky]).mean() < 0.01
    assert texture(np.full((20, 20), 50, np.uint8), 5).max() == 0.0


def test_points_land_on_the_box_face() -> None:
    left, right, _truth, top = band_pair()
    disparity = compute_disparity(left, right, REALTIME)
    x, y, z = vehicle_points(disparity, RASCAL_RIG, top)
    box = SCENE.boxes[0]
    on_face = (np.abs(y - box.y_m) < box.width_m / 2 - 0.1) & (z > 0.2) & (z < box.height_m - 0.2)
    on_face &= np.abs(x - box.x_m) < 2.0
    assert on_face.sum() > 1000
    assert abs(float(np.median(x[on_face])) - box.x_m) < 0.01 * box.x_m


def test_fill_takes_the_background_side_of_each_hole() -> None:
    disparity = np.array([[np.nan, 5.0, np.nan, np.nan, 9.0, np.nan], [np.nan] * 6], np.float32)
    fill_holes(disparity)
    np.testing.assert_array_equal(disparity[0], [5.0, 5.0, 5.0, 5.0, 9.0, 9.0])
    assert np.isnan(disparity[1]).all()  # nothing to fill a row from


def test_each_thread_gets_its_own_matcher() -> None:
    mine = matcher(REALTIME)
    assert matcher(REALTIME) is mine
    theirs = []
    worker = threading.Thread(target=lambda: theirs.append(matcher(REALTIME)))
    worker.start()
    worker.join()
    assert theirs[0] is not mine


def test_bad_input_and_parameters_are_refused() -> None:
    image = np.zeros((10, 64), np.uint8)
    with pytest.raises(ValueError, match="grey uint8"):
        compute_disparity(image, image[:-1])
    with pytest.raises(ValueError, match="grey uint8"):
        compute_disparity(image.astype(np.float32), image)
    with pytest.raises(ValueError, match="multiple of 16"):
        MatcherParams(num_disparities=40)
    with pytest.raises(ValueError, match="odd"):
        MatcherParams(block_size=4)
    with pytest.raises(ValueError, match="mode"):
        MatcherParams(mode="fast")
    with pytest.raises(ValueError, match="at least 5"):
        MatcherParams(mode="bm", block_size=3)
    with pytest.raises(ValueError, match="pre_filter_cap"):
        MatcherParams(pre_filter_cap=64)
