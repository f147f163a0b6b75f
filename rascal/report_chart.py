"""The report's charts along the course and of module timing, drawn with matplotlib
(rascal/plotting.py): speed against the limits, offset from the centre line and distance from
the planned path, and per module jitter beside a table of its figures."""

from __future__ import annotations

from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from rascal.plotting import CORRIDOR_EDGE, CORRIDOR_FILL, INK, new_figure, styled
from rascal.report_data import FloatArray, RunData, Track

CHART_PX = (1600, 640)  # width, height of one chart panel
TRUE = "#c82828"
NAV = "#5a5a5a"
LIMIT = "#3c3c3c"
PROFILE = "#3caae6"
JITTER = "#288cc8"
OBSTACLE = "#784620"
MAX_OUTPUTS = 4
STATION = "station along the course (m)"


# -- along the course ----------------------------------------------------------------------------


@styled
def render_speed(data: RunData) -> Figure:
    figure = new_figure(*CHART_PX)
    ax = figure.add_subplot()
    path = data.frame.path
    ax.plot(path.s_m, path.speed_limit_mps, color=LIMIT, lw=1.6, label="RDDF speed limit")
    ax.plot(path.s_m, path.speed_mps, color=PROFILE, lw=1.6, label="course speed profile (limit, turns, braking)")
    if data.nav is not None:
        ax.plot(*_forward(data.nav, data.nav.speed_mps), color=NAV, lw=0.8, label="navigation estimate")
    if data.truth is not None:
        ax.plot(*_forward(data.truth, data.truth.speed_mps), color=TRUE, lw=1.6, label="true speed")
    drive = data.summary.get("drive") or {}
    note = (
        f"mean {drive.get('mean_speed_mps', 0):.2f} m/s against an allowed mean of "
        f"{drive.get('allowed_mean_speed_mps', 0):.2f} m/s (ratio {drive.get('speed_ratio', 0):.2f}) "
        "over the part driven"
        if "mean_speed_mps" in drive
        else ""
    )
    _along_course(ax, data, "speed along the course", "speed (m/s)", note)
    top = max(float(path.speed_limit_mps.max()), *(float(t.speed_mps.max()) for t in _tracks(data)))
    ax.set_ylim(0.0, 1.15 * top)
    ax.legend(loc="upper right", ncols=4)  # one row, in the headroom above the data
    return figure


@styled
def render_cross_track(data: RunData) -> Figure:
    figure = new_figure(CHART_PX[0], 2 * CHART_PX[1])
    offset, tracking = figure.subplots(2, 1, sharex=True)
    _offset_panel(offset, data)
    _tracking_panel(tracking, data)
    return figure


def _offset_panel(ax: Axes, data: RunData) -> None:
    frame = data.frame
    s = frame.s_m
    half = frame.half_width_at(s)
    ax.fill_between(s, -half, half, color=CORRIDOR_FILL, label="corridor", lw=0)
    ax.plot(s, half, s, -half, color=CORRIDOR_EDGE, lw=0.8)
    if data.obstacles:
        east = np.array([o.east_m for o in data.obstacles])
        north = np.array([o.north_m for o in data.obstacles])
        radius = np.array([o.footprint_radius_m() for o in data.obstacles])
        obstacle_s, obstacle_d = frame.locate(east, north)
        ax.vlines(
            obstacle_s,
            obstacle_d - radius,
            obstacle_d + radius,
            colors=OBSTACLE,
            lw=5,
            label="obstacle across the course (scenario)",
        )
    if data.nav is not None:
        ax.plot(*_forward(data.nav, data.nav.d_m), color=NAV, lw=0.8, label="navigation estimate")
    if data.truth is not None:
        ax.plot(*_forward(data.truth, data.truth.d_m), color=TRUE, lw=1.6, label="true position")
    _along_course(ax, data, "offset from the course centre line", "offset, left positive (m)", "")
    ax.set_ylim(-1.1 * float(half.max()), 1.1 * float(half.max()))
    # Above the panel, beside its title: inside, it would cover the corridor's edge.
    ax.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), ncols=4, frameon=False, borderaxespad=0.2)


def _tracking_panel(ax: Axes, data: RunData) -> None:
    track = data.truth or data.nav
    errors = _path_errors(track, data.paths) if track is not None else np.zeros(0)
    finite = errors[np.isfinite(errors)]
    if track is not None:
        label = "true position" if track is data.truth else "navigation estimate"
        ax.plot(*_forward(track, errors), color=TRUE, lw=1.6, label=label)
        ax.legend(loc="upper right")
    rms = float(np.sqrt(np.mean(finite**2))) if len(finite) else 0.0
    note = f"RMS {rms:.2f} m, max {finite.max():.2f} m, over {len(finite)} samples at 10 Hz" if len(finite) else ""
    _along_course(
        ax, data, "distance from the newest planned path (what control tracks)", "cross-track error (m)", note
    )
    ax.set_ylim(0.0, max(0.5, 1.2 * float(finite.max())) if len(finite) else 1.0)


def _along_course(ax: Axes, data: RunData, title: str, y_label: str, note: str) -> None:
    """Title on the left, what the numbers say on the right, station on x."""
    ax.set_xlim(0.0, data.frame.length_m)
    ax.set_title(title, loc="left", fontsize=12)
    ax.set_title(note, loc="right", fontsize=9)
    ax.set_xlabel(STATION)
    ax.set_ylabel(y_label)


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

COLUMNS = ("CPU %", "loop (Hz)", "heartbeats", "overruns", "restarts", "rejected", "outputs (Hz)")


@styled
def render_timing(data: RunData) -> Figure:
    """Per module: jitter (median to 95th percentile bar, maximum marker) on a log axis, and
    beside it the mean CPU (% of one core, children included), loop rate, heartbeats, overruns,
    restarts, rejects and output rates, row by row."""
    modules = list(data.modules.values())
    rows = max(1, len(modules))
    figure = new_figure(CHART_PX[0], 200 + 30 * rows)
    bars, table = figure.subplots(1, 2, sharey=True, width_ratios=[1.0, 1.6])
    _jitter_bars(bars, modules)
    bars.set_ylim(0.0, rows)
    _timing_table(table, modules, rows)
    figure.suptitle(
        f"module timing: {len(modules)} module{'s' if len(modules) != 1 else ''} over {data.duration_s:.0f} s "
        "(CPU: mean % of one core, children included)",
        x=0.01,
        ha="left",
    )
    return figure


def _jitter_bars(ax: Axes, modules: list[Any]) -> None:
    jitter = [np.array(timing.jitter_ms) for timing in modules]
    rows = max(1, len(modules))
    centres = rows - np.arange(len(modules)) - 0.5  # the first module on top
    stats = np.array([np.percentile(j, [50, 95, 100]) if len(j) else [np.nan] * 3 for j in jitter]).reshape(-1, 3)
    low, high, top = np.maximum(stats, 0.01).T  # the log axis starts at 0.01 ms
    if modules:
        ax.barh(
            centres,
            high - low,
            left=low,
            height=0.6,
            color=JITTER,
            edgecolor=INK,
            lw=0.6,
            label="median to 95th percentile",
        )
        # Unclipped: a module that never ran late has its maximum on the axis' left edge.
        ax.scatter(top, centres, s=30, color=TRUE, edgecolors=INK, lw=0.6, zorder=3, clip_on=False, label="maximum")
        ax.legend(loc="lower left", bbox_to_anchor=(0.0, 1.0), ncols=2, frameon=False)
    worst = max((float(j.max()) for j in jitter if len(j)), default=1.0)
    ax.set_xscale("log")
    ax.set_xlim(0.01, 10 ** np.ceil(np.log10(max(worst, 0.1) * 1.5)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _pos: f"{value:g}"))  # 0.01, not 10^-2
    ax.set_yticks(centres if modules else [0.5], [t.module for t in modules] or ["(no heartbeats recorded)"])
    ax.tick_params(axis="y", length=0)
    ax.grid(axis="y", visible=False)
    ax.set_xlabel("activation jitter: how late each periodic task ran, worst per 1 s heartbeat (ms, log scale)")


def _timing_table(ax: Axes, modules: list[Any], rows: int) -> None:
    """One row of figures beside each module's bar (the axes share y), the headings above. Plain
    texts, not a matplotlib table: its cells cost more to lay out than the rest of the chart."""
    ax.axis("off")
    cells = [_timing_cells(timing) for timing in modules] or [["-"] * len(COLUMNS)]
    # Each column's share of the width follows its longest text, in characters.
    longest = np.array([max(len(text) for text in column) + 3 for column in zip(COLUMNS, *cells, strict=True)])
    starts = np.concatenate([[0.0], np.cumsum(longest)[:-1]]) / longest.sum()
    for x, heading in zip(starts, COLUMNS, strict=True):
        # A fixed distance above the rows, beside the bars' legend: the layout makes room for it.
        ax.annotate(
            heading,
            (x, 1.0),
            xycoords="axes fraction",
            xytext=(0, 6),
            textcoords="offset points",
            fontsize=9,
            fontweight="bold",
        )
    place = ax.get_yaxis_transform()  # x across the axes, y in rows
    for y, row in zip(rows - np.arange(len(cells)) - 0.5, cells, strict=True):
        for x, text in zip(starts, row, strict=True):
            ax.text(x, y, text, transform=place, va="center", fontsize=9)


def _timing_cells(timing: Any) -> list[str]:
    loop_hz = 1e9 / timing.loop_period_ns if timing.loop_period_ns else 0.0
    outputs = sorted(timing.outputs_hz.items(), key=lambda item: -item[1])
    shown = ", ".join(f"{channel} {hz:.3g}" for channel, hz in outputs[:MAX_OUTPUTS])
    shown += f" +{len(outputs) - MAX_OUTPUTS}" if len(outputs) > MAX_OUTPUTS else ""
    cpu = timing.mean_cpu_pct
    return [
        f"{cpu:.1f}" if cpu is not None else "-",
        f"{loop_hz:.0f}" if loop_hz else "-",
        str(timing.heartbeats),
        str(timing.overruns),
        str(timing.restarts),
        str(timing.rx_rejected),
        shown or "-",
    ]
