"""Disparity accuracy on real rectified pairs with ground truth: our matcher beside OpenCV's defaults.

``rascal esvs eval --left L --right R --gt G [--gt-scale S]`` (or ``--pair DIR`` with a meta.json)
prints bad-pixel rates (> 1 px, > 3 px) and density for both matchers, counted two ways:

* over ALL pixels with ground truth, a pixel without a prediction counting as bad (the fair
  comparison between a dense and a sparse matcher);
* over the ground-truth pixels each matcher predicted (its accuracy where it answers).

Ground truth formats: KITTI 16-bit PNG (value / 256, 0 invalid), Middlebury 8-bit PNG or PGM
(value / scale, 0 invalid; the scale is per data set, so it must be given), PFM (value / scale,
+inf invalid, rows stored bottom to top).

``rascal esvs eval --simulated [--scenes N] [--clear-frames M] [--seed S]`` instead scores the whole
obstacle pipeline on rendered scenes with known obstacles: recall, precision and range error by
range band, and false descriptors on clear terrain (``modules.esvs.scenes_eval``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from modules.esvs.vision.disparity import ACCURATE, MatcherParams, compute_disparity

THRESHOLDS_PX = (1.0, 3.0)


class Scores(NamedTuple):
    """One matcher against one ground truth. Rates are fractions (0..1)."""

    bad1_all: float  # of GT pixels: missing or off by more than 1 px
    bad3_all: float  # of GT pixels: missing or off by more than 3 px
    bad1_predicted: float  # of GT pixels with a prediction: off by more than 1 px
    bad3_predicted: float
    density: float  # share of GT pixels with a prediction
    mean_error_px: float  # mean absolute error over the GT pixels with a prediction


class Pair(NamedTuple):
    left: np.ndarray  # grey uint8
    right: np.ndarray
    gt: np.ndarray  # float32 disparity in px, NaN without ground truth


# --- reading -------------------------------------------------------------------------------------


def read_pfm(path: Path) -> np.ndarray:
    """A PFM file as float32 rows top to bottom (the file stores them bottom to top); colour PFMs
    (``PF``) give their first channel."""
    with open(path, "rb") as stream:
        kind = stream.readline().strip()
        if kind not in (b"Pf", b"PF"):
            raise ValueError(f"{path}: not a PFM file (header {kind[:8]!r})")
        dims = stream.readline().split()
        while dims and dims[0].startswith(b"#"):
            dims = stream.readline().split()
        try:
            width, height = int(dims[0]), int(dims[1])
            scale = float(stream.readline().strip())
        except (IndexError, ValueError) as error:
            raise ValueError(f"{path}: bad PFM header") from error
        channels = 3 if kind == b"PF" else 1
        dtype = np.dtype("<f4") if scale < 0 else np.dtype(">f4")
        data = np.frombuffer(stream.read(), dtype=dtype)
    if data.size < width * height * channels:
        raise ValueError(f"{path}: {data.size} values for {width}x{height}x{channels}")
    image = data[: width * height * channels].reshape(height, width, channels)[..., 0]
    return np.flipud(image).astype(np.float32)


def write_pfm(path: Path, image: np.ndarray) -> None:
    """A float image as a little-endian grey PFM (rows written bottom to top)."""
    data = np.flipud(np.asarray(image, dtype="<f4"))
    with open(path, "wb") as stream:
        stream.write(b"Pf\n%d %d\n-1\n" % (data.shape[1], data.shape[0]))
        stream.write(np.ascontiguousarray(data).tobytes())


def read_disparity(path: Path, scale: float | None = None) -> np.ndarray:
    """Ground-truth disparity in pixels (float32), NaN where there is none.

    PNG/PGM: 16-bit values are KITTI's (scale 256 unless given), 8-bit ones Middlebury's, whose
    scale differs by data set and must be given; 0 is invalid. PFM: scale 1 unless given;
    infinities and NaNs are invalid."""
    path = Path(path)
    if scale is not None and not scale > 0:
        raise ValueError(f"scale must be positive, not {scale}")
    if path.suffix.lower() == ".pfm":
        raw = read_pfm(path)
        disparity = raw / np.float32(scale or 1.0)
        disparity[~np.isfinite(raw)] = np.nan
        return disparity
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ValueError(f"{path}: not a readable image")
    if raw.ndim != 2:
        raise ValueError(f"{path}: ground truth must be a single-channel image, got shape {raw.shape}")
    if raw.dtype == np.uint16:
        scale = scale or 256.0
    elif raw.dtype == np.uint8:
        if scale is None:
            raise ValueError(f"{path}: 8-bit ground truth needs its scale (Middlebury 2003 quarter size: 4, 2001: 8)")
    else:
        raise ValueError(f"{path}: unsupported ground-truth pixel type {raw.dtype}")
    disparity = raw.astype(np.float32) / np.float32(scale)
    disparity[raw == 0] = np.nan
    return disparity


def read_grey(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ValueError(f"{path}: not a readable image")
    return image


def load_pair(left: Path, right: Path, gt: Path, scale: float | None = None) -> Pair:
    pair = Pair(read_grey(left), read_grey(right), read_disparity(gt, scale))
    if not pair.left.shape == pair.right.shape == pair.gt.shape:
        raise ValueError(f"sizes differ: left {pair.left.shape}, right {pair.right.shape}, gt {pair.gt.shape}")
    return pair


def load_pair_dir(directory: Path) -> Pair:
    """A pair folder described by its meta.json (``left``, ``right``, ``gt``, ``gt_scale``)."""
    directory = Path(directory)
    try:
        meta = json.loads((directory / "meta.json").read_text())
        names = meta["left"], meta["right"], meta["gt"]
    except (OSError, ValueError, KeyError) as error:
        raise ValueError(f"{directory}: no usable meta.json ({error})") from error
    return load_pair(*(directory / name for name in names), scale=float(meta.get("gt_scale") or 1.0))


# --- scoring -------------------------------------------------------------------------------------


def score(predicted: np.ndarray, gt: np.ndarray) -> Scores:
    """Bad-pixel rates and density of ``predicted`` (NaN = no prediction) against ``gt`` (NaN = no
    ground truth). Raises if there is no ground truth at all."""
    if predicted.shape != gt.shape:
        raise ValueError(f"prediction {predicted.shape} and ground truth {gt.shape} differ in size")
    truth = np.isfinite(gt)
    total = int(truth.sum())
    if total == 0:
        raise ValueError("the ground truth has no valid pixel")
    answered = truth & np.isfinite(predicted)
    errors = np.abs(predicted[answered] - gt[answered])
    count = errors.size
    bad = [int((errors > threshold).sum()) for threshold in THRESHOLDS_PX]
    missing = total - count
    return Scores(
        bad1_all=(bad[0] + missing) / total,
        bad3_all=(bad[1] + missing) / total,
        bad1_predicted=bad[0] / count if count else math.nan,
        bad3_predicted=bad[1] / count if count else math.nan,
        density=count / total,
        mean_error_px=float(errors.mean()) if count else math.nan,
    )


def disparities_needed(gt: np.ndarray) -> int:
    """The smallest multiple of 16 whose search range [0, n) contains the largest true disparity."""
    largest = float(np.nanmax(gt))
    return (int(largest) // 16 + 1) * 16


def opencv_default(left: np.ndarray, right: np.ndarray, num_disparities: int) -> np.ndarray:
    """OpenCV StereoSGBM with its default parameters, only numDisparities set; NaN where invalid."""
    fixed = cv2.StereoSGBM_create(numDisparities=num_disparities).compute(left, right)
    disparity = fixed.astype(np.float32) / 16
    disparity[fixed <= 0] = np.nan
    return disparity


def ours(left: np.ndarray, right: np.ndarray, num_disparities: int, params: MatcherParams = ACCURATE) -> np.ndarray:
    """Our matcher for whole real pairs: the ACCURATE set over the same disparity range."""
    return compute_disparity(left, right, replace(params, num_disparities=num_disparities))


def compare(pair: Pair, params: MatcherParams = ACCURATE) -> dict[str, tuple[Scores, float, np.ndarray]]:
    """Both matchers on ``pair``: name -> (scores, seconds, disparity)."""
    span = disparities_needed(pair.gt)
    runs = {}
    for name, run in (
        ("ours", lambda: ours(pair.left, pair.right, span, params)),
        ("OpenCV SGBM defaults", lambda: opencv_default(pair.left, pair.right, span)),
    ):
        start = time.perf_counter()
        disparity = run()
        runs[name] = (score(disparity, pair.gt), time.perf_counter() - start, disparity)
    return runs


# --- command line --------------------------------------------------------------------------------


def format_table(runs: dict[str, tuple[Scores, float, np.ndarray]]) -> str:
    columns = ["matcher", ">1px all", ">3px all", ">1px pred", ">3px pred", "density", "mean err", "time"]
    rows = [columns]
    for name, (scores, seconds, _) in runs.items():
        rows.append(
            [
                name,
                f"{scores.bad1_all:.1%}",
                f"{scores.bad3_all:.1%}",
                f"{scores.bad1_predicted:.1%}",
                f"{scores.bad3_predicted:.1%}",
                f"{scores.density:.1%}",
                f"{scores.mean_error_px:.2f} px",
                f"{seconds * 1e3:.0f} ms",
            ]
        )
    widths = [max(len(row[i]) for row in rows) for i in range(len(columns))]
    lines = [
        "  ".join([row[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(row[1:], widths[1:], strict=False)])
        for row in rows
    ]
    lines.insert(1, "-" * len(lines[0]))
    return "\n".join(lines)


NOTE = (
    '"all": over every pixel with ground truth, a pixel without a prediction counting as bad. '
    '"pred": over the ground-truth pixels the matcher predicted. density: share of ground-truth '
    "pixels predicted. Both matchers search the same range, the ground truth's largest disparity "
    "rounded up to a multiple of 16."
)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="rascal esvs eval", description=__doc__.splitlines()[0])
    parser.add_argument("--pair", type=Path, help="a folder with meta.json naming left, right, gt and gt_scale")
    parser.add_argument("--left", type=Path, help="rectified left image (the reference view)")
    parser.add_argument("--right", type=Path, help="rectified right image")
    parser.add_argument("--gt", type=Path, help="left-view ground-truth disparity: PNG, PGM or PFM")
    parser.add_argument("--gt-scale", type=float, help="disparity = stored value / this (KITTI 256, PFM 1)")
    parser.add_argument("--out", type=Path, help="also write our disparity here as PFM (+inf where none)")
    simulated = parser.add_argument_group("simulated scenes (obstacle detection, not disparity)")
    simulated.add_argument("--simulated", action="store_true", help="score obstacles on rendered scenes instead")
    simulated.add_argument("--scenes", type=int, help="scenes with obstacles (default 100)")
    simulated.add_argument("--clear-frames", type=int, help="frames of clear terrain (default 200)")
    simulated.add_argument("--seed", type=int, help="seed of the random scenes (default 2005)")
    args = parser.parse_args(argv)
    if args.simulated:
        return _simulated(parser, args)
    if args.scenes is not None or args.clear_frames is not None or args.seed is not None:
        parser.error("--scenes, --clear-frames and --seed go with --simulated")
    try:
        if args.pair is not None:
            if args.left or args.right or args.gt:
                parser.error("give --pair or --left/--right/--gt, not both")
            pair = load_pair_dir(args.pair)
        else:
            if not (args.left and args.right and args.gt):
                parser.error("need --left, --right and --gt (or --pair DIR)")
            pair = load_pair(args.left, args.right, args.gt, args.gt_scale)
        runs = compare(pair)
    except (OSError, ValueError) as error:
        print(f"rascal esvs eval: {error}", file=sys.stderr)
        return 2
    height, width = pair.gt.shape
    print(f"{width}x{height}, ground truth on {np.isfinite(pair.gt).mean():.1%} of pixels")
    print(format_table(runs))
    print(NOTE)
    if args.out is not None:
        disparity = runs["ours"][2]
        write_pfm(args.out, np.where(np.isfinite(disparity), disparity, np.inf))
    return 0


def _simulated(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    if any(value is not None for value in (args.pair, args.left, args.right, args.gt, args.gt_scale, args.out)):
        parser.error("--simulated renders its own scenes: no --pair, --left, --right, --gt, --gt-scale or --out")
    from modules.esvs.scenes_eval import evaluate as evaluate_scenes
    from modules.esvs.scenes_eval import format_report

    try:
        result = evaluate_scenes(
            scenes=100 if args.scenes is None else args.scenes,
            clear_frames=200 if args.clear_frames is None else args.clear_frames,
            seed=2005 if args.seed is None else args.seed,
        )
    except ValueError as error:
        print(f"rascal esvs eval: {error}", file=sys.stderr)
        return 2
    print(format_report(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
