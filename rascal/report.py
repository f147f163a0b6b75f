"""``rascal report RUN_DIR``: the report images of a run, from its ``run.mcap`` and ``summary.json``.

``rascal run`` makes them when a run ends; this rebuilds them (e.g. after a change to the
report). They go to ``RUN_DIR/report/``, each as PNG and SVG (drawn with matplotlib,
rascal/plotting.py):

* ``track``: the course, the track driven coloured by speed, the navigation estimate, the
  obstacles and every hazard the brain mapped (rascal/report_track.py);
* ``map``: the brain's final map up close, with the last planned path;
* ``speed``: speed along the course against the RDDF limit and the course's speed profile
  (rascal/report_chart.py);
* ``cross_track``: the offset from the course centre line within the corridor, and the
  distance from the newest planned path (what control tracks);
* ``timing``: per module, activation jitter over the run's heartbeats, mean CPU, loop rate,
  overruns, restarts, rejected datagrams and output rates.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console

from rascal.latency import summarise
from rascal.report_data import ReportError, drive_line, read_run
from rascal.runtime.deployment import Deployment, DeploymentError, load_deployment

REPORT_DIR = "report"


@dataclass(frozen=True)
class Report:
    directory: Path
    images: dict[str, list[Path]]  # name -> its files (PNG, SVG)
    drive: str  # the drive in one line (rascal/report_data.py: drive_line)
    latency_ms: dict[str, float | int]  # measurement to actuator: p50, p99, max, samples (rascal/latency.py)

    def names(self) -> str:
        return f"{', '.join(self.images)} (.png, .svg)"


def build_report(run_dir: Path, deployment: Deployment | None = None, images: bool = True) -> Report:
    """Read the run and write its images to ``run_dir/report/`` (none without ``images``: the
    drive line and the latency only)."""
    data = read_run(run_dir, deployment)
    if not images:
        return Report(run_dir / REPORT_DIR, {}, drive_line(data), summarise(data.latency_ms))
    # Imported here: every `rascal` command builds the parser from this module, and matplotlib
    # costs half a second to import.
    from rascal.plotting import save_figure
    from rascal.report_chart import render_cross_track, render_speed, render_timing
    from rascal.report_track import render_final_map, render_track

    title = f"run {run_dir.name}: deployment {data.deployment.name}"
    figures = {
        "track": render_track(data, title),
        "map": render_final_map(data, title),
        "speed": render_speed(data),
        "cross_track": render_cross_track(data),
        "timing": render_timing(data),
    }
    directory = run_dir / REPORT_DIR
    directory.mkdir(exist_ok=True)
    written = {name: save_figure(figure, directory / name) for name, figure in figures.items() if figure is not None}
    return Report(directory, written, drive_line(data), summarise(data.latency_ms))


def report_run(run_dir: Path, deployment: Deployment, console: Console, images: bool = True) -> Report | None:
    """The end of ``rascal run``: build the report and say where it is. A report that cannot be
    made is reported, never raised: the run and its recording are what matter."""
    try:
        report = build_report(run_dir, deployment, images)
    except (ReportError, ValueError, OSError) as exc:
        console.print(f"no report: {exc}", markup=False, highlight=False)
        return None
    except Exception as exc:  # a report bug must not turn a good run into a failed one
        console.print(f"no report: {type(exc).__name__}: {exc} (rascal report {run_dir} to retry)", markup=False)
        return None
    if report.images:
        console.print(f"report: {report.directory}/ {report.names()}", markup=False)
    else:
        console.print(f"report images not drawn (rascal report {run_dir} draws them)", markup=False)
    return report


# -- command line ---------------------------------------------------------------------------------


def add_report_command(commands: Any) -> None:
    """Register ``report`` on the `rascal` command's subparsers."""
    report = commands.add_parser("report", help="rebuild a run's report images (RUN_DIR/report/*.png, *.svg)")
    report.add_argument("run_dir", type=Path, help="run directory (runs/<timestamp>/ with run.mcap, summary.json)")
    report.add_argument("--deployment", type=Path, help="deployment file (default: the one summary.json names)")
    report.set_defaults(handler=_report)


def _report(args: argparse.Namespace) -> int:
    try:
        deployment = load_deployment(args.deployment) if args.deployment else None
        report = build_report(args.run_dir, deployment)
    except (ReportError, DeploymentError, OSError) as exc:
        print(f"rascal report: {exc}", file=sys.stderr)
        return 2
    print(f"report of {args.run_dir}: {report.names()} in {report.directory}/")
    print(report.drive)
    return 0
