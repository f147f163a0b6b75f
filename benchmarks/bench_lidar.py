"""Per-scan cost of the simulated horizontal lidar: ray-cast and clustering, beside a plain Python
ray-caster on the same scenes as an anchor.

A scan is 361 rays from the left horizontal lidar, with range noise, against 25 or 100 obstacles
(half cylinders, half boxes) scattered within 60 m of the vehicle, from a new vehicle heading
each time. The plain caster tests every ray against every obstacle; it also checks that the
vectorised caster returns the same ranges.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Sequence

import numpy as np
from rich.console import Console

from benchmarks.report import Table, print_table
from brain.pose import Pose
from modules.lidar.cluster import describe_scan
from modules.lidar.scan import HORIZONTAL_MOUNTS, ScanSpec, sensor_pose
from modules.sim.lidar.raycast import Scene, cast
from modules.sim.world import Shape, WorldObstacle

SCENE_SIZES = (25, 100)
MOUNT = HORIZONTAL_MOUNTS["lidar_h_left"]


def scene_obstacles(count: int, rng: np.random.Generator) -> list[WorldObstacle]:
    obstacles = []
    for i in range(count):
        distance, angle = rng.uniform(3.0, 60.0), rng.uniform(-math.pi, math.pi)
        east, north = distance * math.cos(angle), distance * math.sin(angle)
        if i % 2:
            obstacles.append(WorldObstacle(f"c{i}", Shape.CYLINDER, east, north, 2.0, radius_m=rng.uniform(0.2, 1.5)))
        else:
            length, width, yaw = rng.uniform(0.5, 4.0), rng.uniform(0.5, 4.0), rng.uniform(-math.pi, math.pi)
            obstacles.append(
                WorldObstacle(f"b{i}", Shape.BOX, east, north, 2.0, length_m=length, width_m=width, yaw_rad=yaw)
            )
    return obstacles


def plain_ranges(obstacles: list[WorldObstacle], pose: Pose, spec: ScanSpec) -> list[float]:
    """The anchor: every ray against every obstacle, one float at a time."""
    origin, yaw = sensor_pose(pose, MOUNT)
    ox, oy = float(origin[0]), float(origin[1])
    ranges = []
    for bearing in spec.bearings_rad():
        dx, dy = math.cos(yaw + bearing), math.sin(yaw + bearing)
        best = math.inf
        for obstacle in obstacles:
            if obstacle.height_m > MOUNT.z_m:
                best = min(best, _plain_hit(obstacle, ox, oy, dx, dy))
        ranges.append(best if best <= spec.max_range_m else math.inf)
    return ranges


def _plain_hit(obstacle: WorldObstacle, ox: float, oy: float, dx: float, dy: float) -> float:
    if obstacle.shape is Shape.CYLINDER:
        cx, cy = obstacle.east_m - ox, obstacle.north_m - oy
        along = dx * cx + dy * cy
        disc = along * along - (cx * cx + cy * cy - obstacle.radius_m**2)
        t = along - math.sqrt(disc) if disc >= 0 else -1.0
        return t if t > 0 else math.inf
    c, s = math.cos(obstacle.yaw_rad), math.sin(obstacle.yaw_rad)
    rx, ry = ox - obstacle.east_m, oy - obstacle.north_m
    near, far = -math.inf, math.inf
    for start, direction, half in (
        (rx * c + ry * s, dx * c + dy * s, obstacle.length_m / 2),
        (-rx * s + ry * c, -dx * s + dy * c, obstacle.width_m / 2),
    ):
        direction = direction if abs(direction) > 1e-12 else 1e-12
        t1, t2 = (-half - start) / direction, (half - start) / direction
        near, far = max(near, min(t1, t2)), min(far, max(t1, t2))
    return near if near <= far and near > 0 else math.inf


def percentiles_us(samples: list[float]) -> tuple[str, str]:
    p50, p99 = np.percentile(np.asarray(samples) * 1e6, [50, 99])
    return f"{p50:,.0f}", f"{p99:,.0f}"


def measure(count: int, scans: int, plain_scans: int, spec: ScanSpec) -> tuple[list[str], str]:
    """One table row (cast, cast + cluster, plain cast percentiles) and a note for one scene."""
    rng = np.random.default_rng(count)
    obstacles = scene_obstacles(count, rng)
    scene = Scene.from_obstacles(obstacles)
    poses = [Pose(0.0, 0.0, float(yaw)) for yaw in rng.uniform(-math.pi, math.pi, scans)]
    cast_s, total_s, clusters = [], [], 0
    for pose in poses:
        start = time.perf_counter()
        scan = cast(scene, pose, MOUNT, spec, rng)
        middle = time.perf_counter()
        clusters += len(describe_scan(scan))
        cast_s.append(middle - start)
        total_s.append(time.perf_counter() - start)
    plain_s = []
    worst = 0.0
    for pose in poses[:plain_scans]:
        start = time.perf_counter()
        reference = plain_ranges(obstacles, pose, spec)
        plain_s.append(time.perf_counter() - start)
        worst = max(worst, _largest_difference(cast(scene, pose, MOUNT, spec).ranges_m, reference))
    row = [f"{count} obstacles", *percentiles_us(cast_s), *percentiles_us(total_s), *percentiles_us(plain_s)]
    note = (
        f"{count} obstacles: {clusters / len(poses):.1f} clusters per scan; "
        f"vectorised and plain ranges differ by at most {worst:.1e} m"
    )
    return row, note


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_lidar", description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=400, help="vectorised scans per scene")
    parser.add_argument("--plain-scans", type=int, default=15, help="plain Python scans per scene")
    args = parser.parse_args(argv)
    console = Console()
    spec = ScanSpec()
    table = Table(
        "Horizontal lidar: cost of one 361-ray scan (us)",
        ["scene", "cast p50", "cast p99", "cast+cluster p50", "cast+cluster p99", "plain cast p50", "plain cast p99"],
    )
    notes = []
    for count in SCENE_SIZES:
        row, note = measure(count, args.scans, args.plain_scans, spec)
        table.add(*row)
        notes.append(note)
    print_table(console, table)
    for note in notes:
        console.print(note, markup=False, highlight=False, soft_wrap=True)
    return 0


def _largest_difference(vectorised: np.ndarray, plain: list[float]) -> float:
    reference = np.asarray(plain)
    if not np.array_equal(np.isinf(vectorised), np.isinf(reference)):
        return math.inf
    hit = np.isfinite(reference)
    return float(np.max(np.abs(vectorised[hit] - reference[hit]), initial=0.0))


if __name__ == "__main__":
    raise SystemExit(main())
