"""ESVS vision pipeline at 656x490: the matcher choice (accuracy and cost), obstacle and lane-border
accuracy, per-stage cost, and frames per second on one thread and on two (two frames in flight).

Frames are rendered by the simulated cameras (modules.sim.camera): along the default scenario's
route (desert ground, road edges, the scenario's obstacles) for cost, matching and lane borders;
with random boxes and cylinders 10-35 m ahead of the cameras for obstacles. OpenCV's own
threading is off (cv2.setNumThreads(1)), so "one thread" is one core and "two threads" at most two.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import cv2
import numpy as np
from rich.console import Console

from benchmarks.report import Table, machine_line, print_table
from brain.pose import Pose
from modules.esvs.geometry import RASCAL_RIG
from modules.esvs.vision import STAGES, VisionParams, process
from modules.esvs.vision.band import Band, BandParams, band_disparity, band_rows
from modules.esvs.vision.disparity import REALTIME, MatcherParams
from modules.sim.camera import StereoFrame, render_pair
from modules.sim.scenario import load_scenario
from modules.sim.world import LaneBorderLine, Shape, Texture, World, WorldObstacle

# (label, band, matcher): the candidates measured for the real-time matcher.
MATCHERS: list[tuple[str, BandParams, MatcherParams]] = [
    ("SGBM block 5", BandParams(), MatcherParams(mode="sgbm", block_size=5, texture_threshold=1.0)),
    ("HH4 block 5", BandParams(), MatcherParams(mode="hh4", block_size=5, texture_threshold=1.0)),
    ("3-way block 5", BandParams(), MatcherParams(block_size=5, texture_threshold=1.0)),
    ("3-way block 7", BandParams(), MatcherParams(block_size=7, texture_threshold=1.0)),
    ("BM block 11 (chosen)", BandParams(), REALTIME),
    ("BM block 11, no texture check", BandParams(), replace(REALTIME, texture_threshold=0.0)),
    ("BM block 11, 48 disparities", BandParams(), replace(REALTIME, num_disparities=48)),
    ("BM block 11, band to 1.5 m", BandParams(obstacle_height_m=1.5), REALTIME),
]
FULL_FRAME = Band(0, RASCAL_RIG.height_px)


def render_frames(count: int) -> list[StereoFrame]:
    """``count`` frames from poses spread along the default scenario's route."""
    scenario = load_scenario()
    route = scenario.route
    frames = []
    for index in np.linspace(0, len(route.east_m) - 2, count).astype(int):
        heading = np.arctan2(
            route.north_m[index + 1] - route.north_m[index], route.east_m[index + 1] - route.east_m[index]
        )
        pose = (float(route.east_m[index]), float(route.north_m[index]), float(heading))
        frames.append(render_pair(scenario.world, pose, RASCAL_RIG, np.random.default_rng(int(index))))
    return frames


def matcher_row(label: str, band: Band, params: MatcherParams, frames: list[StereoFrame], repeats: int) -> list[str]:
    """Cost and accuracy on pixels 8-40 m from the cameras: bad (> 1 px) among the matched,
    density among those with truth, and wrong matches on the sky (no truth)."""
    fb = RASCAL_RIG.focal_px * RASCAL_RIG.baseline_m
    seconds, bad, matched, judged, sky_matched, sky = [], 0, 0, 0, 0, 0
    for frame in frames:
        truth = frame.disparity_px[band.top : band.bottom]
        disparity = band_disparity(frame.left, frame.right, band, params)  # as the pipeline matches it
        for _ in range(repeats):
            start = time.perf_counter()
            band_disparity(frame.left, frame.right, band, params)
            seconds.append(time.perf_counter() - start)
        in_range = (truth >= fb / 40) & (truth <= fb / 8)
        in_range[:, : params.num_disparities] = False  # no matcher can reach these columns
        found = in_range & np.isfinite(disparity)
        bad += int((np.abs(disparity[found] - truth[found]) > 1.0).sum())
        matched, judged = matched + int(found.sum()), judged + int(in_range.sum())
        no_truth = ~np.isfinite(truth)
        sky, sky_matched = sky + int(no_truth.sum()), sky_matched + int((no_truth & np.isfinite(disparity)).sum())
    return [
        label,
        f"{band.rows}",
        f"{np.median(seconds) * 1e3:.1f}",
        f"{bad / max(matched, 1):.2%}",
        f"{matched / max(judged, 1):.1%}",
        f"{sky_matched / max(sky, 1):.1%}" if sky else "-",
    ]


def random_obstacles(rng: np.random.Generator, count: int) -> tuple[WorldObstacle, ...]:
    """Boxes and cylinders 0.5-2 m tall, 10-35 m ahead of the cameras, at least 4 m apart."""
    obstacles: list[WorldObstacle] = []
    textures = list(Texture)
    while len(obstacles) < count:
        distance, bearing = rng.uniform(10.0, 35.0), rng.uniform(-0.25, 0.25)
        x, y = RASCAL_RIG.mount_forward_m + distance * math.cos(bearing), distance * math.sin(bearing)
        if any(math.hypot(x - o.east_m, y - o.north_m) < 4.0 for o in obstacles):
            continue
        height, texture, name = rng.uniform(0.5, 2.0), textures[rng.integers(len(textures))], f"o{len(obstacles)}"
        if rng.random() < 0.5:
            shape = WorldObstacle(name, Shape.CYLINDER, x, y, height, radius_m=rng.uniform(0.2, 1.0), texture=texture)
        else:
            size = rng.uniform(0.5, 2.0, 2)
            yaw = rng.uniform(-1.0, 1.0)
            shape = WorldObstacle(
                name, Shape.BOX, x, y, height, length_m=size[0], width_m=size[1], yaw_rad=yaw, texture=texture
            )
        obstacles.append(shape)
    return tuple(obstacles)


def nearest_range(obstacle: WorldObstacle) -> float:
    """Distance from the vehicle origin (pose 0, 0, 0) to the obstacle's nearest footprint point."""
    if obstacle.shape is Shape.CYLINDER:
        return math.hypot(obstacle.east_m, obstacle.north_m) - obstacle.radius_m
    c, s = math.cos(obstacle.yaw_rad), math.sin(obstacle.yaw_rad)
    a, b = np.meshgrid(np.linspace(-0.5, 0.5, 41) * obstacle.length_m, np.linspace(-0.5, 0.5, 41) * obstacle.width_m)
    return float(np.hypot(obstacle.east_m + c * a - s * b, obstacle.north_m + s * a + c * b).min())


def obstacle_table(scenes: int) -> Table:
    """Detection and range error of obstacles showing at least 200 pixels, by range band; an
    obstacle is found by a descriptor within 0.05 rad of its bearing and 20 % of its range."""
    rng = np.random.default_rng(2005)
    bands = ((10.0, 20.0), (20.0, 30.0), (30.0, 37.0))
    errors: dict[tuple[float, float], list[float]] = {band: [] for band in bands}
    shown = dict.fromkeys(bands, 0)
    extra = 0
    for index in range(scenes):
        obstacles = random_obstacles(rng, 3)
        frame = render_pair(World(obstacles=obstacles), (0.0, 0.0, 0.0), RASCAL_RIG, np.random.default_rng(index))
        found, _, _ = process(frame.left, frame.right, RASCAL_RIG)
        visible = frame.visible_obstacles()
        used = set()
        for obstacle in obstacles:
            truth = nearest_range(obstacle)
            band = next((b for b in bands if b[0] <= truth - RASCAL_RIG.mount_forward_m < b[1]), None)
            if band is None or visible.get(obstacle.name, 0) < 200:
                continue
            shown[band] += 1
            bearing = math.atan2(obstacle.north_m, obstacle.east_m)
            near = [
                (abs(o.range_m - truth), i)
                for i, o in enumerate(found.obstacles)
                if abs(math.atan2(o.y_m, o.x_m) - bearing) < 0.05 and abs(o.range_m - truth) < 0.2 * truth
            ]
            if near:
                error, best = min(near)
                used.add(best)
                errors[band].append(error / truth)
        extra += len(found.obstacles) - len(used)
    table = Table(
        f"Obstacles on {scenes} rendered scenes of 3 random boxes and cylinders (extra descriptors: {extra})",
        ["range from cameras", "shown", "found", "range error p50", "p95", "within 5 %"],
    )
    for band in bands:
        found_errors = np.asarray(errors[band])
        cells = ["-", "-", "-"]
        if found_errors.size:
            p50, p95 = np.percentile(found_errors, [50, 95])
            cells = [f"{p50:.1%}", f"{p95:.1%}", f"{np.mean(found_errors <= 0.05):.0%}"]
        table.add(f"{band[0]:.0f}-{band[1]:.0f} m", str(shown[band]), str(found_errors.size), *cells)
    return table


def lane_table(frames: list[StereoFrame], lines: tuple[LaneBorderLine, ...]) -> Table:
    """Road edges in view (at least 8 of 24 points 10.4-33.4 m ahead of the cameras inside the
    image) against the borders found: a border finds an edge when it stays within 0.5 m of it
    over the part of that range both cover (at least 4 m)."""
    shown = hits = extra = 0
    worst: list[float] = []
    xs = np.linspace(12.0, 35.0, 24)
    for frame in frames:
        _, found, _ = process(frame.left, frame.right, RASCAL_RIG)
        used = set()
        for line in lines:
            ys = _line_in_vehicle_frame(line, frame.pose, xs)
            if ys is None:
                continue
            u, _, _ = RASCAL_RIG.project(np.column_stack([xs, ys, np.zeros_like(xs)]))
            seen = (u > 40) & (u < RASCAL_RIG.width_px - 6)
            if seen.sum() < 8:
                continue
            shown += 1
            best = None
            for index, border in enumerate(found.borders):
                both = seen & (xs >= border.x_min_m) & (xs <= border.x_max_m)
                if both.sum() < 9:
                    continue
                gap = float(np.abs(border.c0_m + border.c1 * xs + border.c2_per_m * xs**2 - ys)[both].max())
                if gap < 0.5 and (best is None or gap < best[0]):
                    best = (gap, index)
            if best is not None:
                hits += 1
                worst.append(best[0])
                used.add(best[1])
        extra += len(found.borders) - len(used)
    table = Table(
        f"Road edges on {len(frames)} frames along the route", ["edges shown", "found", "extra borders", "max gap p50"]
    )
    table.add(str(shown), str(hits), str(extra), f"{np.median(worst):.2f} m" if worst else "-")
    return table


def _line_in_vehicle_frame(line: LaneBorderLine, pose: Pose, xs: np.ndarray) -> np.ndarray | None:
    """Lateral position of a polyline at the given forward distances, None unless the line
    runs steadily forward (or back) through all of them."""
    points = np.asarray(line.points_m)
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    dx, dy = points[:, 0] - pose.east_m, points[:, 1] - pose.north_m
    x, y = c * dx + s * dy, -s * dx + c * dy
    ahead = (x > xs[0] - 5) & (x < xs[-1] + 5)
    steps = np.diff(x[ahead])
    if steps.size < 1 or not (np.all(steps > 0) or np.all(steps < 0)):
        return None
    order = np.argsort(x[ahead])
    xa, ya = x[ahead][order], y[ahead][order]
    if xa[0] > xs[0] or xa[-1] < xs[-1]:
        return None
    return np.interp(xs, xa, ya)


def stage_table(frames: list[StereoFrame], rounds: int) -> tuple[Table, list[float]]:
    samples: dict[str, list[float]] = {stage: [] for stage in STAGES}
    totals = []
    for _ in range(rounds):
        for frame in frames:
            start = time.perf_counter()
            _, _, stats = process(frame.left, frame.right, RASCAL_RIG)
            totals.append(time.perf_counter() - start)
            for stage, seconds in stats.timings_s.items():
                samples[stage].append(seconds)
    table = Table("ESVS pipeline, one thread: cost per stage (ms)", ["stage", "p50", "p99", "mean"])
    for stage, values in samples.items():
        table.add(stage, *_ms(values))
    table.add("whole process()", *_ms(totals))
    return table, totals


def throughput(frames: list[StereoFrame], workers: int, seconds: float) -> tuple[float, float]:
    """Frames per second with ``workers`` frames in flight, each on its own thread, and the
    process's CPU seconds per frame (what other load on the machine cannot inflate)."""
    job: Callable[[StereoFrame], object] = lambda frame: process(frame.left, frame.right, RASCAL_RIG)  # noqa: E731
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(job, frames[:workers]))  # each thread builds its matcher first
        done, start, cpu_start = 0, time.perf_counter(), time.process_time()
        pending = [pool.submit(job, frames[i % len(frames)]) for i in range(workers)]
        while time.perf_counter() - start < seconds:
            pending.pop(0).result()
            done += 1
            pending.append(pool.submit(job, frames[(done + workers) % len(frames)]))
        for future in pending:
            future.result()
        done += len(pending)
        elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    return done / elapsed, cpu / done


def _ms(values: list[float]) -> list[str]:
    p50, p99 = np.percentile(np.asarray(values) * 1e3, [50, 99])
    return [f"{p50:.2f}", f"{p99:.2f}", f"{np.mean(values) * 1e3:.2f}"]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_vision", description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=12, help="rendered frames along the route")
    parser.add_argument("--rounds", type=int, default=5, help="passes over the frames for the stage table")
    parser.add_argument("--seconds", type=float, default=4.0, help="duration of each throughput run")
    parser.add_argument("--repeats", type=int, default=3, help="timed matcher runs per frame and candidate")
    parser.add_argument("--obstacle-scenes", type=int, default=30, help="rendered scenes for the obstacle table")
    parser.add_argument("--skip-matchers", action="store_true", help="leave out the matcher comparison")
    parser.add_argument("--skip-accuracy", action="store_true", help="leave out the obstacle and lane tables")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    console = Console()
    console.print(machine_line("ESVS vision"), markup=False, highlight=False, soft_wrap=True)
    frames = render_frames(args.frames)
    lines = load_scenario().world.lane_borders
    process(frames[0].left, frames[0].right, RASCAL_RIG, VisionParams())  # lookup tables, first calls

    if not args.skip_matchers:
        table = Table(
            f"Matcher candidates on {len(frames)} rendered frames, one thread (pixels 8-40 m from the cameras)",
            ["matcher", "rows", "ms p50", "bad >1px of matched", "matched", "sky matched"],
        )
        for label, band_params, params in MATCHERS:
            table.add(*matcher_row(label, band_rows(RASCAL_RIG, band_params), params, frames, args.repeats))
        table.add(*matcher_row("3-way block 7, full frame", FULL_FRAME, REALTIME, frames, args.repeats))
        print_table(console, table)

    if not args.skip_accuracy:
        print_table(console, obstacle_table(args.obstacle_scenes))
        print_table(console, lane_table(frames, lines))

    stages, totals = stage_table(frames, args.rounds)
    print_table(console, stages)

    rates = Table(
        "ESVS pipeline throughput at 656x490",
        ["threads", "fps", "target", "CPU ms per frame", "cores busy"],
    )
    for label, workers, target in (("1 (sequential)", 1, ">= 30"), ("2 (two frames in flight)", 2, ">= 60")):
        fps, cpu = throughput(frames, workers, args.seconds)
        rates.add(label, f"{fps:.1f}", target, f"{cpu * 1e3:.1f}", f"{fps * cpu:.2f}")
    print_table(console, rates)
    console.print(
        f"one-thread latency of process(): p50 {np.median(totals) * 1e3:.1f} ms; "
        f"band rows {band_rows(RASCAL_RIG, BandParams())}",
        markup=False,
        highlight=False,
        soft_wrap=True,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
