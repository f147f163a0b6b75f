"""Maps of a course for `rascal rddf plot` and the run report: axes in the course's local frame
(east and north in metres from the first waypoint, equal aspect), the corridor, a line coloured
by speed, start and finish."""

from __future__ import annotations

import itertools

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import PathPatch
from matplotlib.path import Path as MplPath

from brain.corridor import Corridor, Course
from rascal.plotting import (
    CORRIDOR_EDGE,
    CORRIDOR_FILL,
    INK,
    SPEED_CMAP,
    LabelPlacer,
    freeze_layout,
    new_figure,
    speed_norm,
    style,
)

START_COLOR = "#28aa3c"
FINISH_COLOR = "#d22828"
AXES_PX = (150, 250)  # width and height around the map: tick labels, axis labels, titles, colour bar
MIN_WIDTH_PX = 800  # room for the colour bar and legend beside narrow courses
CIRCLE = MplPath.unit_circle()
SPEED_LEVELS = 64  # colours of a speed line: finer than the eye tells apart on the colour bar


def map_figure(bounds_m: tuple[float, float, float, float], size_px: int) -> tuple[Figure, Axes]:
    """A figure that fits in a square of ``size_px`` with one map axes of the bounds' shape."""
    min_e, min_n, max_e, max_n = bounds_m
    extra_w, extra_h = AXES_PX
    span_e, span_n = max(max_e - min_e, 1.0), max(max_n - min_n, 1.0)
    scale = min((size_px - extra_w) / span_e, (size_px - extra_h) / span_n)
    width = min(max(span_e * scale + extra_w, MIN_WIDTH_PX), size_px)
    figure = new_figure(width, span_n * scale + extra_h)
    ax = figure.add_subplot()
    # The limits give way, not the axes: the map fills its place (no blank bands beside it, a
    # colour bar as wide as the map), showing a little more ground along one axis. So the limits
    # stay automatic, from the bounds and what is drawn.
    ax.set_aspect("equal", adjustable="datalim")
    ax.use_sticky_edges = False  # an image layer does not pin the map's edges
    ax.update_datalim([(min_e, min_n), (max_e, max_n)])
    ax.margins(0.02)
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    return figure, ax


def freeze_map(figure: Figure, ax: Axes) -> None:
    """`freeze_layout` with the map's limits fitted to its place and kept. A first layout pass
    gives the place (widening the limits to fill the place the map had before it); the limits
    refitted to it are fixed, with the axes no longer giving way; the last pass makes room for
    the tick labels of those limits."""
    with style():
        figure.draw_without_rendering()
    ax.autoscale_view()
    ax.apply_aspect()
    ax.set_xlim(ax.get_xlim())
    ax.set_ylim(ax.get_ylim())
    ax.set_adjustable("box")
    freeze_layout(figure)


def corridor_path(corridor: Corridor) -> MplPath:
    """The corridor as one compound path: a band and two end circles per segment, all wound the
    same way, so filling it (non-zero rule) paints their union once, translucent or not."""
    parts: list[MplPath] = []
    for start, end, radius in zip(corridor.start_m, corridor.end_m, corridor.half_width_m, strict=True):
        along = end - start
        length = float(np.hypot(*along))
        if length > 0.0:
            normal = np.array([-along[1], along[0]]) / length * radius
            # Counter-clockwise, as the unit circle is.
            band = np.array([start - normal, end - normal, end + normal, start + normal, start - normal])
            parts.append(MplPath(band, closed=True))
        for centre in (start, end):
            parts.append(MplPath(CIRCLE.vertices * radius + centre, CIRCLE.codes))
    return MplPath.make_compound_path(*parts)


def draw_corridor(ax: Axes, course: Course) -> None:
    """The corridor filled, with its outline: the whole path stroked, then filled over, so only
    the outer half of the stroke (the union's edge) shows."""
    path = corridor_path(course.corridor)
    ax.add_patch(PathPatch(path, facecolor="none", edgecolor=CORRIDOR_EDGE, linewidth=1.6, zorder=1))
    ax.add_patch(PathPatch(path, facecolor=CORRIDOR_FILL, edgecolor="none", zorder=1.1))


def speed_line(
    ax: Axes, east_m: np.ndarray, north_m: np.ndarray, speed_mps: np.ndarray, vmax_mps: float
) -> LineCollection:
    """A line through the points, each step in the colour of its mean speed. Runs of steps whose
    speed falls in one of `SPEED_LEVELS` levels are drawn as one polyline: a few hundred paths in
    the SVG instead of a path per step."""
    points = np.column_stack([east_m, north_m])
    steps = np.clip(0.5 * (speed_mps[:-1] + speed_mps[1:]) / max(vmax_mps, 1e-6), 0.0, 1.0)
    levels = np.round(steps * (SPEED_LEVELS - 1))
    breaks = np.concatenate([[0], np.flatnonzero(np.diff(levels)) + 1, [len(levels)]])
    runs = [points[first : stop + 1] for first, stop in itertools.pairwise(breaks)]
    line = LineCollection(
        runs,
        cmap=SPEED_CMAP,
        norm=speed_norm(vmax_mps),
        linewidths=2.5,
        capstyle="round",
        joinstyle="round",
        zorder=4,
    )
    line.set_array(levels[breaks[:-1]] / (SPEED_LEVELS - 1) * vmax_mps)
    ax.add_collection(line)
    return line


def draw_start_finish(ax: Axes, course: Course) -> list[tuple[tuple[float, float], str, str]]:
    """Start (green disc) and finish (red square); returns their labels for a `LabelPlacer`."""
    start = (float(course.east_m[0]), float(course.north_m[0]))
    finish = (float(course.east_m[-1]), float(course.north_m[-1]))
    # The start's disc is the smaller and on top: on a loop it shows inside the finish's square.
    ax.scatter(*finish, s=110, c=FINISH_COLOR, marker="s", edgecolors=INK, linewidths=0.8, zorder=6)
    ax.scatter(*start, s=50, c=START_COLOR, edgecolors=INK, linewidths=0.8, zorder=6.5)
    return [(start, "START", START_COLOR), (finish, "FINISH", FINISH_COLOR)]


def label_start_finish(placer: LabelPlacer, labels: list[tuple[tuple[float, float], str, str]]) -> None:
    """START and FINISH first, clear of both markers (they coincide on a loop)."""
    for xy, _text, _color in labels:
        placer.avoid(np.array(xy), 6.0)
    for xy, text, color in labels:
        placer.place(xy, text, clear_px=6.0, color=color, fontweight="bold", zorder=7)
