"""`rascal rddf info FILE` and `rascal rddf plot FILE -o OUT.png`: check, summarise and draw an RDDF course;
`rascal rddf generate` and `rascal rddf cut`: write one (brain/course_gen.py)."""

from __future__ import annotations

import argparse
import itertools
import math
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from brain.corridor import (
    DEFAULT_MAX_ACCEL_MPS2,
    DEFAULT_MAX_DECEL_MPS2,
    DEFAULT_MAX_LATERAL_ACCEL_MPS2,
    DEFAULT_SPACING_M,
    MPH_TO_MPS,
    Course,
    CoursePath,
)
from brain.course_gen import (
    NARROW_WIDTH_M,
    CourseSpec,
    corridor_widths_m,
    cut_course,
    generate_course,
    narrow_length_m,
    rddf_text,
)
from brain.rddf import Waypoint, load_rddf

Color = tuple[int, int, int]  # OpenCV's blue, green, red
CORRIDOR_FILL: Color = (236, 226, 214)
CORRIDOR_EDGE: Color = (170, 150, 130)
INK: Color = (40, 40, 40)
PAPER: Color = (255, 255, 255)
START_COLOR: Color = (60, 170, 40)
FINISH_COLOR: Color = (40, 40, 210)
FONT = cv2.FONT_HERSHEY_SIMPLEX
SHIFT = 4  # fractional bits of the pixel coordinates handed to OpenCV, for smooth antialiased shapes
MARGIN_PX = 40
HEADER_PX = 60
FOOTER_PX = 80
MIN_WIDTH_PX = 800  # room for the legend under narrow courses
MIN_SIZE_PX = 400
MAX_LABELS = 60
ARROWS = 16  # direction arrows along the centreline


def add_rddf_commands(commands: Any) -> None:
    """Register ``rddf info``, ``plot``, ``generate`` and ``cut`` on the `rascal` command's subparsers."""
    rddf = commands.add_parser("rddf", help="DARPA route definition files: check, summarise, draw, generate, cut")
    tools = rddf.add_subparsers(dest="tool", required=True)
    info = tools.add_parser("info", help="waypoints, length, corridor width, speeds and drive time of a course")
    info.add_argument("file", type=Path, help="RDDF file")
    _add_profile_options(info)
    info.set_defaults(handler=_info)
    plot = tools.add_parser("plot", help="draw the corridor and the path coloured by desired speed to an image")
    plot.add_argument("file", type=Path, help="RDDF file")
    plot.add_argument("-o", "--output", type=Path, required=True, help="image file to write (e.g. course.png)")
    plot.add_argument(
        "--size-px", type=_size_px, default=1600, help="the image fits in a square this many pixels wide (%(default)s)"
    )
    _add_profile_options(plot)
    plot.set_defaults(handler=_plot)
    generate = tools.add_parser(
        "generate", help="a seeded random course: straights, smooth bends, 10-35 mph, varying and narrow widths"
    )
    generate.add_argument("--seed", type=int, required=True, help="random seed: the same seed gives the same file")
    generate.add_argument("--length-km", type=_positive, required=True, help="length of the course in km")
    generate.add_argument(
        "--min-width-m", type=_positive, default=3.7, help="narrowest total corridor width (%(default)s)"
    )
    generate.add_argument("--max-width-m", type=_positive, default=18.0, help="widest (%(default)s)")
    generate.add_argument("-o", "--output", type=Path, required=True, help="RDDF file to write")
    generate.set_defaults(handler=_generate)
    cut = tools.add_parser("cut", help="a stretch of a course: whole waypoints, numbered from 1")
    cut.add_argument("file", type=Path, help="RDDF file")
    cut.add_argument("--from-m", type=float, default=0.0, help="start at the waypoint nearest this far along (0)")
    cut.add_argument("--length-m", type=_positive, required=True, help="end at the waypoint nearest this far on")
    cut.add_argument("-o", "--output", type=Path, required=True, help="RDDF file to write")
    cut.set_defaults(handler=_cut)


def _size_px(text: str) -> int:
    size = int(text)
    if size < MIN_SIZE_PX:
        raise argparse.ArgumentTypeError(f"{size} is below {MIN_SIZE_PX}")
    return size


def _positive(text: str) -> float:
    value = float(text)
    if not 0.0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"{text} is not a positive number")
    return value


def _add_profile_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--spacing-m", type=float, default=DEFAULT_SPACING_M, help="path point spacing (%(default)s)")
    parser.add_argument(
        "--max-lateral-accel-mps2",
        type=float,
        default=DEFAULT_MAX_LATERAL_ACCEL_MPS2,
        help="lateral acceleration allowed in turns (%(default)s)",
    )
    parser.add_argument(
        "--max-decel-mps2", type=float, default=DEFAULT_MAX_DECEL_MPS2, help="braking allowed (%(default)s)"
    )
    parser.add_argument(
        "--max-accel-mps2", type=float, default=DEFAULT_MAX_ACCEL_MPS2, help="acceleration allowed (%(default)s)"
    )


def _load(args: argparse.Namespace) -> tuple[Course, CoursePath]:
    course = Course.from_file(args.file)
    path = course.interpolate(
        spacing_m=args.spacing_m,
        max_lateral_accel_mps2=args.max_lateral_accel_mps2,
        max_decel_mps2=args.max_decel_mps2,
        max_accel_mps2=args.max_accel_mps2,
    )
    return course, path


def _info(args: argparse.Namespace) -> int:
    try:
        course, path = _load(args)
    except (OSError, ValueError) as exc:  # RddfError is a ValueError
        print(f"rascal rddf info: {exc}", file=sys.stderr)
        return 2
    print(describe_course(course, path, str(args.file)))
    return 0


def _plot(args: argparse.Namespace) -> int:
    try:
        course, path = _load(args)
    except (OSError, ValueError) as exc:
        print(f"rascal rddf plot: {exc}", file=sys.stderr)
        return 2
    image = render_course(course, path, args.file.name, args.size_px)
    try:
        written = cv2.imwrite(str(args.output), image)
    except cv2.error as exc:
        written, reason = False, str(exc).strip()
    else:
        reason = "OpenCV could not write it (unknown extension or unwritable place)"
    if not written:
        print(f"rascal rddf plot: {args.output}: {reason}", file=sys.stderr)
        return 2
    print(f"wrote {args.output} ({image.shape[1]} x {image.shape[0]} px)")
    return 0


def _generate(args: argparse.Namespace) -> int:
    try:
        spec = CourseSpec(args.seed, args.length_km * 1000.0, args.min_width_m, args.max_width_m)
    except ValueError as exc:
        print(f"rascal rddf generate: {exc}", file=sys.stderr)
        return 2
    command = (
        f"rascal rddf generate --seed {args.seed} --length-km {args.length_km:g} "
        f"--min-width-m {args.min_width_m:g} --max-width-m {args.max_width_m:g}"
    )
    return _write("generate", generate_course(spec), args.output, [f"Generated by `{command}`."])


def _cut(args: argparse.Namespace) -> int:
    try:
        waypoints = cut_course(load_rddf(args.file), args.from_m, args.length_m)
    except (OSError, ValueError) as exc:  # RddfError is a ValueError
        print(f"rascal rddf cut: {exc}", file=sys.stderr)
        return 2
    command = f"rascal rddf cut {args.file.name} --from-m {args.from_m:g} --length-m {args.length_m:g}"
    return _write("cut", waypoints, args.output, [f"Cut by `{command}`: its waypoints, numbered from 1."])


def _write(tool: str, waypoints: list[Waypoint], output: Path, comments: list[str]) -> int:
    header = "number, latitude, longitude, lateral boundary offset (ft, half the corridor), speed limit (mph)"
    try:
        output.write_text(rddf_text(waypoints, [*comments, header]), encoding="utf-8")
    except OSError as exc:
        print(f"rascal rddf {tool}: {exc}", file=sys.stderr)
        return 2
    widths = corridor_widths_m(waypoints)
    limits = [w.speed_limit_mph for w in waypoints[:-1]]
    print(
        f"wrote {output}: {len(waypoints)} waypoints, {Course(waypoints).length_m:.1f} m, "
        f"corridor {widths.min():.2f}-{widths.max():.2f} m wide "
        f"({narrow_length_m(waypoints):.0f} m at most {NARROW_WIDTH_M:g} m), "
        f"speed limits {min(limits):g}-{max(limits):g} mph"
    )
    return 0


def describe_course(course: Course, path: CoursePath, name: str) -> str:
    """The plain-text summary printed by ``rascal rddf info``."""
    waypoints = course.waypoints
    phase_lines = sum(w.phase_line is not None for w in waypoints)
    width = 2.0 * course.half_width_m
    limits = course.speed_limit_mps
    mean_limit = float(np.average(limits, weights=course.segment_length_m))
    drive_time_s = path.drive_time_s()
    rows = [
        ("file", name),
        (
            "waypoints",
            f"{len(waypoints)} (numbers {waypoints[0].number}-{waypoints[-1].number}), "
            f"{len(waypoints) - 1} segments, {phase_lines} with a phase line",
        ),
        ("origin", f"{course.origin.lat_deg:.7f}, {course.origin.lon_deg:.7f} (WGS84; local frame east/north in m)"),
        ("length", f"{course.length_m:.1f} m ({course.length_m / 1000.0:.3f} km)"),
        (
            "corridor width",
            f"min {width.min():.2f} m, median {np.median(width):.2f} m, max {width.max():.2f} m "
            "(twice each segment's lateral offset)",
        ),
        (
            "speed limit",
            f"min {_speed(limits.min())}, mean {_speed(mean_limit)}, max {_speed(limits.max())} "
            "(per segment; mean over distance)",
        ),
        ("path", f"{len(path.s_m)} points every {path.spacing_m:.3f} m"),
        ("desired speed", f"mean {_speed(path.speed_mps.mean())}, max {_speed(path.speed_mps.max())} (over distance)"),
        (
            "min drive time",
            f"{_duration(drive_time_s)}{f' ({drive_time_s:.1f} s)' if drive_time_s >= 60.0 else ''} "
            "at the desired speeds from standstill to stop "
            f"(average {_speed(path.length_m / drive_time_s)})",
        ),
    ]
    label_width = max(len(label) for label, _ in rows)
    return "\n".join(f"{label:<{label_width}}  {value}" for label, value in rows)


def _speed(mps: float) -> str:
    return f"{mps:.2f} m/s ({mps / MPH_TO_MPS:.1f} mph)"


def _duration(seconds: float) -> str:
    minutes, rest = divmod(seconds, 60.0)
    hours, minutes = divmod(int(minutes), 60)
    if hours:
        return f"{hours} h {minutes:02d} min {rest:04.1f} s"
    return f"{minutes} min {rest:04.1f} s" if minutes else f"{rest:.1f} s"


class Canvas:
    """An image with the course's metres mapped to pixels, north up, fitted inside a square."""

    def __init__(self, bounds_m: tuple[float, float, float, float], size_px: int) -> None:
        min_e, min_n, max_e, max_n = bounds_m
        fit_w = size_px - 2 * MARGIN_PX
        fit_h = size_px - 2 * MARGIN_PX - HEADER_PX - FOOTER_PX
        self.px_per_m = min(fit_w / max(max_e - min_e, 1e-6), fit_h / max(max_n - min_n, 1e-6))
        map_w = (max_e - min_e) * self.px_per_m
        width = max(round(map_w) + 2 * MARGIN_PX, min(MIN_WIDTH_PX, size_px))
        height = round((max_n - min_n) * self.px_per_m) + 2 * MARGIN_PX + HEADER_PX + FOOTER_PX
        self.image = np.full((height, width, 3), PAPER, dtype=np.uint8)
        self._left = (width - map_w) / 2.0 - min_e * self.px_per_m
        self._top = HEADER_PX + MARGIN_PX + max_n * self.px_per_m

    def pixels(self, east_m: Any, north_m: Any) -> np.ndarray:
        """Pixel positions (x right, y down) of local positions, as floats."""
        x = self._left + np.asarray(east_m) * self.px_per_m
        y = self._top - np.asarray(north_m) * self.px_per_m
        return np.stack([x, y], axis=-1)

    @staticmethod
    def fixed(points: np.ndarray) -> np.ndarray:
        """Float pixels as OpenCV's fixed-point integers (see `SHIFT`)."""
        return np.round(np.asarray(points) * (1 << SHIFT)).astype(np.int32)


def render_course(course: Course, path: CoursePath, title: str, size_px: int = 1600) -> np.ndarray:
    """A BGR image of the corridor, the path coloured by desired speed, waypoints, legend and scale."""
    canvas = Canvas(course.corridor.bounds_m(), size_px)
    vmax_mps = float(course.speed_limit_mps.max())
    draw_corridor(canvas, course)
    _draw_path(canvas, path, vmax_mps)
    _draw_waypoints(canvas, course)
    draw_start_finish(canvas, course)
    _draw_header(canvas, course, path, title)
    draw_scale_bar(canvas)
    draw_speed_legend(canvas, vmax_mps)
    draw_north_arrow(canvas)
    return canvas.image


def draw_corridor(canvas: Canvas, course: Course) -> None:
    corridor = course.corridor
    mask = np.zeros(canvas.image.shape[:2], dtype=np.uint8)
    starts = canvas.pixels(corridor.start_m[:, 0], corridor.start_m[:, 1])
    ends = canvas.pixels(corridor.end_m[:, 0], corridor.end_m[:, 1])
    for start, end, half_width_m in zip(starts, ends, corridor.half_width_m, strict=True):
        radius = half_width_m * canvas.px_per_m
        along = end - start
        length = float(np.hypot(*along))
        if length > 0.0:
            normal = np.array([-along[1], along[0]]) / length * radius
            band = np.array([start + normal, end + normal, end - normal, start - normal])
            cv2.fillConvexPoly(mask, canvas.fixed(band), 255, cv2.LINE_AA, SHIFT)
        for centre in (start, end):
            x, y = (int(v) for v in canvas.fixed(centre))
            cv2.circle(mask, (x, y), round(radius * (1 << SHIFT)), 255, -1, cv2.LINE_AA, SHIFT)
    alpha = (mask.astype(np.float32) / 255.0)[..., None]
    canvas.image[:] = (canvas.image * (1.0 - alpha) + np.array(CORRIDOR_FILL) * alpha).astype(np.uint8)
    contours, _ = cv2.findContours((mask >= 128).astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(canvas.image, contours, -1, CORRIDOR_EDGE, 1, cv2.LINE_AA)


def speed_colors(speed_mps: np.ndarray, vmax_mps: float) -> np.ndarray:
    """Turbo colours (BGR): dark blue at standstill, dark red at the course's highest limit."""
    levels = np.clip(np.round(speed_mps / vmax_mps * 255.0), 0, 255).astype(np.uint8)
    return cv2.applyColorMap(levels.reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3)


def _draw_path(canvas: Canvas, path: CoursePath, vmax_mps: float) -> None:
    points = canvas.fixed(canvas.pixels(path.east_m, path.north_m))
    step_speed = 0.5 * (path.speed_mps[:-1] + path.speed_mps[1:])
    levels = np.round(np.clip(step_speed / vmax_mps, 0.0, 1.0) * 63).astype(int)
    colors = speed_colors(levels / 63.0 * vmax_mps, vmax_mps)
    # One polyline per run of steps with the same colour level keeps the draw calls few.
    breaks = np.concatenate([[0], np.flatnonzero(np.diff(levels)) + 1, [len(levels)]])
    for first, stop in itertools.pairwise(breaks):
        color = tuple(int(c) for c in colors[first])
        cv2.polylines(canvas.image, [points[first : stop + 1]], False, color, 3, cv2.LINE_AA, SHIFT)
    _draw_direction_arrows(canvas, path)


def _draw_direction_arrows(canvas: Canvas, path: CoursePath) -> None:
    pixels = canvas.pixels(path.east_m, path.north_m)
    count = len(path.s_m)
    for k in np.linspace(0, count - 1, ARROWS + 2).round().astype(int)[1:-1]:
        heading = pixels[min(k + 1, count - 1)] - pixels[max(k - 1, 0)]
        norm = float(np.hypot(*heading))
        if norm == 0.0:
            continue
        tip = pixels[k] + heading / norm * 9.0
        tail = pixels[k] - heading / norm * 9.0
        cv2.arrowedLine(canvas.image, to_point(tail), to_point(tip), INK, 1, cv2.LINE_AA, 0, 0.6)


def _draw_waypoints(canvas: Canvas, course: Course) -> None:
    pixels = canvas.pixels(course.east_m, course.north_m)
    every = max(1, math.ceil(len(pixels) / MAX_LABELS))
    labels: list[tuple[np.ndarray, list[str]]] = []
    # Long courses show every n-th waypoint only, so the markers do not bury the path.
    for pixel, waypoint in zip(pixels[::every], course.waypoints[::every], strict=True):
        cv2.circle(canvas.image, to_point(pixel), 4, PAPER, -1, cv2.LINE_AA)
        cv2.circle(canvas.image, to_point(pixel), 4, INK, 1, cv2.LINE_AA)
        _add_label(labels, pixel, str(waypoint.number))
    for pixel, numbers in labels:
        draw_text(canvas.image, ",".join(numbers), pixel + np.array([7.0, -7.0]), 0.45)


def _add_label(labels: list[tuple[np.ndarray, list[str]]], pixel: np.ndarray, number: str) -> None:
    """Waypoints drawn on top of each other (out-and-back courses) share one label."""
    for place, numbers in labels:
        if np.hypot(*(place - pixel)) < 8.0:
            numbers.append(number)
            return
    labels.append((pixel, [number]))


def draw_start_finish(canvas: Canvas, course: Course) -> None:
    start, finish = canvas.pixels(course.east_m[[0, -1]], course.north_m[[0, -1]])
    corner = np.array([8.0, 8.0])
    cv2.rectangle(canvas.image, to_point(finish - corner), to_point(finish + corner), FINISH_COLOR, -1, cv2.LINE_AA)
    cv2.circle(canvas.image, to_point(start), 8, START_COLOR, -1, cv2.LINE_AA)
    draw_text(canvas.image, "START", start + np.array([-70.0, -14.0]), 0.6, START_COLOR)
    draw_text(canvas.image, "FINISH", finish + np.array([14.0, 26.0]), 0.6, FINISH_COLOR)


def _draw_header(canvas: Canvas, course: Course, path: CoursePath, title: str) -> None:
    summary = (
        f"{len(course.waypoints)} waypoints, {_distance(course.length_m)}, "
        f"corridor {_range(2.0 * course.half_width_m)} m wide, "
        f"drive time {_duration(path.drive_time_s())}"
    )
    draw_text(canvas.image, title, np.array([MARGIN_PX, 28.0]), 0.7)
    draw_text(canvas.image, summary, np.array([MARGIN_PX, 52.0]), 0.5)


def _distance(metres: float) -> str:
    return f"{metres:.0f} m" if metres < 10_000.0 else f"{metres / 1000.0:.1f} km"


def _range(values: np.ndarray) -> str:
    low, high = f"{values.min():.1f}", f"{values.max():.1f}"
    return low if low == high else f"{low}-{high}"


def draw_scale_bar(canvas: Canvas) -> None:
    length_m = nice_length(canvas.image.shape[1] / 5.0 / canvas.px_per_m)
    length_px = length_m * canvas.px_per_m
    y = canvas.image.shape[0] - FOOTER_PX / 2.0
    left = np.array([MARGIN_PX, y])
    right = left + np.array([length_px, 0.0])
    cv2.line(canvas.image, to_point(left), to_point(right), INK, 3)
    for end in (left, right):
        tick = np.array([0.0, 6.0])
        cv2.line(canvas.image, to_point(end - tick), to_point(end + tick), INK, 2)
    draw_text(canvas.image, f"{length_m:g} m", left + np.array([0.0, -12.0]), 0.5)


def nice_length(target_m: float) -> float:
    """The largest 1, 2 or 5 times a power of ten not above ``target_m``."""
    power = 10.0 ** math.floor(math.log10(target_m))
    return max(step * power for step in (1.0, 2.0, 5.0) if step * power <= target_m)


def draw_speed_legend(canvas: Canvas, vmax_mps: float, title: str = "desired speed") -> None:
    """The speed colour bar in the footer's right corner."""
    width_px, height_px = 256, 12
    right = canvas.image.shape[1] - MARGIN_PX
    top = canvas.image.shape[0] - FOOTER_PX // 2 - height_px // 2
    colors = speed_colors(np.linspace(0.0, vmax_mps, width_px), vmax_mps)
    canvas.image[top : top + height_px, right - width_px : right] = colors[None, :, :]
    cv2.rectangle(canvas.image, (right - width_px, top), (right, top + height_px), INK, 1)
    draw_text(canvas.image, title, np.array([right - width_px, top - 8.0]), 0.5)
    draw_text(canvas.image, "0", np.array([right - width_px, top + height_px + 18.0]), 0.45)
    top_label = f"{vmax_mps:.1f} m/s ({vmax_mps / MPH_TO_MPS:.0f} mph)"
    label_w = cv2.getTextSize(top_label, FONT, 0.45, 1)[0][0]
    draw_text(canvas.image, top_label, np.array([right - label_w, top + height_px + 18.0]), 0.45)


def draw_north_arrow(canvas: Canvas) -> None:
    """In the header's right corner, clear of the map."""
    x = canvas.image.shape[1] - MARGIN_PX / 2.0
    cv2.arrowedLine(canvas.image, to_point([x, HEADER_PX - 8.0]), to_point([x, 12.0]), INK, 2, cv2.LINE_AA, 0, 0.3)
    draw_text(canvas.image, "N", np.array([x - 24.0, 30.0]), 0.55)


def draw_text(image: np.ndarray, text: str, origin: np.ndarray, scale: float, color: Color = INK) -> None:
    """Text with a white halo, readable over the corridor and the path, kept inside the image."""
    (width, height), _ = cv2.getTextSize(text, FONT, scale, 1)
    x = min(max(float(origin[0]), 3.0), image.shape[1] - width - 3.0)
    y = min(max(float(origin[1]), height + 3.0), image.shape[0] - 3.0)
    cv2.putText(image, text, to_point([x, y]), FONT, scale, PAPER, 4, cv2.LINE_AA)
    cv2.putText(image, text, to_point([x, y]), FONT, scale, color, 1, cv2.LINE_AA)


def to_point(pixel: Any) -> tuple[int, int]:
    x, y = np.round(np.asarray(pixel, dtype=float)).astype(int)
    return int(x), int(y)
