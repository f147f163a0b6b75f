"""Disparity with OpenCV's block matcher or semi-global matcher, as float pixels with NaN where
there is no match.

Two parameter sets: ``REALTIME`` for the rig's row band at camera rate, chosen by measured accuracy
and speed (README), and ``ACCURATE`` for whole real image pairs, where density counts as much as
accuracy: wider blocks, a left-right check, and the holes it leaves filled from the background side.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np

_SGBM_MODES = {
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "hh": cv2.STEREO_SGBM_MODE_HH,
    "hh4": cv2.STEREO_SGBM_MODE_HH4,
}
MODES = (*_SGBM_MODES, "bm")  # bm: StereoBM, plain block matching (sum of absolute differences)


@dataclass(frozen=True)
class MatcherParams:
    """StereoSGBM / StereoBM settings (OpenCV names), plus what happens to the result."""

    num_disparities: int = 32  # multiple of 16; the search is [min_disparity, min_disparity + this)
    block_size: int = 5
    p1: int = 8  # SGBM's smoothness penalties per pixel of the block: P1 = p1 * block^2, P2 = p2 * block^2
    p2: int = 32
    uniqueness_ratio: int = 10
    speckle_window: int = 100
    speckle_range: int = 2  # pixels of disparity within one speckle
    disp12_max_diff: int = 1  # OpenCV's internal left-right check, in pixels; -1 disables it
    pre_filter_cap: int = 63  # at most 63
    mode: str = "3way"
    min_disparity: int = 0
    texture_threshold: float = 0.0  # reject matches whose block's mean |dI/dx| (grey levels/px) is lower
    fill: bool = False  # fill invalid runs along each row from their background (smaller) side

    def __post_init__(self) -> None:
        if self.num_disparities <= 0 or self.num_disparities % 16:
            raise ValueError(f"num_disparities must be a positive multiple of 16, not {self.num_disparities}")
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise ValueError(f"block_size must be odd and positive, not {self.block_size}")
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {sorted(MODES)}, not {self.mode!r}")
        if self.mode == "bm" and self.block_size < 5:
            raise ValueError(f"block_size must be at least 5 for bm, not {self.block_size}")
        if not 1 <= self.pre_filter_cap <= 63:
            raise ValueError(f"pre_filter_cap must be in 1..63, not {self.pre_filter_cap}")

    @property
    def border_rows(self) -> int:
        """Rows at the top and at the bottom of its input that the matcher leaves without a match."""
        return self.block_size // 2 if self.mode == "bm" else 0


# Chosen on rendered RASCAL scenes (README, "Choosing the matcher"). OpenCV's semi-global modes
# cost about the same per pixel whatever the block and the disparity range; its block matcher, with
# its own left-right check and speckle filter, costs half as much and was as accurate there, with
# fewer phantom obstacles; block 11 kept every obstacle apart that block 9 merged. 32 disparities
# reach 8.4 m, short of the 10 m near edge by a margin.
REALTIME = MatcherParams(mode="bm", block_size=11, pre_filter_cap=31, texture_threshold=1.0)

# Tuned on the three real pairs (README, "Real pairs"); num_disparities is set per pair. Strong
# smoothness and a wide speckle filter remove the small wrong patches that filling would spread.
ACCURATE = MatcherParams(
    num_disparities=128,
    block_size=3,
    p1=32,
    p2=128,
    uniqueness_ratio=10,
    speckle_window=800,
    speckle_range=1,
    mode="3way",
    fill=True,
)

_local = threading.local()


def matcher(params: MatcherParams) -> cv2.StereoMatcher:
    """A StereoBM or StereoSGBM for ``params``, one per thread: compute() keeps its work buffers in
    the object, so a matcher must never run in two threads at once, and making one per frame costs
    those buffers' allocation every frame."""
    cache: dict[MatcherParams, cv2.StereoMatcher] = _local.__dict__.setdefault("matchers", {})
    found = cache.get(params)
    if found is None:
        found = _block_matcher(params) if params.mode == "bm" else _semi_global_matcher(params)
        cache[params] = found
    return found


def _block_matcher(params: MatcherParams) -> cv2.StereoBM:
    found = cv2.StereoBM_create(params.num_disparities, params.block_size)
    found.setMinDisparity(params.min_disparity)
    found.setPreFilterType(cv2.STEREO_BM_PREFILTER_XSOBEL)  # what SGBM matches on too
    found.setPreFilterCap(params.pre_filter_cap)
    # StereoBM's own texture check sums |x-Sobel| (clipped at pre_filter_cap) over the block, as
    # texture() does (Sobel / 8 per pixel) but for the clipping, and spares the matching it rejects.
    found.setTextureThreshold(round(8 * params.block_size**2 * params.texture_threshold))
    found.setUniquenessRatio(params.uniqueness_ratio)
    found.setSpeckleWindowSize(params.speckle_window)
    found.setSpeckleRange(16 * params.speckle_range)  # StereoBM takes it in 1/16 px
    found.setDisp12MaxDiff(params.disp12_max_diff)
    return found


def _semi_global_matcher(params: MatcherParams) -> cv2.StereoSGBM:
    area = params.block_size * params.block_size
    return cv2.StereoSGBM_create(
        minDisparity=params.min_disparity,
        numDisparities=params.num_disparities,
        blockSize=params.block_size,
        P1=params.p1 * area,
        P2=params.p2 * area,
        disp12MaxDiff=params.disp12_max_diff,
        preFilterCap=params.pre_filter_cap,
        uniquenessRatio=params.uniqueness_ratio,
        speckleWindowSize=params.speckle_window,
        speckleRange=params.speckle_range,
        mode=_SGBM_MODES[params.mode],
    )


def compute_disparity(left: np.ndarray, right: np.ndarray, params: MatcherParams = REALTIME) -> np.ndarray:
    """Left-view disparity in pixels (float32), NaN where the matcher found none."""
    if left.shape != right.shape or left.ndim != 2 or left.dtype != np.uint8 or right.dtype != np.uint8:
        raise ValueError(f"need two grey uint8 images of one size, got {left.shape} {left.dtype}, {right.shape}")
    fixed = matcher(params).compute(left, right)  # int16, 1/16 px; invalid is (min_disparity - 1) * 16
    disparity = fixed.astype(np.float32) * np.float32(1 / 16)
    # Below min_disparity is the invalid mark; zero disparity is a point at infinity: no depth.
    disparity[fixed < max(params.min_disparity * 16, 1)] = np.nan
    if params.texture_threshold > 0 and params.mode != "bm":  # StereoBM checks it itself
        disparity[texture(left, params.block_size) < params.texture_threshold] = np.nan
    if params.fill:
        fill_holes(disparity)
    return disparity


def texture(image: np.ndarray, block_size: int) -> np.ndarray:
    """Mean absolute horizontal gradient over each block, in grey levels per pixel: what a
    matcher along rows has to go on. Sensor noise alone gives about 0.35 * its standard deviation."""
    gradient = np.abs(cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3))
    return cv2.boxFilter(gradient, -1, (block_size, block_size), normalize=True) * np.float32(1 / 8)


def fill_holes(disparity: np.ndarray) -> None:
    """Fill NaN runs in place, row by row, with the smaller of the disparities bounding each run:
    most holes left by the left-right check are occlusions, which belong to the background."""
    valid = np.isfinite(disparity)
    width = disparity.shape[1]
    columns = np.broadcast_to(np.arange(width), disparity.shape)
    # Index of the nearest valid pixel to the left and to the right of each pixel, per row.
    left_index = np.maximum.accumulate(np.where(valid, columns, -1), axis=1)
    right_index = np.minimum.accumulate(np.where(valid, columns, width)[:, ::-1], axis=1)[:, ::-1]
    rows = np.arange(disparity.shape[0])[:, None]
    from_left = np.where(left_index >= 0, disparity[rows, np.clip(left_index, 0, width - 1)], np.inf)
    from_right = np.where(right_index < width, disparity[rows, np.clip(right_index, 0, width - 1)], np.inf)
    filled = np.minimum(from_left, from_right)
    holes = ~valid & np.isfinite(filled)
    disparity[holes] = filled[holes]
