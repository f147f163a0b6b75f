"""`rascal rddf info FILE` and `rascal rddf plot FILE -o OUT.png`: check, summarise and draw an RDDF course;
`rascal rddf generate` and `rascal rddf cut`: write one (brain/course_gen.py). The drawing is
rascal/rddf_plot.py's, whose handler the command line hands in (rddf_plot reads courses with
``load_course_path`` from here)."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

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

MIN_SIZE_PX = 400


def add_rddf_commands(commands: Any, plot_handler: Callable[[argparse.Namespace], int]) -> None:
    """Register ``rddf info``, ``plot`` (run by ``plot_handler``), ``generate`` and ``cut`` on the
    `rascal` command's subparsers."""
    rddf = commands.add_parser("rddf", help="DARPA route definition files: check, summarise, draw, generate, cut")
    tools = rddf.add_subparsers(dest="tool", required=True)
    info = tools.add_parser("info", help="waypoints, length, corridor width, speeds and drive time of a course")
    info.add_argument("file", type=Path, help="RDDF file")
    _add_profile_options(info)
    info.set_defaults(handler=_info)
    plot = tools.add_parser("plot", help="draw the corridor and the path coloured by desired speed to an image")
    plot.add_argument("file", type=Path, help="RDDF file")
    plot.add_argument(
        "-o", "--output", type=Path, required=True, help="image file to write: .png, .svg or .pdf (e.g. course.png)"
    )
    plot.add_argument(
        "--size-px", type=_size_px, default=1600, help="the image fits in a square this many pixels wide (%(default)s)"
    )
    _add_profile_options(plot)
    plot.set_defaults(handler=plot_handler)
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


def load_course_path(args: argparse.Namespace) -> tuple[Course, CoursePath]:
    """The course named by ``args.file`` and its path with the profile options' limits."""
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
        course, path = load_course_path(args)
    except (OSError, ValueError) as exc:  # RddfError is a ValueError
        print(f"rascal rddf info: {exc}", file=sys.stderr)
        return 2
    print(describe_course(course, path, str(args.file)))
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
            f"{duration_text(drive_time_s)}{f' ({drive_time_s:.1f} s)' if drive_time_s >= 60.0 else ''} "
            "at the desired speeds from standstill to stop "
            f"(average {_speed(path.length_m / drive_time_s)})",
        ),
    ]
    label_width = max(len(label) for label, _ in rows)
    return "\n".join(f"{label:<{label_width}}  {value}" for label, value in rows)


def _speed(mps: float) -> str:
    return f"{mps:.2f} m/s ({mps / MPH_TO_MPS:.1f} mph)"


def duration_text(seconds: float) -> str:
    """A duration for people: 42.0 s, 3 min 07.5 s, 1 h 02 min 03.0 s."""
    minutes, rest = divmod(seconds, 60.0)
    hours, minutes = divmod(int(minutes), 60)
    if hours:
        return f"{hours} h {minutes:02d} min {rest:04.1f} s"
    return f"{minutes} min {rest:04.1f} s" if minutes else f"{rest:.1f} s"
