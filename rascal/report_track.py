"""The report's two maps, drawn with matplotlib on the RDDF plot's map (rascal/plot_map.py): the
whole course with the track driven, the obstacles and every hazard the brain mapped; and the
brain's final map up close."""

from __future__ import annotations

import math

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import PatchCollection
from matplotlib.colors import LinearSegmentedColormap
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Patch, Polygon
from matplotlib.transforms import Bbox

from brain.corridor import Corridor
from brain.fusion.snapshot import SnapshotError, decode_snapshot
from modules.sim.world import Shape, WorldObstacle
from protocol.messages import MapSnapshot
from rascal.plot_map import draw_corridor, draw_start_finish, freeze_map, label_start_finish, map_figure, speed_line
from rascal.plotting import (
    CORRIDOR_EDGE,
    CORRIDOR_FILL,
    INK,
    PAPER,
    LabelPlacer,
    pin_legend,
    speed_colorbar,
    styled,
)
from rascal.report_data import RunData, Track, drive_line

HAZARD = "#c83c28"
UNKNOWN = "#cdcdcd"
OBSTACLE = "#784620"
NAV = "#3c3c3c"
PLAN = "#0078c8"
MOSAIC_FLOOR = 0.6  # mapped cells above this hazard probability are shown on the course map
MOSAIC_CELLS = 1600  # the course map's hazard layer: at most this many cells across
MAP_PX_PER_M = 8.0
PROBABILITY_CMAP = LinearSegmentedColormap.from_list("hazard", [PAPER, UNKNOWN, HAZARD])


@styled
def render_track(data: RunData, title: str, size_px: int = 1600) -> Figure:
    """The course: corridor, hazards mapped, obstacles, the true track coloured by speed, the
    navigation estimate, start and finish, with the drive in one line and a legend."""
    bounds = data.course.corridor.bounds_m()
    figure, ax = map_figure(bounds, size_px)
    draw_corridor(ax, data.course)
    legend = [Patch(facecolor=CORRIDOR_FILL, edgecolor=CORRIDOR_EDGE, label="corridor (RDDF)")]
    if _draw_hazard_mosaic(ax, data.snapshots, bounds):
        legend.append(Patch(facecolor=HAZARD, label=f"hazard mapped by the brain (probability > {MOSAIC_FLOOR:g})"))
    if data.obstacles:
        east, north = zip(*((o.east_m, o.north_m) for o in data.obstacles), strict=True)
        ax.scatter(east, north, s=14, c=OBSTACLE, edgecolors="none", zorder=3)
        legend.append(Line2D([], [], ls="", marker="o", ms=4, color=OBSTACLE, label="obstacle (scenario)"))
    if data.nav is not None:
        ax.plot(data.nav.east_m, data.nav.north_m, color=NAV, lw=0.8, zorder=3.5)
        legend.append(Line2D([], [], color=NAV, lw=0.8, label="navigation estimate"))
    if data.truth is not None:
        line = speed_line(
            ax, data.truth.east_m, data.truth.north_m, data.truth.speed_mps, float(data.course.speed_limit_mps.max())
        )
        speed_colorbar(figure, ax, line, "true speed driven")
    ends = draw_start_finish(ax, data.course)
    figure.suptitle(title, x=0.01, ha="left", fontsize=13)
    ax.set_title(drive_line(data), loc="left", fontsize=9)
    key = ax.legend(handles=legend, loc="best", framealpha=0.9)
    freeze_map(figure, ax)
    pin_legend(key, ax)
    placer = LabelPlacer(ax)
    placer.avoid_artist(key)
    label_start_finish(placer, ends)
    return figure


@styled
def render_final_map(data: RunData, title: str) -> Figure | None:
    """The brain's last map snapshot up close, with the corridor, the true obstacles, the last
    planned path and the track; None when the run has no snapshot."""
    decoded = _last_decodable(data.snapshots)
    if decoded is None:
        return None
    t_s, snapshot, probability = decoded
    rows, cols = probability.shape
    bounds = (
        snapshot.origin_east_m,
        snapshot.origin_north_m,
        snapshot.origin_east_m + cols * snapshot.resolution_m,
        snapshot.origin_north_m + rows * snapshot.resolution_m,
    )
    side_px = max(bounds[2] - bounds[0], bounds[3] - bounds[1]) * MAP_PX_PER_M
    figure, ax = map_figure(bounds, round(side_px) + 250)
    image = ax.imshow(
        probability,
        origin="lower",
        extent=(bounds[0], bounds[2], bounds[1], bounds[3]),
        cmap=PROBABILITY_CMAP,
        vmin=0.0,
        vmax=1.0,
        interpolation="nearest",
        zorder=0,
    )
    _corridor_over_map(ax, data.course.corridor, bounds)
    patches = [_obstacle_patch(o) for o in data.obstacles]
    ax.add_collection(PatchCollection(patches, facecolors="none", edgecolors=OBSTACLE, linewidths=2, zorder=3))
    newest = [points for t, points in data.paths if t <= t_s]
    if newest:
        ax.plot(newest[-1][:, 0], newest[-1][:, 1], color=PLAN, lw=2, zorder=4)
    track = data.truth or data.nav
    if track is not None:
        _track_to(ax, track, t_s)
    # The map's edge is the grid's: the track, paths and obstacles beyond it do not widen it.
    ax.dataLim.set_points(np.array([bounds[:2], bounds[2:]]))
    ax.margins(0.0)
    ax.patch.set_hatch("//")  # beyond the grid (the equal aspect may show some): not white, which is clear
    ax.patch.set_hatchcolor(UNKNOWN)
    bar = figure.colorbar(
        image, ax=ax, orientation="horizontal", location="bottom", fraction=0.035, aspect=40, pad=0.02
    )
    bar.set_label("hazard probability")
    bar.set_ticks([0.0, 0.5, 1.0], labels=["0 clear", "0.5 unknown", "1 hazard"])
    first, _middle, last = bar.ax.get_xticklabels()
    first.set_horizontalalignment("left")  # the end labels stay over the bar, clear of the page's edge
    last.set_horizontalalignment("right")
    figure.suptitle(title, x=0.01, ha="left", fontsize=13)
    ax.set_title(
        f"the brain's map at {t_s:.0f} s: {cols} x {rows} cells of {snapshot.resolution_m:.2f} m",
        loc="left",
        fontsize=9,
    )
    legend = [
        Patch(facecolor=PAPER, edgecolor=UNKNOWN, hatch="//", label="outside the brain's map"),
        Line2D([], [], color=OBSTACLE, lw=2, label="obstacle outline (scenario)"),
        Line2D([], [], color=PLAN, lw=2, label="last planned path"),
        Line2D([], [], color=INK, lw=1.5, marker="o", mfc="none", label="track (circle: vehicle at the map's time)"),
    ]
    in_view = Bbox.from_extents(bounds[0], bounds[1], bounds[2], bounds[3])
    seen = any(in_view.overlaps(patch.get_extents()) for patch in patches)
    ax.legend(handles=legend if seen else [legend[0], *legend[2:]], loc="best", framealpha=0.9)
    freeze_map(figure, ax)
    return figure


# -- pieces -------------------------------------------------------------------------------------


def _draw_hazard_mosaic(ax: Axes, snapshots: list[tuple[float, MapSnapshot]], bounds: tuple[float, ...]) -> bool:
    """Every cell any snapshot held above `MOSAIC_FLOOR`, the most probable on top, as one
    translucent layer; False when there is none."""
    min_e, min_n, max_e, max_n = bounds
    finest = min((s.resolution_m for _t, s in snapshots), default=1.0)
    cell_m = max(finest, max(max_e - min_e, max_n - min_n) / MOSAIC_CELLS)
    shape = (math.ceil((max_n - min_n) / cell_m) + 1, math.ceil((max_e - min_e) / cell_m) + 1)
    hazard = np.zeros(shape, dtype=np.float32)
    for _t, snapshot in snapshots:
        _raise_hazard(hazard, snapshot, (min_e, min_n), cell_m)
    if not hazard.any():
        return False
    layer = np.zeros((*shape, 4), dtype=np.float32)
    layer[..., :3] = np.array([int(HAZARD[k : k + 2], 16) for k in (1, 3, 5)]) / 255.0
    layer[..., 3] = np.clip((hazard - MOSAIC_FLOOR) / (1.0 - MOSAIC_FLOOR), 0.0, 1.0) * 0.85
    extent = (min_e, min_e + shape[1] * cell_m, min_n, min_n + shape[0] * cell_m)
    ax.imshow(layer, origin="lower", extent=extent, interpolation="nearest", zorder=2)
    return True


def _raise_hazard(hazard: np.ndarray, snapshot: MapSnapshot, origin: tuple[float, float], cell_m: float) -> None:
    """Raise the mosaic's cells to the snapshot's hazardous cells' probabilities (max-pooled: a
    hazard smaller than a mosaic cell still shows)."""
    try:
        probability = decode_snapshot(snapshot)[1]
    except SnapshotError:
        return
    rows, cols = np.nonzero(probability > MOSAIC_FLOOR)
    if not len(rows):
        return
    east = snapshot.origin_east_m + (cols + 0.5) * snapshot.resolution_m
    north = snapshot.origin_north_m + (rows + 0.5) * snapshot.resolution_m
    mosaic_rows = np.clip(((north - origin[1]) / cell_m).astype(int), 0, hazard.shape[0] - 1)
    mosaic_cols = np.clip(((east - origin[0]) / cell_m).astype(int), 0, hazard.shape[1] - 1)
    np.maximum.at(hazard, (mosaic_rows, mosaic_cols), probability[rows, cols])


def _last_decodable(snapshots: list[tuple[float, MapSnapshot]]) -> tuple[float, MapSnapshot, np.ndarray] | None:
    for t_s, snapshot in reversed(snapshots):
        try:
            return t_s, snapshot, decode_snapshot(snapshot)[1]
        except SnapshotError:
            continue
    return None


def _corridor_over_map(ax: Axes, corridor: Corridor, bounds: tuple[float, float, float, float]) -> None:
    """The corridor see-through over the map, its edge a contour of the distance to it (only
    the segments near the map are measured)."""
    min_e, min_n, max_e, max_n = bounds
    reach = corridor.half_width_m
    low = np.minimum(corridor.start_m, corridor.end_m) - reach[:, None]
    high = np.maximum(corridor.start_m, corridor.end_m) + reach[:, None]
    near = (low[:, 0] <= max_e) & (high[:, 0] >= min_e) & (low[:, 1] <= max_n) & (high[:, 1] >= min_n)
    if not near.any():
        return
    part = Corridor(corridor.start_m[near], corridor.end_m[near], corridor.half_width_m[near])
    east, north = np.meshgrid(np.linspace(min_e, max_e, 400), np.linspace(min_n, max_n, 400))
    inside = part.distance_to_edge(east, north)
    if inside.max() <= 0.0:
        return
    ax.contourf(east, north, inside, levels=[0.0, inside.max() + 1.0], colors=[CORRIDOR_FILL], alpha=0.45, zorder=1)
    if inside.min() < 0.0:
        ax.contour(east, north, inside, levels=[0.0], colors=[CORRIDOR_EDGE], linewidths=1.2, zorder=1)


def _obstacle_patch(obstacle: WorldObstacle) -> Patch:
    centre = (obstacle.east_m, obstacle.north_m)
    if obstacle.shape is Shape.CYLINDER:
        return Circle(centre, obstacle.radius_m)
    c, s = math.cos(obstacle.yaw_rad), math.sin(obstacle.yaw_rad)
    half_l, half_w = obstacle.length_m / 2.0, obstacle.width_m / 2.0
    corners = [
        (centre[0] + dx * c - dy * s, centre[1] + dx * s + dy * c)
        for dx, dy in ((half_l, half_w), (-half_l, half_w), (-half_l, -half_w), (half_l, -half_w))
    ]
    return Polygon(corners, closed=True)


def _track_to(ax: Axes, track: Track, t_s: float) -> None:
    """The track, and a circle where the vehicle was at ``t_s``."""
    ax.plot(track.east_m, track.north_m, color=INK, lw=1.5, zorder=4)
    last = int(np.searchsorted(track.t_s, t_s, side="right")) - 1
    if last >= 0:
        ax.scatter(track.east_m[last], track.north_m[last], s=150, facecolors="none", edgecolors=INK, lw=1.8, zorder=5)
