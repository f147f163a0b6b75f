"""The evaluation tool: metrics on hand-made arrays, the three ground-truth formats, the command
line, and our matcher against OpenCV's defaults on the real pairs (when present)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from modules.esvs import evaluate
from modules.esvs.evaluate import (
    compare,
    disparities_needed,
    load_pair_dir,
    main,
    read_disparity,
    read_pfm,
    score,
    write_pfm,
)
from tests.conftest import ROOT

STEREO_DATA = ROOT.parent / "shared" / "data" / "stereo"
REAL_PAIRS = ("eth3d_terrace", "kitti2015_000001_10", "middlebury2003_teddy")


def test_scores_count_missing_predictions_as_bad_only_over_all_pixels() -> None:
    gt = np.array([[10.0, 10.0, 10.0, 10.0], [10.0, np.nan, 10.0, 10.0]])
    predicted = np.array([[10.5, 11.5, 14.0, np.nan], [np.nan, 3.0, 10.0, 9.2]])
    s = score(predicted, gt)
    # 7 GT pixels; 5 predicted: errors 0.5, 1.5, 4.0, 0.0, 0.8.
    assert s.density == pytest.approx(5 / 7)
    assert s.bad1_predicted == pytest.approx(2 / 5) and s.bad3_predicted == pytest.approx(1 / 5)
    assert s.bad1_all == pytest.approx(4 / 7) and s.bad3_all == pytest.approx(3 / 7)
    assert s.mean_error_px == pytest.approx((0.5 + 1.5 + 4.0 + 0.0 + 0.8) / 5)


def test_scores_of_a_silent_matcher_and_of_empty_ground_truth() -> None:
    gt = np.full((2, 2), 5.0)
    s = score(np.full((2, 2), np.nan), gt)
    assert s.bad3_all == 1.0 and s.density == 0.0 and math.isnan(s.bad3_predicted)
    with pytest.raises(ValueError, match="no valid pixel"):
        score(gt, np.full((2, 2), np.nan))
    with pytest.raises(ValueError, match="differ in size"):
        score(gt, np.ones((3, 2)))


def test_kitti_png_is_value_over_256_with_zero_invalid(tmp_path: Path) -> None:
    raw = np.array([[0, 256, 512 + 128]], np.uint16)
    cv2.imwrite(str(tmp_path / "gt.png"), raw)
    np.testing.assert_array_equal(read_disparity(tmp_path / "gt.png"), [[np.nan, 1.0, 2.5]])


def test_middlebury_png_and_pgm_need_their_scale(tmp_path: Path) -> None:
    raw = np.array([[0, 4, 210]], np.uint8)
    for name in ("gt.png", "gt.pgm"):
        cv2.imwrite(str(tmp_path / name), raw)
        np.testing.assert_array_equal(read_disparity(tmp_path / name, scale=4), [[np.nan, 1.0, 52.5]])
        with pytest.raises(ValueError, match="needs its scale"):
            read_disparity(tmp_path / name)


def test_pfm_rows_are_bottom_up_and_inf_is_invalid(tmp_path: Path) -> None:
    # Written by hand: the first stored row is the image's bottom row.
    stored = np.array([[1.0, np.inf], [3.0, 4.0]], "<f4")
    (tmp_path / "gt.pfm").write_bytes(b"Pf\n2 2\n-1.0\n" + stored.tobytes())
    np.testing.assert_array_equal(read_disparity(tmp_path / "gt.pfm"), [[3.0, 4.0], [1.0, np.nan]])
    # Big-endian (positive scale), and a colour PFM's first channel.
    (tmp_path / "be.pfm").write_bytes(b"Pf\n2 1\n1.0\n" + np.array([7.0, 8.0], ">f4").tobytes())
    np.testing.assert_array_equal(read_pfm(tmp_path / "be.pfm"), [[7.0, 8.0]])
    colour = np.array([[1, 2, 3, 4, 5, 6]], "<f4")
    (tmp_path / "rgb.pfm").write_bytes(b"PF\n2 1\n-1\n" + colour.tobytes())
    np.testing.assert_array_equal(read_pfm(tmp_path / "rgb.pfm"), [[1.0, 4.0]])


def test_pfm_round_trip_and_bad_files(tmp_path: Path) -> None:
    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    write_pfm(tmp_path / "x.pfm", image)
    np.testing.assert_array_equal(read_pfm(tmp_path / "x.pfm"), image)
    (tmp_path / "bad.pfm").write_bytes(b"P6\n1 1\n255\n\0\0\0")
    with pytest.raises(ValueError, match="not a PFM"):
        read_pfm(tmp_path / "bad.pfm")
    (tmp_path / "short.pfm").write_bytes(b"Pf\n4 4\n-1\n" + bytes(8))
    with pytest.raises(ValueError, match="values for"):
        read_pfm(tmp_path / "short.pfm")
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(ValueError, match="not a readable image"):
        read_disparity(tmp_path / "junk.png")


def test_the_search_range_covers_the_largest_true_disparity() -> None:
    assert disparities_needed(np.array([[np.nan, 12.5, 52.75]])) == 64
    assert disparities_needed(np.array([[78.5]])) == 80
    assert disparities_needed(np.array([[80.0]])) == 96


def synthetic_pair(tmp_path: Path, shift: int = 9) -> tuple[Path, Path, Path]:
    """Smooth random texture seen with a constant disparity; KITTI-encoded ground truth."""
    rng = np.random.default_rng(0)
    wide = cv2.GaussianBlur(rng.uniform(0, 255, (80, 240 + shift)).astype(np.float32), (0, 0), 1.2)
    wide = np.clip((wide - wide.mean()) * 4 + 128, 0, 255).astype(np.uint8)
    left, right = wide[:, :-shift], wide[:, shift:]  # a point at column c shows at c - shift on the right
    gt = np.full(left.shape, shift * 256, np.uint16)
    paths = tmp_path / "left.png", tmp_path / "right.png", tmp_path / "gt.png"
    for path, image in zip(paths, (left, right, gt), strict=True):
        cv2.imwrite(str(path), image)
    return paths


def test_the_command_line_prints_both_matchers(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    left, right, gt = synthetic_pair(tmp_path)
    out = tmp_path / "ours.pfm"
    assert main(["--left", str(left), "--right", str(right), "--gt", str(gt), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "ours" in printed and "OpenCV SGBM defaults" in printed and "counting as bad" in printed
    ours = read_pfm(out)
    assert np.median(ours[np.isfinite(ours)]) == pytest.approx(9.0, abs=0.1)


def test_the_command_line_reads_a_pair_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    synthetic_pair(tmp_path)
    meta = {"left": "left.png", "right": "right.png", "gt": "gt.png", "gt_scale": 256.0}
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    assert main(["--pair", str(tmp_path)]) == 0
    assert "ours" in capsys.readouterr().out


def test_the_command_line_reports_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    left, right, _ = synthetic_pair(tmp_path)
    assert main(["--left", str(left), "--right", str(right), "--gt", str(tmp_path / "missing.png")]) == 2
    assert "rascal esvs eval:" in capsys.readouterr().err
    assert main(["--pair", str(tmp_path / "nowhere")]) == 2
    with pytest.raises(SystemExit):
        main(["--left", str(left)])


def real_pair(name: str) -> Path:
    directory = STEREO_DATA / name
    if not (directory / "meta.json").is_file():
        pytest.skip(f"real stereo pair {name} not found at {directory} (shared data is outside the repo)")
    return directory


@pytest.mark.parametrize("name", REAL_PAIRS)
def test_ours_beats_opencv_defaults_on_each_real_pair(name: str) -> None:
    pair = load_pair_dir(real_pair(name))
    runs = compare(pair)
    ours, defaults = runs["ours"][0], runs["OpenCV SGBM defaults"][0]
    assert ours.bad3_all <= defaults.bad3_all
    assert ours.density > 0.99


def test_the_real_pairs_are_read_with_their_stated_scale() -> None:
    # SOURCES.md's ground-truth ranges: Teddy 12.5-52.75 px, KITTI 4.7-78.5, terrace 8.1-17.4.
    expected = {"middlebury2003_teddy": (12.5, 52.75), "kitti2015_000001_10": (4.7, 78.5), "eth3d_terrace": (8.1, 17.4)}
    for name, (low, high) in expected.items():
        gt = load_pair_dir(real_pair(name)).gt
        assert float(np.nanmin(gt)) == pytest.approx(low, abs=0.1)
        assert float(np.nanmax(gt)) == pytest.approx(high, abs=0.1)


def test_module_names_its_command() -> None:
    assert "rascal esvs eval" in (evaluate.__doc__ or "")
