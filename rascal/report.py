"""``rascal report RUN_DIR``: the report images of a run, from its ``run.mcap`` and ``summary.json``.

``rascal run`` makes them when a run ends; this rebuilds them (e.g. after a change to the
report). They go to ``RUN_DIR/report/``:

* ``track.png``: the course, the track driven coloured by speed, the navigation estimate, the
  obstacles and every hazard the brain mapped (rascal/report_track.py);
* ``map.png``: the brain's final map up close, with the last planned path;
* ``speed.png``: speed along the course against the RDDF limit and the course's speed profile;
* ``cross_track.png``: the offset from the course centre line within the corridor, and the
  distance from the newest planned path (what control tracks);
* ``timing.png``: per module, activation jitter over the run's heartbeats, mean CPU, loop rate,
  overruns, restarts, rejected datagrams and output rates.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rich.console import Console

from brain.rddf_cli import CORRIDOR_EDGE, CORRIDOR_FILL, FONT, INK, PAPER, Color, draw_text
from rascal.deployment import Deployment, DeploymentError, load_deployment
from rascal.latency import summarise
from rascal.report_chart import Chart, LegendEntry
from rascal.report_data import FloatArray, ReportError, RunData, Track, read_run
from rascal.report_track import OBSTACLE, drive_line, render_final_map, render_track

REPORT_DIR = "report"
CHART_SIZE = (1600, 640)  # width, height of one chart panel
TRUE: Color = (40, 40, 200)
NAV: Color = (90, 90, 90)
LIMIT: Color = (60, 60, 60)
PROFILE: Color = (230, 170, 60)
JITTER: Color = (200, 140, 40)
MAX_OUTPUTS = 4


@dataclass(frozen=True)
class Report:
    directory: Path
    images: dict[str, Path]  # name -> file
    drive: str  # the drive in one line (rascal/report_track.py: drive_line)
    latency_ms: dict[str, float | int]  # measurement to actuator: p50, p99, max, samples (rascal/latency.py)


def build_report(run_dir: Path, deployment: Deployment | None = None) -> Report:
    """Read the run and write its images to ``run_dir/report/``."""
    data = read_run(run_dir, deployment)
    title = f"run {run_dir.name}: deployment {data.deployment.name}"
    images: dict[str, np.ndarray | None] = {
        "track": render_track(data, title),
        "map": render_final_map(data, title),
        "speed": render_speed(data),
        "cross_track": render_cross_track(data),
        "timing": render_timing(data),
    }
    directory = run_dir / REPORT_DIR
    directory.mkdir(exist_ok=True)
    written = {}
    for name, image in images.items():
        if image is None:
            continue
        path = directory / f"{name}.png"
        if not cv2.imwrite(str(path), image):
            raise OSError(f"{path}: OpenCV could not write it")
        written[name] = path
    return Report(directory, written, drive_line(data), summarise(data.latency_ms))


def report_run(run_dir: Path, deployment: Deployment, console: Console) -> Report | None:
    """The end of ``rascal run``: build the report and say where it is. A report that cannot be
    made is reported, never raised: the run and its recording are what matter."""
    try:
        report = build_report(run_dir, deployment)
    except (ReportError, ValueError, OSError) as exc:
        console.print(f"no report: {exc}", markup=False, highlight=False)
        return None
    except Exception as exc:  # a report bug must not turn a good run into a failed one
        console.print(f"no report: {type(exc).__name__}: {exc} (rascal report {run_dir} to retry)", markup=False)
        return None
    console.print(f"report: {report.directory}/ ({', '.join(p.name for p in report.images.values())})", markup=False)
    return report


# -- along the course ----------------------------------------------------------------------------


def render_speed(data: RunData) -> np.ndarray:
    path = data.frame.path
    top = 1.15 * float(max(path.speed_limit_mps.max(), *(t.speed_mps.max() for t in _tracks(data))))
    image, chart = _panel(
        data,
        (0.0, top),
        "speed along the course",
        "speed (m/s)",
    )
    chart.line(path.s_m, path.speed_limit_mps, LIMIT, "RDDF speed limit", 2)
    chart.line(path.s_m, path.speed_mps, PROFILE, "course speed profile (limit, turns, braking)", 2)
    if data.nav is not None:
        chart.line(*_forward(data.nav, data.nav.speed_mps), NAV, "navigation estimate", 1)
    if data.truth is not None:
        chart.line(*_forward(data.truth, data.truth.speed_mps), TRUE, "true speed", 2)
    drive = data.summary.get("drive") or {}
    if "mean_speed_mps" in drive:
        chart.note(
            f"mean {drive.get('mean_speed_mps', 0):.2f} m/s against an allowed mean of "
            f"{drive.get('allowed_mean_speed_mps', 0):.2f} m/s (ratio {drive.get('speed_ratio', 0):.2f}) "
            "over the part driven"
        )
    chart.draw_legend("bottom right")
    return image


def render_cross_track(data: RunData) -> np.ndarray:
    width, height = CHART_SIZE
    image = np.full((2 * height, width, 3), PAPER, dtype=np.uint8)
    frame = data.frame
    s = frame.s_m
    half = frame.half_width_at(s)
    reach = 1.1 * float(half.max())
    x_range = (0.0, frame.length_m)
    offset = Chart(
        image,
        (0, 0, width, height),
        x_range,
        (-reach, reach),
        "offset from the course centre line (left positive)",
        "station along the course (m)",
        "offset (m)",
    )
    offset.band(s, -half, half, CORRIDOR_FILL, "corridor")
    offset.line(s, half, CORRIDOR_EDGE, "", 1)
    offset.line(s, -half, CORRIDOR_EDGE, "", 1)
    if data.obstacles:
        east = np.array([o.east_m for o in data.obstacles])
        north = np.array([o.north_m for o in data.obstacles])
        radius = np.array([o.footprint_radius_m() for o in data.obstacles])
        obstacle_s, obstacle_d = frame.locate(east, north)
        offset.spans(
            obstacle_s, obstacle_d - radius, obstacle_d + radius, OBSTACLE, "obstacle across the course (scenario)"
        )
    if data.nav is not None:
        offset.line(*_forward(data.nav, data.nav.d_m), NAV, "navigation estimate", 1)
    if data.truth is not None:
        offset.line(*_forward(data.truth, data.truth.d_m), TRUE, "true position", 2)
    offset.draw_legend("top right")
    track = data.truth or data.nav
    errors = _path_errors(track, data.paths) if track is not None else np.zeros(0)
    finite = errors[np.isfinite(errors)]
    tracking = Chart(
        image,
        (0, height, width, height),
        x_range,
        (0.0, max(0.5, 1.2 * float(finite.max())) if len(finite) else 1.0),
        "distance from the newest planned path (what control tracks)",
        "station along the course (m)",
        "cross-track error (m)",
    )
    if track is not None:
        label = "true position" if track is data.truth else "navigation estimate"
        tracking.line(*_forward(track, errors), TRUE, label, 2)
    if len(finite):
        rms = float(np.sqrt(np.mean(finite**2)))
        tracking.note(f"RMS {rms:.2f} m, max {finite.max():.2f} m, over {len(finite)} samples at 10 Hz")
    tracking.draw_legend("top right")
    return image


def _panel(data: RunData, y_range: tuple[float, float], title: str, y_label: str) -> tuple[np.ndarray, Chart]:
    width, height = CHART_SIZE
    image = np.full((height, width, 3), PAPER, dtype=np.uint8)
    chart = Chart(
        image,
        (0, 0, width, height),
        (0.0, data.frame.length_m),
        y_range,
        title,
        "station along the course (m)",
        y_label,
    )
    return image, chart


def _tracks(data: RunData) -> list[Track]:
    return [track for track in (data.truth, data.nav) if track is not None and len(track)]


def _forward(track: Track, values: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(station, value) with a gap wherever the station goes back (a reversal or a restart), so
    the line never scribbles backwards over itself."""
    values = np.asarray(values, dtype=float).copy()
    back = np.concatenate([[False], np.diff(track.s_m) < -0.5])
    values[back] = np.nan
    return track.s_m, values


def _path_errors(track: Track, paths: list[tuple[float, FloatArray]]) -> FloatArray:
    """Per track sample, the distance to the newest planned path published before it (NaN
    before the first)."""
    errors = np.full(len(track), np.nan)
    if not paths:
        return errors
    times = np.array([t for t, _points in paths])
    newest = np.searchsorted(times, track.t_s, side="right") - 1
    for k in np.flatnonzero(newest >= 0):
        points = paths[newest[k]][1]
        errors[k] = _distance_to_polyline(points, track.east_m[k], track.north_m[k])
    return errors


def _distance_to_polyline(points: FloatArray, east: float, north: float) -> float:
    start, step = points[:-1], np.diff(points, axis=0)
    length2 = np.maximum(np.einsum("ij,ij->i", step, step), 1e-12)
    along = np.clip(np.einsum("ij,ij->i", np.array([east, north]) - start, step) / length2, 0.0, 1.0)
    nearest = start + along[:, None] * step
    return float(np.min(np.hypot(nearest[:, 0] - east, nearest[:, 1] - north)))


# -- module timing -------------------------------------------------------------------------------


def render_timing(data: RunData) -> np.ndarray:
    """Per module: jitter (median to 95th percentile bar, maximum marker) on a log axis, and
    beside it the mean CPU (% of one core, children included), loop rate, heartbeats, overruns,
    restarts, rejects and output rates."""
    modules = list(data.modules.values())
    row_px = 30
    width = CHART_SIZE[0]
    height = 56 + 62 + row_px * max(1, len(modules)) + 40
    image = np.full((height, width, 3), PAPER, dtype=np.uint8)
    labels = [timing.module for timing in modules] or ["(no heartbeats recorded)"]
    jitter = [np.array(timing.jitter_ms) for timing in modules]
    worst = max((float(j.max()) for j in jitter if len(j)), default=1.0)
    chart_w = 760
    names_px = max(cv2.getTextSize(label, FONT, 0.45, 1)[0][0] for label in labels) + 20
    chart = Chart(
        image,
        (0, 0, chart_w, height - 40),
        (0.01, 10 ** np.ceil(np.log10(max(worst, 0.1) * 1.5))),
        (0.0, float(len(labels))),
        "module timing",
        "activation jitter per heartbeat (ms, log scale)",
        "",
        log_x=True,
        left_px=names_px,
        y_labels=labels,
    )
    for index, values in enumerate(jitter):
        if not len(values):
            continue
        centre = len(labels) - index - 0.5
        p50, p95, top = (float(v) for v in np.percentile(values, [50, 95, 100]))
        low, high = chart.px([max(p50, 0.01), max(p95, 0.01)], [centre - 0.3, centre + 0.3])
        cv2.rectangle(image, _int(low), _int(high), JITTER, -1)
        cv2.rectangle(image, _int(low), _int(high), INK, 1)
        chart.markers([max(top, 0.01)], [centre], TRUE, radius=4)
    chart.legend = [
        LegendEntry("median to 95th percentile", JITTER, kind="band"),
        LegendEntry("maximum", TRUE, 4, "marker"),
    ]
    chart.draw_legend("above")
    _timing_table(image, modules, chart, chart_w + 20)
    draw_text(
        image,
        f"{len(modules)} modules over {data.duration_s:.0f} s; jitter = how late each periodic task ran "
        "(the worst in each 1 s heartbeat)",
        np.array([20.0, height - 14.0]),
        0.45,
    )
    return image


def _timing_table(image: np.ndarray, modules: list[Any], chart: Chart, left: int) -> None:
    columns = [
        ("cpu %", 60),
        ("loop Hz", 70),
        ("beats", 60),
        ("overruns", 80),
        ("restarts", 75),
        ("rejects", 70),
        ("outputs (Hz)", 0),
    ]
    _plot_left, plot_top, _w, _h = chart.plot
    x = left
    for name, width in columns:
        draw_text(image, name, np.array([float(x), plot_top - 10.0]), 0.45)
        x += width
    rows = len(chart.y_labels or [])
    for index, timing in enumerate(modules):
        _, y = chart.px(1.0, rows - index - 0.5)
        loop_hz = 1e9 / timing.loop_period_ns if timing.loop_period_ns else 0.0
        outputs = sorted(timing.outputs_hz.items(), key=lambda item: -item[1])
        shown = ", ".join(f"{channel} {hz:.3g}" for channel, hz in outputs[:MAX_OUTPUTS])
        shown += f" +{len(outputs) - MAX_OUTPUTS}" if len(outputs) > MAX_OUTPUTS else ""
        cpu = timing.mean_cpu_pct
        cells = [
            f"{cpu:.1f}" if cpu is not None else "-",
            f"{loop_hz:.0f}" if loop_hz else "-",
            str(timing.heartbeats),
            str(timing.overruns),
            str(timing.restarts),
            str(timing.rx_rejected),
            shown or "-",
        ]
        x = left
        for (_name, width), cell in zip(columns, cells, strict=True):
            draw_text(image, cell, np.array([float(x), float(y) + 5.0]), 0.45)
            x += width


def _int(point: np.ndarray) -> tuple[int, int]:
    return round(float(point[0])), round(float(point[1]))


# -- command line ---------------------------------------------------------------------------------


def add_report_command(commands: Any) -> None:
    """Register ``report`` on the `rascal` command's subparsers."""
    report = commands.add_parser("report", help="rebuild a run's report images (RUN_DIR/report/*.png)")
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
    print(f"report of {args.run_dir}: {', '.join(path.name for path in report.images.values())} in {report.directory}/")
    print(report.drive)
    return 0
