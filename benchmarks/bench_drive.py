"""Drive leaderboard: the whole stack drives a suite of courses and is scored the way CARLA's
leaderboard scores (issue 23 item 4; the suites and their times are in benchmarks/README.md).

The drives: the default scenario with its seed changed; courses generated for the seeds
(``rascal rddf generate``, straights, smooth bends, 10-35 mph, corridors 3.7-18 m wide with
narrow stretches); and stretches of the longer real RDDFs in ``../shared/data/rddf``, read in
place (``rascal rddf cut``; left out, saying so, when that folder is absent). Every course but the
default gets a hard but fair scenario of the drive's seed (``rascal scenario generate``). Each
drive is ``rascal run`` on a copy of deploy/localhost.toml pointing at its course and scenario, on
a bus of its own (a multicast group and port picked from the seed, ttl=0), ended by ``--duration``
at a timeout that grows with the course's length (a stalled drive ends too), and stopped the way
rascal run expects (SIGTERM) if it outlives that, is interrupted, or the benchmark is stopped.

Scoring and the tables: benchmarks/leaderboard.py.

Usage: ``python -m benchmarks.bench_drive [--suite quick|standard|full] [--seeds N ...] [--km KM]
[--runs-dir DIR] [--json PATH] [--real-rddf-dir DIR] [--plan]``; ``--plan`` lists the drives and the time they should
take, and drives nothing. The stack needs both cores of a 2-core machine: run this alone.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import re
import signal
import subprocess
import sys
import tempfile
import time
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from types import FrameType
from typing import IO, Any

from rich.console import Console

from benchmarks.leaderboard import (
    INFRACTIONS,
    NARROW_MIN_WIDTH_M,
    PENALTIES,
    Target,
    completion,
    drive_table,
    driving_score,
    infraction_table,
    leaderboard,
    meets_targets,
    target_table,
    write_json,
)
from benchmarks.report import Table, machine_line, print_table
from brain.corridor import Course
from brain.course_gen import (
    NARROW_WIDTH_M,
    CourseSpec,
    corridor_widths_m,
    cut_course,
    generate_course,
    rddf_text,
)
from brain.rddf import load_rddf
from modules.sim.generate import Options, generate
from modules.sim.scenario import load_scenario

ROOT = Path(__file__).resolve().parent.parent
DEPLOYMENT = ROOT / "deploy" / "localhost.toml"
REAL_RDDF_DIR = ROOT.parent / "shared" / "data" / "rddf"
RASCAL = Path(sys.executable).with_name("rascal")  # the command the venv installs
STOP_GRACE_S = 30.0  # for rascal run to stop its modules in order and write its summary
# A drive ends at DURATION_START_S + DURATION_FACTOR x the course's minimum drive time (at the
# desired speeds): 1.6 times what a drive at the speed target (80 %) takes, plus the start. Past
# that and POST_S more (the run's report and recording), the benchmark stops rascal run itself.
DURATION_START_S = 60.0
DURATION_FACTOR = 2.0
POST_S = 120.0
# Wall time per drive, estimated: start-up, the drive at the speed ratio drives have had, then
# the run's report and the recording's JSON twins. Measured on a 2-core VM: a generated 300 m
# course took 42 s (33 s of driving at 97 %), the default scenario about 330 s (280 s at 90 %).
STARTUP_S = 8.0
EXPECTED_SPEED_RATIO = 0.88
REPORT_SHARE = 0.15

REAL_MIN_M = 300.0  # the longer real RDDFs: the others are parking-lot loops of 50-200 m
SMALLEST_KM = 0.3


@dataclass(frozen=True)
class Suite:
    seeds: tuple[int, ...]
    km: float  # of generated courses, split evenly over the seeds
    default_drives: int  # the default scenario, with this many of the seeds
    real_files: int | None  # the longest this many real RDDFs (None: all of the longer ones)
    real_stretch_m: float  # of each, from its start
    real_seeds: int  # each stretch once with this many seeds


SUITES = {
    "quick": Suite((2005,), SMALLEST_KM, 0, 1, 300.0, 1),
    "standard": Suite(tuple(range(2005, 2015)), 20.0, 1, None, 1000.0, 1),
    "full": Suite(tuple(range(2005, 2025)), 50.0, 10, None, math.inf, 3),
}


@dataclass(frozen=True)
class Drive:
    name: str
    kind: str  # "default", "generated" or "real"
    seed: int
    length_m: float  # asked for: a generated course's length, a real file's stretch
    source: str = ""  # the real RDDF


def plan(suite: Suite, real_dir: Path) -> tuple[list[Drive], list[str]]:
    """The suite's drives, and why any were left out."""
    seeds = suite.seeds
    drives = [Drive(f"default-{seed}", "default", seed, 0.0) for seed in seeds[: suite.default_drives]]
    per_course_km = suite.km / len(seeds)
    drives += [Drive(f"gen-{seed}-{per_course_km:g}km", "generated", seed, 1000 * per_course_km) for seed in seeds]
    notes = []
    if suite.real_seeds and suite.real_files != 0:
        files, note = longer_real_rddfs(real_dir)
        notes += [note] if note else []
        for i, path in enumerate(files[: suite.real_files]):
            for j in range(suite.real_seeds):
                seed = seeds[(i + j) % len(seeds)]
                drives.append(Drive(f"{path.stem}-{seed}", "real", seed, suite.real_stretch_m, str(path)))
    return drives, notes


def longer_real_rddfs(real_dir: Path) -> tuple[list[Path], str]:
    """The real RDDFs of at least REAL_MIN_M, longest first, and a note when there are none."""
    if not real_dir.is_dir():
        return [], f"real RDDF stretches left out: {real_dir} is absent"
    lengths = {}
    for path in sorted(p for p in real_dir.iterdir() if p.is_file()):
        with contextlib.suppress(OSError, ValueError):  # a file that is no course is no drive
            lengths[path] = Course.from_file(path).length_m
    files = sorted((p for p, length in lengths.items() if length >= REAL_MIN_M), key=lambda p: -lengths[p])
    return files, "" if files else f"real RDDF stretches left out: no course of {REAL_MIN_M:g} m or more in {real_dir}"


@dataclass(frozen=True)
class Prepared:
    """A drive's deployment copy and what its course and scenario hold."""

    deployment: Path
    route_length_m: float
    min_drive_time_s: float
    min_width_m: float
    max_width_m: float
    narrow_m: float  # of corridor NARROW_MIN_WIDTH_M..NARROW_WIDTH_M wide
    obstacles: int
    hazards: int

    @property
    def duration_s(self) -> float:
        return DURATION_START_S + DURATION_FACTOR * self.min_drive_time_s


def prepare(drive: Drive, where: Path, bus: str | None = None) -> Prepared:
    """Write the drive's course, scenario and deployment copy into ``where``."""
    if drive.kind == "default":
        deployment = seeded_deployment(drive.seed, where)
        scenario_file = Path(tomllib.loads(deployment.read_text())["deployment"]["scenario"])
        if bus is not None:
            deployment.write_text(_replace_line(deployment.read_text(), "bus", json.dumps(bus)))
    else:
        if drive.kind == "generated":
            waypoints = generate_course(CourseSpec(drive.seed, drive.length_m))
        else:
            waypoints = cut_course(load_rddf(drive.source), 0.0, drive.length_m)
        course_file, scenario_file = where / f"{drive.name}.rddf", where / f"{drive.name}.toml"
        course_file.write_text(rddf_text(waypoints))
        scenario_file.write_text(generate(course_file, scenario_file, Options(drive.seed)).text)
        deployment = deployment_copy(
            scenario_file, course_file, bus or seed_bus(drive.seed), where / f"deploy-{drive.name}.toml"
        )
    scenario = load_scenario(scenario_file)  # checks it is fair, again
    waypoints = list(scenario.course.waypoints)
    widths = corridor_widths_m(waypoints)
    narrow = (widths >= NARROW_MIN_WIDTH_M) & (widths <= NARROW_WIDTH_M)
    return Prepared(
        deployment=deployment,
        route_length_m=scenario.route.length_m,
        min_drive_time_s=scenario.route.drive_time_s(),
        min_width_m=float(widths.min()),
        max_width_m=float(widths.max()),
        narrow_m=float(scenario.course.segment_length_m[narrow].sum()),
        obstacles=len(scenario.world.obstacles),
        hazards=len(scenario.world.hazards),
    )


def seed_bus(seed: int) -> str:
    """A bus of the seed's own, so a demo running meanwhile cannot mix with the drive."""
    return f"udpm://239.255.{77 + seed % 100}.{seed % 250 + 1}:{20000 + seed % 10000}?ttl=0"


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
    return deployment_copy(scenario_copy, course_file, seed_bus(seed), where / f"deploy-{seed}.toml")


def deployment_copy(scenario: Path, course: Path, bus: str, copy: Path) -> Path:
    """deploy/localhost.toml driving ``course`` through ``scenario`` on ``bus``, written to ``copy``."""
    text = _replace_line(DEPLOYMENT.read_text(), "scenario", json.dumps(str(scenario.resolve())))
    text = _replace_line(text, "course", json.dumps(str(course.resolve())))
    copy.write_text(_replace_line(text, "bus", json.dumps(bus)))
    return copy


def _replace_line(text: str, key: str, value: str) -> str:
    """``text`` with its one top-level ``key = ...`` line set to ``value`` (a TOML literal)."""
    pattern = re.compile(rf"^{re.escape(key)} = .*$", re.MULTILINE)
    if len(pattern.findall(text)) != 1:
        raise ValueError(f"expected exactly one '{key} = ' line")
    return pattern.sub(lambda _: f"{key} = {value}", text)


def run_drive(drive: Drive, prepared: Prepared, runs_dir: Path) -> dict[str, Any]:
    """One closed-loop drive: its record (the drive, its course, the referee's measures, the score)."""
    out = runs_dir / drive.name
    out.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    command = [str(RASCAL), "run", str(prepared.deployment), "--runs-dir", str(out)]
    command += ["--duration", f"{prepared.duration_s:.0f}"]
    # Past the backstop it is stopped; its summary (if any) says how far it got.
    with (out / "rascal-run.log").open("w") as log, contextlib.suppress(subprocess.TimeoutExpired):
        run_stack(command, log, prepared.duration_s + POST_S, STOP_GRACE_S)
    summaries = sorted(out.glob("*/summary.json"))
    summary = json.loads(summaries[-1].read_text()) if summaries else {}
    run_dir = str(summaries[-1].parent) if summaries else str(out)
    return record(drive, prepared, dict(summary.get("drive") or {}), time.monotonic() - start, run_dir)


def record(drive: Drive, prepared: Prepared, measures: dict[str, Any], wall_s: float, run_dir: str) -> dict[str, Any]:
    """What the table and the JSON file show of a drive; ``measures`` empty when it wrote none."""
    course = {k: v for k, v in asdict(prepared).items() if k != "deployment"}
    return {
        **asdict(drive),
        "course": course,
        "timeout_s": round(prepared.duration_s),
        "measures": measures,
        "completion": completion(measures),
        "infractions": {kind: int(measures.get(kind, 0)) for kind in PENALTIES},
        "driving_score": driving_score(measures),
        "clean": meets_targets(measures),
        "wall_s": round(wall_s, 1),
        "run_dir": run_dir,
    }


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


# -- scoring ---------------------------------------------------------------------------------


def result_line(r: Mapping[str, Any]) -> str:
    infractions = ", ".join(f"{n} {INFRACTIONS[kind]}" for kind, n in r["infractions"].items() if n) or "no infraction"
    speed = f", speed {r['measures']['speed_ratio']:.1%}" if r["measures"] else ", no measures"
    return (
        f"{r['name']}: done {r['completion']:.1%}, score {r['driving_score']:.1%}, {infractions}{speed}, "
        f"{r['wall_s']:.0f} s; {r['run_dir']}"
    )


def estimate_s(prepared: Prepared) -> float:
    """A drive's wall time, estimated (see STARTUP_S)."""
    return STARTUP_S + prepared.min_drive_time_s / EXPECTED_SPEED_RATIO * (1 + REPORT_SHARE)


def plan_table(drives: Sequence[Drive], prepared: Sequence[Prepared]) -> Table:
    out = Table(
        "drives planned (wall time estimated)",
        ["drive", "km", "width m", "narrow m", "obstacles", "ditches/berms", "timeout s", "estimate min"],
    )
    for drive, p in zip(drives, prepared, strict=True):
        out.add(
            drive.name,
            f"{p.route_length_m / 1000:.2f}",
            f"{p.min_width_m:.1f}-{p.max_width_m:.1f}",
            f"{p.narrow_m:.0f}",
            str(p.obstacles),
            str(p.hazards),
            f"{p.duration_s:.0f}",
            f"{estimate_s(p) / 60:.1f}",
        )
    km = sum(p.route_length_m for p in prepared) / 1000
    out.add("total", f"{km:.2f}", "", "", "", "", "", f"{sum(map(estimate_s, prepared)) / 60:.1f}")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", choices=list(SUITES), default="standard", help="which drives (%(default)s)")
    parser.add_argument("--seeds", type=int, nargs="+", help="instead of the suite's")
    parser.add_argument("--km", type=float, help="generated courses in total, instead of the suite's")
    parser.add_argument("--runs-dir", type=Path, default=ROOT / "runs" / "drive-bench")
    parser.add_argument("--real-rddf-dir", type=Path, default=REAL_RDDF_DIR, help="real RDDFs (%(default)s)")
    parser.add_argument("--json", type=Path, help="JSON file to write (default: RUNS_DIR/leaderboard.json)")
    parser.add_argument("--plan", action="store_true", help="list the drives and their estimated times only")
    args = parser.parse_args(argv)
    suite = SUITES[args.suite]
    suite = replace(suite, seeds=tuple(args.seeds or suite.seeds), km=suite.km if args.km is None else args.km)
    if not 0 < suite.km < math.inf:
        parser.error(f"--km must be positive, got {suite.km:g}")
    json_path = args.json or args.runs_dir / "leaderboard.json"
    console = Console()
    machine = machine_line("drive", f"suite {args.suite}")

    def say(text: str) -> None:
        console.print(text, markup=False, highlight=False)

    say(machine)
    drives, notes = plan(suite, args.real_rddf_dir)
    for note in notes:
        say(note)
    records: list[dict[str, Any]] = []
    signal.signal(signal.SIGTERM, _raise_stopped)  # unwind like Ctrl-C: stop the stack, clean up
    try:
        with tempfile.TemporaryDirectory(prefix="rascal-drive-") as scratch:
            prepared = [prepare(drive, Path(scratch)) for drive in drives]
            print_table(console, plan_table(drives, prepared))
            if args.plan:
                return 0
            for drive, p in zip(drives, prepared, strict=True):
                say(f"{drive.name}: {p.route_length_m / 1000:.2f} km, ended at {p.duration_s:.0f} s if not done")
                records.append(run_drive(drive, p, args.runs_dir))
                say(result_line(records[-1]))
    except (Stopped, KeyboardInterrupt):
        say(f"stopped after {len(records)} of {len(drives)} drives")
        if records:
            write_json(leaderboard(records, args.suite, suite.seeds, [*notes, "stopped early"], machine), json_path)
        return 130
    board = leaderboard(records, args.suite, suite.seeds, notes, machine)
    print_table(console, drive_table(records, board["totals"]))
    print_table(console, infraction_table(board["totals"]))
    print_table(console, target_table([Target(**t) for t in board["targets"]]))
    write_json(board, json_path)
    say(f"wrote {json_path}: {'every target met' if board['passed'] else 'targets missed'}")
    return 0 if board["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
