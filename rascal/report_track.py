"""The report's two maps: the whole course with the track driven, the obstacles and every hazard
the brain mapped; and the brain's final map up close. Drawn on the RDDF plot's canvas
(brain/rddf_cli.py: corridor, start and finish, scale bar, north arrow, speed colours)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from brain.fusion.snapshot import SnapshotError, decode_snapshot
from brain.rddf_cli import (
    FOOTER_PX,
    HEADER_PX,
    INK,
    MARGIN_PX,
    PAPER,
    SHIFT,
    Canvas,
    Color,
    draw_corridor,
    draw_north_arrow,
    draw_scale_bar,
    draw_speed_legend,
    draw_start_finish,
    draw_text,
    speed_colors,
    to_point,
)
from modules.sim.world import Shape, WorldObstacle
from protocol.messages import MapSnapshot
from rascal.report_chart import LegendEntry, draw_legend, legend_size
from rascal.report_data import RunData, Track

HAZARD: Color = (40, 60, 200)
UNKNOWN: Color = (205, 205, 205)
OBSTACLE: Color = (30, 70, 120)
NAV: Color = (60, 60, 60)
PLAN: Color = (200, 120, 0)
MOSAIC_FLOOR = 0.6  # mapped cells above this hazard probability are shown on the course map
MAP_PX_PER_M = 8.0


def render_track(data: RunData, title: str, size_px: int = 1600) -> np.ndarray:
    """The course: corridor, hazards mapped, obstacles, the true track coloured by speed, the
    navigation estimate, start and finish, with a header, legend, scale and north arrow."""
    canvas = Canvas(data.course.corridor.bounds_m(), size_px)
    draw_corridor(canvas, data.course)
    hazard = np.zeros(canvas.image.shape[:2], dtype=np.float32)
    for _t, snapshot in data.snapshots:
        _mosaic(canvas, snapshot, hazard)
    alpha = np.clip((hazard - MOSAIC_FLOOR) / (1.0 - MOSAIC_FLOOR), 0.0, 1.0)[..., None] * 0.85
    canvas.image[:] = (canvas.image * (1.0 - alpha) + np.array(HAZARD) * alpha).astype(np.uint8)
    for obstacle in data.obstacles:
        _draw_obstacle(canvas, obstacle, filled=True)
    vmax = float(data.course.speed_limit_mps.max())
    if data.nav is not None:
        _polyline(canvas, data.nav, NAV, 1)
    if data.truth is not None:
        _speed_track(canvas, data.truth, vmax)
    draw_start_finish(canvas, data.course)
    draw_text(canvas.image, title, np.array([MARGIN_PX, 28.0]), 0.7)
    draw_text(canvas.image, drive_line(data), np.array([MARGIN_PX, 52.0]), 0.5)
    draw_scale_bar(canvas)
    draw_speed_legend(canvas, vmax, "speed driven (true)")
    draw_north_arrow(canvas)
    entries = [LegendEntry("corridor (RDDF)", (236, 226, 214), kind="band")]
    entries += [LegendEntry("hazard mapped by the brain", HAZARD, kind="band")] if data.snapshots else []
    entries += [LegendEntry("obstacle (scenario)", OBSTACLE, 5, "marker")] if data.obstacles else []
    entries += [LegendEntry("navigation estimate", NAV, 2)] if data.nav is not None else []
    _corner_legend(canvas.image, entries)
    return canvas.image


def render_final_map(data: RunData, title: str) -> np.ndarray | None:
    """The brain's last map snapshot up close, with the corridor edge, the true obstacles, the
    last planned path and the track; None when the run has no snapshot."""
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
    side_m = max(bounds[2] - bounds[0], bounds[3] - bounds[1])
    canvas = Canvas(bounds, round(side_m * MAP_PX_PER_M) + 2 * MARGIN_PX + HEADER_PX + FOOTER_PX)
    inside = _warp_cells(canvas, snapshot, np.full(probability.shape, 255, np.uint8), cv2.INTER_NEAREST) > 0
    canvas.image[inside] = _warp_cells(canvas, snapshot, _probability_colours(probability), cv2.INTER_NEAREST)[inside]
    under = canvas.image.copy()
    draw_corridor(canvas, data.course)  # see-through, so the map shows inside the corridor
    canvas.image[:] = (0.55 * under + 0.45 * canvas.image).astype(np.uint8)
    for obstacle in data.obstacles:
        _draw_obstacle(canvas, obstacle, filled=False)
    newest = [points for t, points in data.paths if t <= t_s]
    if newest:
        pixels = canvas.fixed(canvas.pixels(newest[-1][:, 0], newest[-1][:, 1]))
        cv2.polylines(canvas.image, [pixels], False, PLAN, 2, cv2.LINE_AA, SHIFT)
    track = data.truth or data.nav
    if track is not None:
        _polyline(canvas, track, INK, 2)
        last = int(np.searchsorted(track.t_s, t_s, side="right")) - 1
        if last >= 0:
            cv2.circle(canvas.image, to_point(canvas.pixels(track.east_m[last], track.north_m[last])), 7, INK, 2)
    canvas.image[~inside] = PAPER  # the corridor and track beyond the map would only crowd the labels
    x0, y0 = canvas.pixels(bounds[0], bounds[3])
    x1, y1 = canvas.pixels(bounds[2], bounds[1])
    cv2.rectangle(canvas.image, to_point([x0 - 1, y0 - 1]), to_point([x1, y1]), INK, 1)
    draw_text(canvas.image, title, np.array([MARGIN_PX, 28.0]), 0.7)
    draw_text(
        canvas.image,
        f"the brain's map at {t_s:.0f} s: {cols} x {rows} cells of {snapshot.resolution_m:.2f} m",
        np.array([MARGIN_PX, 52.0]),
        0.5,
    )
    draw_scale_bar(canvas)
    draw_north_arrow(canvas)
    _probability_bar(canvas.image)
    entries = [
        LegendEntry("obstacle outline (scenario)", OBSTACLE, 2),
        LegendEntry("last planned path", PLAN, 2),
        LegendEntry("track (circle: vehicle at the map's time)", INK, 2),
    ]
    _corner_legend(canvas.image, entries if data.obstacles else entries[1:])
    return canvas.image


def drive_line(data: RunData) -> str:
    """The drive in one line: the referee's measures when the run has them."""
    drive = data.summary.get("drive") or {}
    finished = drive.get("finished", data.summary.get("finished"))
    parts = [
        f"{'finished' if finished else 'not finished'}: "
        + (
            f"{100 * drive['completion']:.1f} % of {drive.get('route_length_m', data.frame.length_m):.0f} m"
            if "completion" in drive
            else f"course {data.frame.length_m:.0f} m"
        )
        + f" in {drive.get('time_s', data.duration_s):.0f} s"
    ]
    for key, text in (
        ("mean_speed_mps", "mean {:.1f} m/s"),
        ("collisions", "collisions {}"),
        ("corridor_exits", "corridor exits {}"),
        ("hazard_entries", "ditch/berm entries {}"),
        ("min_clearance_m", "min clearance {:.2f} m"),
    ):
        if drive.get(key) is not None:
            parts.append(text.format(drive[key]))
    return ", ".join(parts)


# -- pieces -------------------------------------------------------------------------------------


def _warp_cells(canvas: Canvas, snapshot: MapSnapshot, cells: np.ndarray, interpolation: int) -> np.ndarray:
    """Map cells (row 0 south) laid onto the canvas's pixels (zero where the map is not)."""
    scale = snapshot.resolution_m * canvas.px_per_m
    west_px, north_px = canvas.pixels(
        snapshot.origin_east_m, snapshot.origin_north_m + cells.shape[0] * snapshot.resolution_m
    )
    # Flipped, row 0 is the northern edge as in an image; a cell's centre is half a cell in.
    matrix = np.array([[scale, 0.0, west_px + 0.5 * scale], [0.0, scale, north_px + 0.5 * scale]])
    height, width = canvas.image.shape[:2]
    flipped = np.ascontiguousarray(cells[::-1])
    return cv2.warpAffine(flipped, matrix, (width, height), flags=interpolation, borderValue=0)


def _mosaic(canvas: Canvas, snapshot: MapSnapshot, hazard: np.ndarray) -> None:
    """Raise ``hazard`` (canvas pixels) to the snapshot's probabilities where it covers them."""
    try:
        _window, probability = decode_snapshot(snapshot)
    except SnapshotError:
        return
    np.maximum(hazard, _warp_cells(canvas, snapshot, probability, cv2.INTER_LINEAR), out=hazard)


def _last_decodable(snapshots: list[tuple[float, MapSnapshot]]) -> tuple[float, MapSnapshot, np.ndarray] | None:
    for t_s, snapshot in reversed(snapshots):
        try:
            return t_s, snapshot, decode_snapshot(snapshot)[1]
        except SnapshotError:
            continue
    return None


def _probability_colours(probability: np.ndarray) -> np.ndarray:
    """Clear (0) white, unknown (0.5) grey, hazard (1) red."""
    p = probability[..., None]
    low = np.array(PAPER) + (np.array(UNKNOWN) - np.array(PAPER)) * (p / 0.5)
    high = np.array(UNKNOWN) + (np.array(HAZARD) - np.array(UNKNOWN)) * ((p - 0.5) / 0.5)
    return np.where(p <= 0.5, low, high).astype(np.uint8)


def _probability_bar(image: np.ndarray) -> None:
    width_px, height_px = 256, 12
    right = image.shape[1] - MARGIN_PX
    top = image.shape[0] - FOOTER_PX // 2 - height_px // 2
    bar = _probability_colours(np.linspace(0.0, 1.0, width_px, dtype=np.float32)[None, :])
    image[top : top + height_px, right - width_px : right] = bar
    cv2.rectangle(image, (right - width_px, top), (right, top + height_px), INK, 1)
    draw_text(image, "hazard probability", np.array([right - width_px, top - 8.0]), 0.5)
    for value, x in (("0 clear", right - width_px), ("0.5 unknown", right - width_px / 2 - 40), ("1", right - 8)):
        draw_text(image, value, np.array([x, top + height_px + 18.0]), 0.45)


def _draw_obstacle(canvas: Canvas, obstacle: WorldObstacle, filled: bool) -> None:
    if obstacle.shape is Shape.CYLINDER:
        radius = max(obstacle.radius_m * canvas.px_per_m, 2.5)
        centre = canvas.fixed(canvas.pixels(obstacle.east_m, obstacle.north_m))
        scaled = round(radius * (1 << SHIFT))
        if filled:
            cv2.circle(canvas.image, tuple(int(v) for v in centre), scaled, OBSTACLE, -1, cv2.LINE_AA, SHIFT)
        cv2.circle(canvas.image, tuple(int(v) for v in centre), scaled, OBSTACLE, 2, cv2.LINE_AA, SHIFT)
        return
    c, s = math.cos(obstacle.yaw_rad), math.sin(obstacle.yaw_rad)
    half_l, half_w = obstacle.length_m / 2.0, obstacle.width_m / 2.0
    corners = [
        (dx * c - dy * s, dx * s + dy * c)
        for dx, dy in ((half_l, half_w), (-half_l, half_w), (-half_l, -half_w), (half_l, -half_w))
    ]
    east = [obstacle.east_m + de for de, _dn in corners]
    north = [obstacle.north_m + dn for _de, dn in corners]
    polygon = canvas.fixed(canvas.pixels(east, north))
    if filled:
        cv2.fillConvexPoly(canvas.image, polygon, OBSTACLE, cv2.LINE_AA, SHIFT)
    cv2.polylines(canvas.image, [polygon], True, OBSTACLE, 2, cv2.LINE_AA, SHIFT)


def _polyline(canvas: Canvas, track: Track, color: Color, thickness: int) -> None:
    points = canvas.fixed(canvas.pixels(track.east_m, track.north_m))
    cv2.polylines(canvas.image, [points], False, color, thickness, cv2.LINE_AA, SHIFT)


def _speed_track(canvas: Canvas, track: Track, vmax_mps: float) -> None:
    """The track, each step in the colour of its speed (the RDDF plot's colours)."""
    points = canvas.fixed(canvas.pixels(track.east_m, track.north_m))
    colours = speed_colors(0.5 * (track.speed_mps[:-1] + track.speed_mps[1:]), vmax_mps)
    for k in range(len(points) - 1):
        colour = tuple(int(v) for v in colours[k])
        cv2.line(canvas.image, tuple(points[k]), tuple(points[k + 1]), colour, 3, cv2.LINE_AA, SHIFT)


def _corner_legend(image: np.ndarray, entries: list[LegendEntry]) -> None:
    """The legend in the corner of the map area where it hides the least of the drawing."""
    if not entries:
        return
    box_w, box_h = legend_size(entries)
    left, right = MARGIN_PX // 2, image.shape[1] - MARGIN_PX // 2 - box_w
    top, bottom = HEADER_PX + 4, image.shape[0] - FOOTER_PX - box_h - 4
    corners = [(x, y) for y in (top, bottom) for x in (left, right)]
    drawn = np.any(image != np.array(PAPER, dtype=np.uint8), axis=-1)
    x0, y0 = min(corners, key=lambda c: int(drawn[c[1] : c[1] + box_h, c[0] : c[0] + box_w].sum()))
    draw_legend(image, entries, x0, y0)
