"""Simulated ESVS cameras: what one rendered 656x490 stereo pair costs, and whether OpenCV's
semi-global matcher recovers the true disparity from the renders.

Poses are spread evenly along the default scenario's route, facing along it, so the frames hold
what the course holds: desert ground, road edges, the scenario's rocks, shrubs, pole and car, the
wash and the berm. Each pair has sensor noise and the cameras' gain mismatch. OpenCV's own
threading is off (cv2.setNumThreads(1)): every number is one core's.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence

import cv2
import numpy as np
from rich.console import Console

from benchmarks.report import Table, machine_line, print_table
from modules.sim.camera import StereoFrame, StereoRenderer, render_pair
from modules.sim.scenario import load_scenario

TARGET_PAIRS_PER_S = 20.0
BAND_M = (10.0, 35.0)  # RASCAL's stereo working range
Pose = tuple[float, float, float]


def route_poses(step_m: float) -> list[Pose]:
    """Poses every ``step_m`` metres along the default route, facing along it."""
    route = load_scenario().route
    indices = np.arange(0, len(route.s_m) - 1, max(1, round(step_m / route.spacing_m)))
    heading = np.arctan2(
        route.north_m[indices + 1] - route.north_m[indices], route.east_m[indices + 1] - route.east_m[indices]
    )
    return [(float(route.east_m[i]), float(route.north_m[i]), float(h)) for i, h in zip(indices, heading, strict=True)]


def time_pairs(render: Callable[[Pose, np.random.Generator], object], poses: list[Pose]) -> list[float]:
    seconds = []
    for index, pose in enumerate(poses):
        start = time.perf_counter()
        render(pose, np.random.default_rng(index))
        seconds.append(time.perf_counter() - start)
    return seconds


def cost_row(label: str, seconds: list[float]) -> list[str]:
    ms = np.asarray(seconds) * 1e3
    p50, p99 = np.percentile(ms, [50, 99])
    return [label, f"{len(ms)}", f"{p50:.1f}", f"{p99:.1f}", f"{ms.max():.1f}", f"{1e3 / ms.mean():.1f}"]


def sgbm_errors(frame: StereoFrame, matcher: cv2.StereoSGBM) -> tuple[np.ndarray, int, np.ndarray]:
    """(absolute errors of the matched band pixels, band pixels with truth, errors on obstacles)."""
    estimate = matcher.compute(frame.left, frame.right).astype(np.float32) / 16.0
    band = np.isfinite(frame.disparity_px) & (frame.depth_m >= BAND_M[0]) & (frame.depth_m <= BAND_M[1])
    found = band & (estimate > 0)
    error = np.abs(estimate - frame.disparity_px)
    return error[found], int(band.sum()), error[found & (frame.labels > 0)]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_camera", description=__doc__.splitlines()[0])
    parser.add_argument("--step-m", type=float, default=10.0, help="route distance between rendered poses")
    parser.add_argument("--sgbm-frames", type=int, default=12, help="frames checked with StereoSGBM")
    args = parser.parse_args(argv)
    if args.step_m <= 0 or args.sgbm_frames < 1:
        parser.error("--step-m must be positive and --sgbm-frames at least 1")
    cv2.setNumThreads(1)
    console = Console()
    console.print(machine_line("simulated cameras"), markup=False, highlight=False, soft_wrap=True)
    world = load_scenario().world
    poses = route_poses(args.step_m)
    renderer = StereoRenderer(world)
    renderer.render(poses[0], np.random.default_rng(0))  # textures and rays are built once, here

    costs = Table(
        f"One 656x490 stereo pair along the default route, one core (target >= {TARGET_PAIRS_PER_S:.0f} pairs/s)",
        ["render", "pairs", "p50 ms", "p99 ms", "max ms", "pairs/s"],
    )
    grey = time_pairs(renderer.render, poses)
    costs.add(*cost_row("StereoRenderer.render, grey", grey))
    costs.add(
        *cost_row("StereoRenderer.render, grey + BGR", time_pairs(lambda p, r: renderer.render(p, r, True), poses))
    )
    costs.add(
        *cost_row(
            "render_pair (renderer looked up per call)", time_pairs(lambda p, r: render_pair(world, p, rng=r), poses)
        )
    )
    print_table(console, costs)

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
    accuracy = Table(
        f"StereoSGBM (block 5, 64 disparities) against the truth, {BAND_M[0]:.0f}-{BAND_M[1]:.0f} m band",
        ["frames", "median |error| px", "bad > 1 px", "bad > 3 px", "matched", "obstacle median px"],
    )
    chosen = np.linspace(0, len(poses) - 1, min(args.sgbm_frames, len(poses))).astype(int)
    errors, obstacle_errors, judged = [], [], 0
    for index in chosen:
        error, band, on_obstacles = sgbm_errors(
            renderer.render(poses[index], np.random.default_rng(int(index))), matcher
        )
        errors.append(error)
        obstacle_errors.append(on_obstacles)
        judged += band
    error, on_obstacles = np.concatenate(errors), np.concatenate(obstacle_errors)
    accuracy.add(
        f"{len(chosen)}",
        f"{np.median(error):.2f}",
        f"{np.mean(error > 1.0):.1%}",
        f"{np.mean(error > 3.0):.1%}",
        f"{error.size / max(judged, 1):.1%}",
        f"{np.median(on_obstacles):.2f}" if on_obstacles.size else "-",
    )
    print_table(console, accuracy)
    rate = 1.0 / float(np.mean(grey))
    verdict = "PASS" if rate >= TARGET_PAIRS_PER_S else "MISS"
    console.print(
        f"{verdict}  {rate:.1f} grey pairs/s on one core (target {TARGET_PAIRS_PER_S:.0f})",
        markup=False,
        highlight=False,
        soft_wrap=True,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
