"""The rendered pair is a stereo pair: the right image warped by the true disparity reproduces
the left one, and OpenCV's semi-global matcher recovers the true disparity from it."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from modules.sim.camera import StereoFrame, StereoRenderer
from modules.sim.scenario import load_scenario

# Along the default Mojave course: the narrow passage between two rocks, and the abandoned car.
COURSE_POINTS_M = (580.0, 2138.0)


def course_pose(at_m: float) -> tuple[float, float, float]:
    route = load_scenario().route
    i = int(np.searchsorted(route.s_m, at_m))
    yaw = math.atan2(route.north_m[i + 1] - route.north_m[i], route.east_m[i + 1] - route.east_m[i])
    return float(route.east_m[i]), float(route.north_m[i]), yaw


@pytest.fixture(scope="module")
def frames() -> dict[float, StereoFrame]:
    renderer = StereoRenderer(load_scenario().world)
    return {at: renderer.render(course_pose(at), np.random.default_rng(int(at))) for at in COURSE_POINTS_M}


def band_10_35(frame: StereoFrame) -> np.ndarray:
    return np.isfinite(frame.disparity_px) & (frame.depth_m >= 10.0) & (frame.depth_m <= 35.0)


def high_pass(image: np.ndarray) -> np.ndarray:
    image = image.astype(np.float32)
    return image - cv2.blur(image, (5, 5))


def test_the_right_image_warped_by_the_true_disparity_is_the_left_image(frames: dict[float, StereoFrame]) -> None:
    frame = frames[COURSE_POINTS_M[0]]
    assert len(frame.visible_obstacles()) >= 2  # the two passage rocks are in the test region
    height, width = frame.left.shape
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    disparity = np.nan_to_num(frame.disparity_px, nan=0.0)
    # Pixels whose surface the right camera also sees: its own truth agrees at the matching pixel.
    match = np.clip(np.rint(cols - disparity).astype(int), 0, width - 1)
    seen = np.abs(frame.right_disparity_px[rows.astype(int), match] - frame.disparity_px) < 0.5
    valid = band_10_35(frame) & seen & (cols - disparity >= 1)
    assert valid.sum() > 40_000
    left = high_pass(frame.left)[valid]

    def correlation(shift_px: float) -> float:
        warped = cv2.remap(frame.right.astype(np.float32), cols - disparity - shift_px, rows, cv2.INTER_LINEAR)
        return float(np.corrcoef(left, high_pass(warped)[valid])[0, 1])

    # Fine texture matches up to sensor noise and the cameras' gain mismatch (which correlation
    # ignores) at the true disparity, and stops matching a pixel away from it.
    exact = correlation(0.0)
    assert exact > 0.93
    assert correlation(1.0) < exact - 0.1 and correlation(-1.0) < exact - 0.1


@pytest.mark.parametrize("at_m", COURSE_POINTS_M)
def test_semi_global_matching_recovers_the_true_disparity(frames: dict[float, StereoFrame], at_m: float) -> None:
    frame = frames[at_m]
    matcher = cv2.StereoSGBM_create(
        minDisparity=0,
        numDisparities=64,
        blockSize=5,
        P1=8 * 25,
        P2=32 * 25,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
    )
    estimate = matcher.compute(frame.left, frame.right).astype(np.float32) / 16.0
    band = band_10_35(frame)
    found = band & (estimate > 0)
    assert found.sum() > 0.8 * band.sum()  # the texture is matchable almost everywhere in the band
    error = np.abs(estimate - frame.disparity_px)[found]
    assert np.median(error) < 1.0
    assert np.mean(error > 3.0) < 0.05
    on_obstacles = found & (frame.labels > 0)
    assert on_obstacles.sum() > 1000
    assert np.median(np.abs(estimate - frame.disparity_px)[on_obstacles]) < 1.0
