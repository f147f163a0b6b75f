"""Simulator benchmark: what one 100 Hz simulator step costs, vehicle dynamics plus collision checks.

Every call is timed on its own with ``time.perf_counter_ns`` (so the table has percentiles, not
only a mean); the first row is an empty function timed the same way, the floor that timing and
calling add to every other row. Rows:

- the vehicle step alone;
- step + ``collides`` against 25 and 100 obstacles scattered around a 40 m circle the vehicle
  drives at full throttle (a course: most obstacles are far and the prefilter skips them);
- step + ``collides`` with the vehicle held by its brake among 100 obstacles that all pass the
  bounding-circle prefilter without touching it (the worst case: every obstacle gets the exact test);
- the same two collision workloads checked by a numpy-vectorised version (all obstacles at once,
  no prefilter), as an anchor: at this size numpy's per-call overhead dominates.

Usage: ``python -m benchmarks.bench_sim [--samples N]``.
"""

from __future__ import annotations

import argparse
import math
import random
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from rich.console import Console

from benchmarks.report import Table, machine_line, print_table
from brain.pose import PoseLike
from modules.sim.collision import clearance_m, collides, footprint
from modules.sim.scenario import DEFAULT_SCENARIO, load_scenario
from modules.sim.simulator import WorldState
from modules.sim.vehicle import VehicleParams, VehicleState, step
from modules.sim.world import Shape, WorldObstacle
from protocol.messages import ActuatorCommand

DT_S = 0.01
BUDGET_US = 1_000.0
SAMPLES = 20_000
WARMUP = 1_000
VERIFY_STEPS = 3_000
SEED = 20051008  # the 2005 Grand Challenge; any fixed seed makes the obstacle layouts repeatable

COURSE_RADIUS_M = 40.0
COURSE_HALF_SIZE_M = 70.0
# Obstacles stay this far from the driven circle, so the course run never collides (a collision
# would end the check early and flatter the numbers) while the nearest still pass the prefilter.
COURSE_CLEAR_M = 1.8
WORST_CASE_RING_M = (0.8, 2.6)

Timed = Callable[[int], object]


@dataclass(frozen=True)
class Row:
    label: str
    obstacles: str
    samples_us: list[float]

    def cells(self) -> list[str]:
        cuts = statistics.quantiles(self.samples_us, n=100, method="inclusive")
        values = (statistics.fmean(self.samples_us), cuts[49], cuts[98], max(self.samples_us))
        return [self.label, self.obstacles, *(f"{value:.1f}" for value in values)]

    def p99(self) -> float:
        return statistics.quantiles(self.samples_us, n=100, method="inclusive")[98]


# -- workloads ----------------------------------------------------------------------------------


def course_commands(params: VehicleParams, count: int) -> list[ActuatorCommand]:
    """Full throttle on a 40 m circle, with a small steering wobble so the actuator model works."""
    steering_rad = math.atan(params.wheelbase_m / COURSE_RADIUS_M)
    return [ActuatorCommand(1.0, 0.0, steering_rad + 0.002 * math.sin(k / 50)) for k in range(count)]


def course_start(params: VehicleParams) -> VehicleState:
    """On the circle (centred at the origin) heading north at speed, steering already set."""
    steering_rad = math.atan(params.wheelbase_m / COURSE_RADIUS_M)
    return VehicleState(east_m=COURSE_RADIUS_M, yaw_rad=math.pi / 2, speed_mps=15.0, steering_rad=steering_rad)


def course_obstacles(rng: random.Random, count: int) -> list[WorldObstacle]:
    """Boxes and cylinders scattered over the square around the circle, none on the driven line."""
    obstacles: list[WorldObstacle] = []
    while len(obstacles) < count:
        east, north = (rng.uniform(-COURSE_HALF_SIZE_M, COURSE_HALF_SIZE_M) for _ in range(2))
        if abs(math.hypot(east, north) - COURSE_RADIUS_M) < COURSE_CLEAR_M:
            continue
        obstacles.append(_random_obstacle(rng, f"course-{len(obstacles)}", east, north))
    return obstacles


def worst_case_obstacles(rng: random.Random, params: VehicleParams, count: int) -> list[WorldObstacle]:
    """Obstacles close around a vehicle at the origin: all inside the prefilter's reach, none touching."""
    rect = footprint(VehicleState(), params)
    obstacles: list[WorldObstacle] = []
    while len(obstacles) < count:
        bearing, distance = rng.uniform(-math.pi, math.pi), rng.uniform(*WORST_CASE_RING_M)
        east, north = rect.east_m + distance * math.cos(bearing), rect.north_m + distance * math.sin(bearing)
        obstacle = _random_obstacle(rng, f"near-{len(obstacles)}", east, north, scale=0.4)
        reach_m = rect.radius_m() + obstacle.footprint_radius_m()
        if distance <= reach_m and clearance_m(VehicleState(), obstacle, params) > 0.0:
            obstacles.append(obstacle)
    return obstacles


def _random_obstacle(rng: random.Random, name: str, east: float, north: float, scale: float = 1.0) -> WorldObstacle:
    if rng.random() < 0.5:
        return WorldObstacle(name, Shape.CYLINDER, east, north, 1.0, radius_m=scale * rng.uniform(0.15, 0.6))
    length, width = scale * rng.uniform(0.3, 1.2), scale * rng.uniform(0.3, 1.0)
    return WorldObstacle(
        name, Shape.BOX, east, north, 1.0, length_m=length, width_m=width, yaw_rad=rng.uniform(-math.pi, math.pi)
    )


class VectorisedObstacles:
    """The same exact check with numpy, over all obstacles at once (the anchor).

    Boxes get the four-axis separating-axis test and cylinders the closest-point test, each as
    array expressions; the first colliding obstacle in the original order is returned.
    """

    def __init__(self, obstacles: Sequence[WorldObstacle]) -> None:
        self.obstacles = tuple(obstacles)
        boxes = [i for i, o in enumerate(obstacles) if o.shape is Shape.BOX]
        cylinders = [i for i, o in enumerate(obstacles) if o.shape is Shape.CYLINDER]
        self.box_index = np.array(boxes, dtype=np.intp)
        self.cylinder_index = np.array(cylinders, dtype=np.intp)

        def column(indices: list[int], value: Callable[[WorldObstacle], float]) -> np.ndarray:
            return np.array([value(obstacles[i]) for i in indices], dtype=float)

        self.box_east = column(boxes, lambda o: o.east_m)
        self.box_north = column(boxes, lambda o: o.north_m)
        self.box_cos = column(boxes, lambda o: math.cos(o.yaw_rad))
        self.box_sin = column(boxes, lambda o: math.sin(o.yaw_rad))
        self.box_half_length = column(boxes, lambda o: 0.5 * o.length_m)
        self.box_half_width = column(boxes, lambda o: 0.5 * o.width_m)
        self.cylinder_east = column(cylinders, lambda o: o.east_m)
        self.cylinder_north = column(cylinders, lambda o: o.north_m)
        self.cylinder_radius_sq = column(cylinders, lambda o: o.radius_m**2)

    def collides(self, pose: PoseLike, params: VehicleParams) -> WorldObstacle | None:
        east, north, ca, sa, half_length, half_width = footprint(pose, params)
        cb, sb = self.box_cos, self.box_sin
        box_length, box_width = self.box_half_length, self.box_half_width
        d_east, d_north = self.box_east - east, self.box_north - north
        cos_rel = np.abs(ca * cb + sa * sb)
        sin_rel = np.abs(ca * sb - sa * cb)
        box_hit = np.abs(d_east * ca + d_north * sa) <= half_length + box_length * cos_rel + box_width * sin_rel
        box_hit &= np.abs(d_north * ca - d_east * sa) <= half_width + box_length * sin_rel + box_width * cos_rel
        box_hit &= np.abs(d_east * cb + d_north * sb) <= box_length + half_length * cos_rel + half_width * sin_rel
        box_hit &= np.abs(d_north * cb - d_east * sb) <= box_width + half_length * sin_rel + half_width * cos_rel

        d_east, d_north = self.cylinder_east - east, self.cylinder_north - north
        along = np.maximum(np.abs(d_east * ca + d_north * sa) - half_length, 0.0)
        across = np.maximum(np.abs(d_north * ca - d_east * sa) - half_width, 0.0)
        cylinder_hit = along * along + across * across <= self.cylinder_radius_sq

        hits = np.concatenate((self.box_index[box_hit], self.cylinder_index[cylinder_hit]))
        return self.obstacles[int(hits.min())] if hits.size else None


# -- measuring ----------------------------------------------------------------------------------


def time_each(call: Timed, samples: int) -> list[float]:
    """Microseconds of each of ``samples`` calls, after a warm-up that is thrown away."""
    clock = time.perf_counter_ns
    for i in range(WARMUP):
        call(i)
    out = [0.0] * samples
    for i in range(samples):
        start = clock()
        call(WARMUP + i)
        out[i] = (clock() - start) / 1e3
    return out


def simulator_step(
    state: VehicleState, commands: list[ActuatorCommand], params: VehicleParams, check: Callable[[], object] | None
) -> Timed:
    """One simulator step as the simulator will run it: the dynamics, then the collision check."""
    count = len(commands)

    def run(i: int) -> object:
        step(state, commands[i % count], DT_S, params)
        return check() if check is not None else None

    return run


def measure(samples: int) -> tuple[list[Row], list[str]]:
    params = VehicleParams()
    rng = random.Random(SEED)
    course = course_obstacles(rng, 100)
    worst = worst_case_obstacles(rng, params, 100)
    commands = course_commands(params, 2 * (WARMUP + samples))
    held = [ActuatorCommand(0.0, 1.0, 0.5 * math.sin(k / 40)) for k in range(2 * (WARMUP + samples))]
    notes = verify(params, course, worst, commands)

    def course_run(check: Callable[[VehicleState], object] | None) -> Timed:
        state = course_start(params)
        return simulator_step(state, commands, params, None if check is None else lambda: check(state))

    def held_run(check: Callable[[VehicleState], object]) -> Timed:
        state = VehicleState(brake_actual=1.0)
        return simulator_step(state, held, params, lambda: check(state))

    def python_check(obstacles: list[WorldObstacle]) -> Callable[[VehicleState], object]:
        return lambda state: collides(state, obstacles, params)

    def numpy_check(obstacles: list[WorldObstacle]) -> Callable[[VehicleState], object]:
        vectorised = VectorisedObstacles(obstacles)
        return lambda state: vectorised.collides(state, params)

    def bare(i: int) -> object:
        return None

    def full_step() -> Timed:
        # What the simulator module does each tick on the default scenario, bus aside.
        world = WorldState(load_scenario(DEFAULT_SCENARIO), params)
        cruise = ActuatorCommand(0.4, 0.0, 0.0)

        def run(i: int) -> object:
            world.advance(cruise, DT_S)
            return world.truth()

        return run

    plan: list[tuple[str, str, Timed]] = [
        ("bare Python call, timed the same way (floor)", "-", bare),
        ("vehicle step", "-", course_run(None)),
        ("step + collides, course", "25", course_run(python_check(course[:25]))),
        ("step + collides, course", "100", course_run(python_check(course))),
        ("step + collides, all within reach (worst case)", "100", held_run(python_check(worst))),
        ("anchor: step + numpy-vectorised check, course", "100", course_run(numpy_check(course))),
        ("anchor: step + numpy-vectorised check, worst case", "100", held_run(numpy_check(worst))),
        ("simulator step, default scenario (+ corridor, progress, truth)", "27", full_step()),
    ]
    return [Row(label, obstacles, time_each(call, samples)) for label, obstacles, call in plan], notes


def verify(
    params: VehicleParams, course: list[WorldObstacle], worst: list[WorldObstacle], commands: list[ActuatorCommand]
) -> list[str]:
    """The course run never collides, and the anchor answers exactly like collides()."""
    state = course_start(params)
    course_collisions, closest_m = 0, math.inf
    for command in commands[:VERIFY_STEPS]:
        step(state, command, DT_S, params)
        course_collisions += collides(state, course, params) is not None
        closest_m = min(closest_m, *(clearance_m(state, obstacle, params) for obstacle in course))
    # Poses jittered around the worst-case cluster collide often, so both answers get exercised.
    rng = random.Random(SEED + 1)
    vectorised = VectorisedObstacles(worst)
    colliding = disagreements = 0
    for _ in range(VERIFY_STEPS):
        pose = VehicleState(rng.uniform(-3.0, 3.0), rng.uniform(-3.0, 3.0), rng.uniform(-math.pi, math.pi))
        found = collides(pose, worst, params)
        colliding += found is not None
        disagreements += found is not vectorised.collides(pose, params)
    return [
        f"course check over {VERIFY_STEPS:,} steps: {course_collisions} collisions (expected 0), "
        f"closest approach {closest_m:.2f} m",
        f"anchor check over {VERIFY_STEPS:,} jittered poses ({colliding:,} colliding): "
        f"{disagreements} disagreements between collides() and the numpy version (expected 0)",
    ]


# -- report -------------------------------------------------------------------------------------


def acceptance(rows: list[Row]) -> tuple[str, str]:
    worst = next(row for row in rows if "worst case" in row.label and not row.label.startswith("anchor"))
    course = next(row for row in rows if row.label == "step + collides, course" and row.obstacles == "100")
    full = next(row for row in rows if row.label.startswith("simulator step"))
    ok = worst.p99() < BUDGET_US and full.p99() < BUDGET_US
    detail = (
        f"p99 {worst.p99():.1f} us in the worst case, {course.p99():.1f} us on the course, "
        f"{full.p99():.1f} us for the whole default-scenario step "
        f"(budget {BUDGET_US:.0f} us; the 100 Hz period is 10,000 us)"
    )
    verdict = "PASS" if ok else "FAIL"
    return verdict, f"one simulator step (dynamics + collisions vs 100 obstacles) < 1 ms at 100 Hz: {detail}"


def _say(console: Console, text: str) -> None:
    # Verbatim and unwrapped: these lines are read in logs as often as on a terminal.
    console.print(text, markup=False, highlight=False, soft_wrap=True)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_sim", description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=SAMPLES, help=f"timed steps per row (default {SAMPLES:,})")
    args = parser.parse_args(argv)
    if args.samples < 100:
        parser.error("--samples must be at least 100 for a p99")
    console = Console()
    machine = machine_line("simulator")
    rows, notes = measure(args.samples)
    _say(console, "\n".join([machine, *notes, ""]))
    table = Table(
        f"One simulator step at {1 / DT_S:.0f} Hz, {args.samples:,} timed steps per row after {WARMUP:,} warm-up",
        ["step", "obstacles", "mean us", "p50 us", "p99 us", "max us"],
    )
    for row in rows:
        table.add(*row.cells())
    print_table(console, table)
    verdict, text = acceptance(rows)
    _say(console, f"{verdict}  {text}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
