"""Closed-loop drive benchmark: the whole stack drives the default scenario once per seed.

Issue 7's measure of the stack as a driver: ``rascal run`` on the default deployment, every module
its own process on the signed loopback bus, with the scenario's seed changed so the random rocks
and bushes (and the GPS jumps) lie elsewhere each time. Each drive writes its run directory; the
table is read from their ``summary.json`` (the referee's drive measures). The targets are those of
the issue: every seed finished with 0 collisions, 0 corridor exits and no wheel on a ditch or berm
(the simulator drives through them; the referee counts it), mean speed at least 80 % of
what the RDDF and curvature allow, RMS cross-track error to the path at most 0.3 m.

A drive takes about 5.5 minutes and needs both cores of a 2-core machine: run this alone. Each
drive gets its own bus (a multicast group and port picked from the seed, ttl=0) so a demo running
meanwhile cannot mix with it. Stopped (Ctrl-C, SIGTERM) or past its timeout, the benchmark stops
the stack it started the way ``rascal run`` expects (SIGTERM: its modules in order), and removes
its scratch copies: no stack is left driving on a bus nobody watches.

Usage: ``python -m benchmarks.bench_drive [--seeds 2005 2006 ...] [--runs-dir DIR]``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import re
import signal
import subprocess
import sys
import tempfile
import time
import tomllib
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import IO

from rich.console import Console

from benchmarks.report import Table, machine_line, print_table
from modules.referee.measures import drove_safely
from modules.sim.scenario import load_scenario

ROOT = Path(__file__).resolve().parent.parent
DEPLOYMENT = ROOT / "deploy" / "localhost.toml"
RASCAL = Path(sys.executable).with_name("rascal")  # the command the venv installs
DEFAULT_SEEDS = (2005, 2006, 2007, 2008, 2009)
TIMEOUT_S = 900.0  # a drive that has not ended by then has stalled
STOP_GRACE_S = 30.0  # for rascal run to stop its modules in order and write its summary
MIN_SPEED_RATIO = 0.80
MAX_CROSS_TRACK_RMS_M = 0.3


def seeded_deployment(seed: int, where: Path) -> Path:
    """A copy of the default deployment whose scenario has ``seed``, on a bus of its own."""
    deployment = tomllib.loads(DEPLOYMENT.read_text())["deployment"]
    scenario_file = (DEPLOYMENT.parent / deployment["scenario"]).resolve()
    course_file = (DEPLOYMENT.parent / deployment["course"]).resolve()
    rddf = tomllib.loads(scenario_file.read_text())["scenario"]["rddf"]
    scenario = _replace_line(scenario_file.read_text(), "seed", str(seed))
    scenario = _replace_line(scenario, "rddf", json.dumps(str((scenario_file.parent / rddf).resolve())))
    scenario_copy = where / f"scenario-{seed}.toml"
    scenario_copy.write_text(scenario)
    if load_scenario(scenario_copy).seed != seed:
        raise RuntimeError(f"{scenario_copy}: the seed did not take")
    text = _replace_line(DEPLOYMENT.read_text(), "scenario", json.dumps(str(scenario_copy)))
    text = _replace_line(text, "course", json.dumps(str(course_file)))
    bus = f"udpm://239.255.{77 + seed % 100}.{seed % 250 + 1}:{20000 + seed % 10000}?ttl=0"
    text = _replace_line(text, "bus", json.dumps(bus))
    copy = where / f"deploy-{seed}.toml"
    copy.write_text(text)
    return copy


def _replace_line(text: str, key: str, value: str) -> str:
    """``text`` with its one top-level ``key = ...`` line set to ``value`` (a TOML literal)."""
    pattern = re.compile(rf"^{re.escape(key)} = .*$", re.MULTILINE)
    if len(pattern.findall(text)) != 1:
        raise ValueError(f"expected exactly one '{key} = ' line")
    return pattern.sub(lambda _: f"{key} = {value}", text)


def drive(seed: int, runs_dir: Path, scratch: Path) -> dict[str, object]:
    """One closed-loop drive; its drive measures, plus its wall time and run directory."""
    deployment = seeded_deployment(seed, scratch)
    out = runs_dir / f"seed-{seed}"
    start = time.monotonic()
    # Past the timeout it is stopped; its summary (if any) says it did not finish.
    with (scratch / f"rascal-run-{seed}.log").open("w") as log, contextlib.suppress(subprocess.TimeoutExpired):
        run_stack([str(RASCAL), "run", str(deployment), "--runs-dir", str(out)], log, TIMEOUT_S, STOP_GRACE_S)
    summaries = sorted(out.glob("*/summary.json"))
    if not summaries:
        return {"seed": seed, "finished": False, "wall_s": time.monotonic() - start, "run_dir": str(out)}
    summary = json.loads(summaries[-1].read_text())
    measures = dict(summary.get("drive") or {})
    measures.update(seed=seed, wall_s=time.monotonic() - start, run_dir=str(summaries[-1].parent))
    return measures


class Stopped(Exception):
    """The benchmark itself was told to stop (SIGTERM)."""


def _raise_stopped(signum: int, _frame: FrameType | None) -> None:
    raise Stopped(signal.Signals(signum).name)


def run_stack(command: Sequence[str], log: IO[str], timeout_s: float, grace_s: float) -> None:
    """Run ``command`` (a ``rascal run``) to its end; if that takes over ``timeout_s`` (raising
    TimeoutExpired) or anything interrupts the wait, SIGTERM it, and SIGKILL it after ``grace_s``."""
    process = subprocess.Popen(command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    try:
        process.wait(timeout=timeout_s)
    finally:
        if process.poll() is None:
            process.terminate()
            try:
                process.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def meets_targets(measures: dict[str, object]) -> bool:
    return bool(
        drove_safely(measures)
        and float(measures.get("speed_ratio", 0.0)) >= MIN_SPEED_RATIO  # type: ignore[arg-type]
        and float(measures.get("cross_track_rms_m", 1e9)) <= MAX_CROSS_TRACK_RMS_M  # type: ignore[arg-type]
    )


def table(results: Sequence[dict[str, object]]) -> Table:
    out = Table(
        f"closed-loop drives of the default scenario (targets: finished, 0 collisions, 0 exits, 0 ditch/berm entries, "
        f"speed >= {MIN_SPEED_RATIO:.0%} of allowed, RMS <= {MAX_CROSS_TRACK_RMS_M} m)",
        [
            "seed",
            "finished",
            "time s",
            "mean m/s",
            "allowed m/s",
            "speed %",
            "RMS m",
            "max m",
            "collisions",
            "exits",
            "ditch/berm entries",
            "clearance m",
            "meets",
        ],
    )
    for m in results:
        if "time_s" not in m:
            out.add(str(m["seed"]), "no", *(["-"] * 10), "no")
            continue
        out.add(
            str(m["seed"]),
            "yes" if m["finished"] else "no",
            f"{m['time_s']:.1f}",
            f"{m['mean_speed_mps']:.2f}",
            f"{m['allowed_mean_speed_mps']:.2f}",
            f"{100 * float(m['speed_ratio']):.1f}",  # type: ignore[arg-type]
            f"{m['cross_track_rms_m']:.2f}",
            f"{m['cross_track_max_m']:.2f}",
            str(m["collisions"]),
            str(m["corridor_exits"]),
            str(m["hazard_entries"]),
            f"{m['min_clearance_m']:.2f}",
            "yes" if meets_targets(m) else "no",
        )
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(DEFAULT_SEEDS))
    parser.add_argument("--runs-dir", type=Path, default=ROOT / "runs" / "drive-bench")
    args = parser.parse_args(argv)
    console = Console()
    console.print(machine_line("drive"), markup=False, highlight=False)
    results = []
    signal.signal(signal.SIGTERM, _raise_stopped)  # unwind like Ctrl-C: stop the stack, clean up
    try:
        with tempfile.TemporaryDirectory(prefix="rascal-drive-") as scratch:
            for seed in args.seeds:
                results.append(drive(seed, args.runs_dir, Path(scratch)))
                console.print(f"seed {seed}: {json.dumps(results[-1])}", markup=False, highlight=False)
    except (Stopped, KeyboardInterrupt):
        console.print(f"stopped after {len(results)} of {len(args.seeds)} drives", markup=False, highlight=False)
        return 130
    print_table(console, table(results))
    return 0 if all(meets_targets(m) for m in results) else 1


if __name__ == "__main__":
    sys.exit(main())
