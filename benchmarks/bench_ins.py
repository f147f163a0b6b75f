"""Navigation filter benchmark: the cost of one IMU step, both estimators side by side.

One "IMU step" is everything the filter does per 10 ms of a real stream: the IMU prediction plus
the measurements that arrive with it (GPS at 10 Hz, speedometer at 50 Hz, two magnetometers at
20 Hz each), fed in arrival order from a seeded simulated drive. Each step is timed on its own
with ``time.perf_counter_ns``. Rows: the EKF and the UKF with GPS and during a GPS outage, the
same two with every GPS fix 250 ms late (each one rewinds the history and replays 25 IMU steps),
and, as the floor, filterpy's linear KalmanFilter doing one 9-state predict and update per step.

Usage: ``python -m benchmarks.bench_ins [--seconds S]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Sequence

import numpy as np
from filterpy.kalman import KalmanFilter
from rich.console import Console

from benchmarks.report import Table, machine_line, print_table
from modules.ins.cores import FILTERS
from modules.ins.navigator import InsFilter
from modules.sim.nav import replay

BUDGET_US = 200.0
SECONDS = 60.0
WARMUP_S = 5.0  # the filter initialises and settles; not timed


def step_times_ns(kind: str, events: Sequence[replay.Event]) -> list[int]:
    """Time per IMU step: from an IMU sample up to (not including) the next one."""
    nav = InsFilter(replay.ORIGIN, kind=kind)
    handlers = {"imu": nav.on_imu, "gps": nav.on_gps, "speed": nav.on_speed, "mag": nav.on_mag}
    warm_until_ns = replay.t_ns_at(WARMUP_S)
    times: list[int] = []
    current = 0
    for event in events:
        if event.kind == "imu" and event.t_ns > warm_until_ns:
            if current:
                times.append(current)
            current = 0
        started = time.perf_counter_ns()
        handlers[event.kind](event.msg, event.t_ns)
        if event.t_ns > warm_until_ns:
            current += time.perf_counter_ns() - started
    return times


def floor_times_ns(steps: int) -> list[int]:
    """filterpy's linear KalmanFilter, 9 states, one predict and one 2-D update per step."""
    kf = KalmanFilter(dim_x=9, dim_z=2)
    kf.F = np.eye(9) + np.eye(9, k=1) * 0.01
    kf.H = np.zeros((2, 9))
    kf.H[0, 0] = kf.H[1, 1] = 1.0
    kf.Q *= 1e-4
    z = np.zeros(2)
    times = []
    for _ in range(steps):
        started = time.perf_counter_ns()
        kf.predict()
        kf.update(z)
        times.append(time.perf_counter_ns() - started)
    return times


def row(label: str, times_ns: Sequence[int]) -> list[str]:
    us = sorted(t / 1e3 for t in times_ns)
    p99 = us[min(len(us) - 1, int(0.99 * len(us)))]
    return [
        label,
        f"{len(us):,}",
        f"{statistics.fmean(us):.0f}",
        f"{us[len(us) // 2]:.0f}",
        f"{p99:.0f}",
        f"{us[-1]:.0f}",
    ]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_ins", description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=SECONDS, help=f"simulated seconds per row (default {SECONDS})")
    args = parser.parse_args(argv)
    if args.seconds < WARMUP_S + 5:
        parser.error(f"--seconds must be at least {WARMUP_S + 5}")
    console = Console()
    console.print(machine_line("navigation filter"), markup=False, highlight=False)
    with_gps = replay.drive(args.seconds, seed=1).events
    outage = replay.drive(args.seconds, seed=1, faults=[replay.gps_outage(WARMUP_S, args.seconds + 1)]).events
    late_gps = replay.delay(with_gps, {"gps": 250_000_000})
    table = Table(
        f"One IMU step (100 Hz) with the measurements arriving in it, {args.seconds:.0f} s of a simulated drive",
        ["filter / stream", "steps", "mean us", "p50 us", "p99 us", "max us"],
    )
    worst_mean = 0.0
    for kind in FILTERS:
        for stream, events in (("with GPS", with_gps), ("GPS outage", outage), ("GPS 250 ms late", late_gps)):
            cells = row(f"{kind}, {stream}", step_times_ns(kind, events))
            table.add(*cells)
            if stream != "GPS 250 ms late":
                worst_mean = max(worst_mean, float(cells[2]))
    table.add(*row("floor: filterpy KalmanFilter predict+update", floor_times_ns(round(args.seconds * 100))))
    print_table(console, table)
    # The budget is the cost per step, i.e. the mean: it sets how much of a core the filter takes.
    # Percentiles are shown because on a shared machine they carry the other work's noise.
    verdict = "PASS" if worst_mean <= BUDGET_US else "FAIL"
    console.print(
        f"{verdict}  worst mean cost of the in-order streams {worst_mean:.0f} us per IMU step against the "
        f"{BUDGET_US:.0f} us budget (late GPS is the replay path, shown for its cost, not budgeted)",
        markup=False,
        highlight=False,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
