"""``rascal ins accuracy``: replay a scenario's sensor stream through the navigation filters and
print their errors against the truth.

The vehicle follows the scenario's route (pure pursuit on the true pose, at the RDDF speeds
capped at ``--speed``); the nav sensor models measure it with the scenario's own fault schedule
(its GPS jumps, say) plus a GPS outage (``--outage START:END`` seconds; ``none`` for none). Each
selected filter gets the same measurements in the same order, seed by seed.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from rich.console import Console
from rich.table import Table

from modules.ins.cores import FILTERS
from modules.ins.navigator import InsFilter
from modules.sim.nav import replay
from modules.sim.scenario import DEFAULT_SCENARIO, Scenario, load_scenario
from modules.sim.vehicle import VehicleState
from modules.sim.world import SensorFault

SETTLE_S = 20.0  # errors count from here: the filter's first seconds learn its biases
OUTAGE_MARKS_S = (60.0, 180.0)  # errors reported this long into the outage


@dataclass(frozen=True)
class Accuracy:
    """One filter on one seeded replay."""

    filter: str
    seed: int
    position_rms_m: float  # with GPS, after SETTLE_S
    heading_rms_deg: float
    speed_rms_mps: float
    outage_error_m: dict[float, float]  # error this far into the outage (NaN if it is shorter)
    outage_max_m: float
    gps_rejected: int
    reacquisitions: int
    us_per_imu_step: float
    min_eigenvalue: float


def evaluate(
    scenario: Scenario,
    kind: str,
    seed: int,
    duration_s: float,
    speed_mps: float,
    outage: tuple[float, float] | None,
) -> Accuracy:
    faults: list[SensorFault] = list(scenario.world.faults)
    if outage is not None:
        faults.append(replay.gps_outage(*outage))
    east, north, yaw = scenario.start_pose()
    drive = replay.drive(
        duration_s,
        seed,
        faults,
        driver=replay.route_driver(scenario.route, speed_mps),
        start=VehicleState(east_m=east, north_m=north, yaw_rad=yaw),
        origin=scenario.origin,
    )
    nav = InsFilter(scenario.origin, kind=kind)
    started = time.perf_counter()
    run = replay.run(nav, drive.events, len(drive.truth))
    elapsed_s = time.perf_counter() - started
    errors = replay.errors(run, drive.truth)
    with_gps = np.ones(len(drive.truth), dtype=bool)
    with_gps[: replay.window(0.0, SETTLE_S).stop] = False
    outage_error: dict[float, float] = {}
    outage_max = math.nan
    if outage is not None:
        span = replay.window(*outage)
        # Back on GPS takes a few fixes: leave 5 s after the outage out of the with-GPS figures.
        with_gps[span.start : span.stop + 500] = False
        during = errors.position_m[span]
        outage_max = float(np.nanmax(during)) if len(during) else math.nan
        for mark in OUTAGE_MARKS_S:
            k = round(mark * 100) - 1
            outage_error[mark] = float(during[k]) if k < len(during) else math.nan
    return Accuracy(
        kind,
        seed,
        replay.rms(errors.position_m[with_gps]),
        math.degrees(replay.rms(errors.yaw_rad[with_gps])),
        replay.rms(errors.speed_mps[with_gps]),
        outage_error,
        outage_max,
        nav.gps_rejected,
        nav.reacquisitions,
        # The replay loop's own reading of the estimate is inside this: an upper bound.
        elapsed_s / len(drive.truth) * 1e6,
        run.min_eigenvalue,
    )


def table(results: Sequence[Accuracy], title: str) -> Table:
    out = Table(title=title)
    for column in ("filter", "seed", "pos RMS m", "heading RMS deg", "speed RMS m/s"):
        out.add_column(column, justify="right")
    for mark in OUTAGE_MARKS_S:
        out.add_column(f"outage +{mark:.0f} s m", justify="right")
    for column in ("outage max m", "GPS rejected", "reacquired", "us/IMU step", "min eig P"):
        out.add_column(column, justify="right")
    for r in results:
        out.add_row(
            r.filter,
            str(r.seed),
            f"{r.position_rms_m:.3f}",
            f"{r.heading_rms_deg:.3f}",
            f"{r.speed_rms_mps:.3f}",
            *(f"{r.outage_error_m.get(mark, math.nan):.2f}" for mark in OUTAGE_MARKS_S),
            f"{r.outage_max_m:.2f}",
            str(r.gps_rejected),
            str(r.reacquisitions),
            f"{r.us_per_imu_step:.0f}",
            f"{r.min_eigenvalue:.1e}",
        )
    return out


def _outage(text: str) -> tuple[float, float] | None:
    if text == "none":
        return None
    try:
        start, end = (float(part) for part in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:END seconds or 'none', got {text!r}") from None
    if not 0 <= start < end:
        raise argparse.ArgumentTypeError(f"outage {text!r}: need 0 <= START < END")
    return start, end


def _filters(text: str) -> list[str]:
    kinds = [part.strip() for part in text.split(",") if part.strip()]
    unknown = [k for k in kinds if k not in FILTERS]
    if not kinds or unknown:
        raise argparse.ArgumentTypeError(f"filters must be a comma list of {', '.join(FILTERS)}; got {text!r}")
    return kinds


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="rascal ins accuracy", description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default=str(DEFAULT_SCENARIO), help="scenario TOML (default: %(default)s)")
    parser.add_argument("--filters", type=_filters, default=list(FILTERS), help="comma list (default: ekf,ukf)")
    parser.add_argument("--seeds", type=int, default=1, help="seeded replays per filter (default: 1)")
    parser.add_argument("--duration", type=float, default=270.0, help="seconds of driving (default: 270)")
    parser.add_argument("--speed", type=float, default=10.0, help="speed cap, m/s (default: 10)")
    parser.add_argument(
        "--outage", type=_outage, default=(60.0, 240.0), help="GPS outage START:END s, or none (default: 60:240)"
    )
    args = parser.parse_args(argv)
    if args.seeds < 1 or args.duration <= SETTLE_S or args.speed <= 0:
        parser.error(f"need --seeds >= 1, --duration > {SETTLE_S:.0f} and --speed > 0")
    scenario = load_scenario(args.scenario)
    results = [
        evaluate(scenario, kind, seed, args.duration, args.speed, args.outage)
        for seed in range(args.seeds)
        for kind in args.filters
    ]
    outage = "no outage" if args.outage is None else f"GPS outage {args.outage[0]:.0f}-{args.outage[1]:.0f} s"
    title = f"Navigation accuracy: {scenario.name}, {args.duration:.0f} s at <= {args.speed:.0f} m/s, {outage}"
    console = Console()
    console.width = max(console.width, 160)  # a wide table: do not squeeze it into a pipe's 80 columns
    console.print(table(results, title))
    return 0
