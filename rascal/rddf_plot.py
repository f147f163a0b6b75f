"""`rascal rddf plot FILE -o OUT.png|.svg`: the corridor, the path coloured by desired speed,
direction arrows, numbered waypoints (labels kept apart where the course loops back), start and
finish. The command's options are declared with the other rddf tools (rascal/rddf_cli.py)."""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from brain.corridor import Course, CoursePath
from rascal.plot_map import draw_corridor, draw_start_finish, freeze_map, label_start_finish, map_figure, speed_line
from rascal.plotting import DPI, INK, PAPER, LabelPlacer, save_as, speed_colorbar, styled
from rascal.rddf_cli import duration_text, load_course_path

MAX_LABELS = 60  # long courses mark every n-th waypoint only, so the markers do not bury the path
ARROWS = 16  # direction arrows along the centreline
MARKER_PX = 4.0
FORMATS = (".png", ".svg", ".pdf")


def plot_command(args: argparse.Namespace) -> int:
    """The handler of ``rascal rddf plot``: one clear line and exit 2 for a bad file or output."""
    if args.output.suffix.lower() not in FORMATS:
        print(f"rascal rddf plot: {args.output}: name it .png, .svg or .pdf", file=sys.stderr)
        return 2
    try:
        course, path = load_course_path(args)
    except (OSError, ValueError) as exc:  # RddfError is a ValueError
        print(f"rascal rddf plot: {exc}", file=sys.stderr)
        return 2
    figure = render_course(course, path, args.file.name, args.size_px)
    try:
        save_as(figure, args.output)
    except OSError as exc:
        print(f"rascal rddf plot: {args.output}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    width, height = (round(v) for v in figure.get_size_inches() * DPI)
    print(f"wrote {args.output} ({width} x {height} px)")
    return 0


@styled
def render_course(course: Course, path: CoursePath, title: str, size_px: int = 1600) -> Figure:
    """The course map: fits in a square of ``size_px`` pixels (PNG)."""
    figure, ax = map_figure(course.corridor.bounds_m(), size_px)
    vmax_mps = float(course.speed_limit_mps.max())
    draw_corridor(ax, course)
    line = speed_line(ax, path.east_m, path.north_m, path.speed_mps, vmax_mps)
    _direction_arrows(ax, path)
    shown = _marked_waypoints(course)
    ax.scatter(
        course.east_m[shown],
        course.north_m[shown],
        s=(2 * MARKER_PX) ** 2 / 4,
        c=PAPER,
        edgecolors=INK,
        linewidths=0.8,
        zorder=5,
    )
    ends = draw_start_finish(ax, course)
    figure.suptitle(title, x=0.01, ha="left", fontsize=13)
    ax.set_title(_summary(course, path), loc="left", fontsize=9)
    speed_colorbar(figure, ax, line, "desired speed")
    freeze_map(figure, ax)
    placer = LabelPlacer(ax)
    placer.avoid(np.column_stack([course.east_m[shown], course.north_m[shown]]), MARKER_PX)
    label_start_finish(placer, ends)
    for k in shown:
        xy = (float(course.east_m[k]), float(course.north_m[k]))
        placer.place(xy, str(course.waypoints[k].number), clear_px=MARKER_PX, fontsize=8, color=INK, zorder=7)
    return figure


def _marked_waypoints(course: Course) -> np.ndarray:
    every = max(1, math.ceil(len(course.waypoints) / MAX_LABELS))
    return np.arange(0, len(course.waypoints), every)


def _direction_arrows(ax: Axes, path: CoursePath) -> None:
    count = len(path.s_m)
    for k in np.linspace(0, count - 1, ARROWS + 2).round().astype(int)[1:-1]:
        heading = np.array(
            [
                path.east_m[min(k + 1, count - 1)] - path.east_m[max(k - 1, 0)],
                path.north_m[min(k + 1, count - 1)] - path.north_m[max(k - 1, 0)],
            ]
        )
        norm = float(np.hypot(*heading))
        if norm == 0.0:
            continue
        # A fixed size on the page whatever the course's scale: the tail is offset in points.
        tail = -heading / norm * 12.0
        ax.annotate(
            "",
            (path.east_m[k], path.north_m[k]),
            xytext=tuple(tail),
            textcoords="offset points",
            arrowprops={"arrowstyle": "-|>", "color": INK, "lw": 1.0, "shrinkA": 0, "shrinkB": 0},
            zorder=5,
        )


def _summary(course: Course, path: CoursePath) -> str:
    return (
        f"{len(course.waypoints)} waypoints, {_distance(course.length_m)}, "
        f"corridor {_range(2.0 * course.half_width_m)} m wide, "
        f"drive time {duration_text(path.drive_time_s())}"
    )


def _distance(metres: float) -> str:
    return f"{metres:.0f} m" if metres < 10_000.0 else f"{metres / 1000.0:.1f} km"


def _range(values: np.ndarray) -> str:
    low, high = f"{values.min():.1f}", f"{values.max():.1f}"
    return low if low == high else f"{low}-{high}"
