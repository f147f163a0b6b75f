"""Courses for the drive benchmark: seeded random RDDFs, and stretches cut from real ones.

A generated course is what a DARPA route looks like: straight stretches and smooth bends (arcs
drawn as chords at most 10 degrees apart), speed limits of 10-35 mph, and a corridor whose width
changes from stretch to stretch, with narrow stretches (up to 6 m wide in total) where the
limits are low. Its heading stays within 60 degrees of one direction, so the route always makes
ground that way and never comes back across itself. Widths are total corridor widths: the RDDF's
lateral boundary offset is half of one (brain/rddf.py).

A cut keeps whole waypoints of a real file, as they were, numbered again from 1.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import pymap3d

from brain.corridor import FT_TO_M, Course
from brain.rddf import Waypoint

DEFAULT_ORIGIN = (34.8650, -116.8900)  # the Mojave, where the default course starts
NARROW_WIDTH_M = 6.0  # stretches at most this wide (in total) are the narrow ones
NARROW_SHARE = 0.3  # of the stretches, when the widths allow both kinds
STRETCH_M = (100.0, 600.0)  # one width and speed limit over this much, to the next piece's start
STRAIGHT_CHANCE = 0.4  # of a piece being a straight (never two in a row)
STRAIGHT_M = (60.0, 400.0)
BEND_TURN_DEG = (20.0, 110.0)
BEND_RADIUS_M = (15.0, 150.0)
MAX_HEADING_DEG = 60.0  # from the course's general direction
CHORD_TURN_DEG = 10.0  # a bend's waypoints: at most this turn from one chord to the next
NARROW_LIMITS_MPH = (10, 15, 20)
WIDE_LIMITS_MPH = (15, 20, 25, 30, 35)
OFFSET_STEP_FT = 0.01  # offsets are written to this step, rounded towards the inside of the bounds
DEGREE_DIGITS = 8  # about 1 mm


@dataclass(frozen=True)
class CourseSpec:
    seed: int
    length_m: float
    min_width_m: float = 3.7
    max_width_m: float = 18.0
    origin: tuple[float, float] = DEFAULT_ORIGIN  # (lat, lon) of the first waypoint

    def __post_init__(self) -> None:
        if not self.length_m > 0.0:
            raise ValueError(f"length must be positive, got {self.length_m} m")
        if not 0.0 < self.min_width_m <= self.max_width_m:
            raise ValueError(f"widths must satisfy 0 < min <= max, got {self.min_width_m}, {self.max_width_m} m")
        low, high = _offset_bounds_ft(self.min_width_m, self.max_width_m)
        if low > high:
            raise ValueError(f"no {OFFSET_STEP_FT} ft offset step between {self.min_width_m} and {self.max_width_m} m")


@dataclass(frozen=True)
class _Stretch:
    offset_ft: float
    speed_mph: float


def generate_course(spec: CourseSpec) -> list[Waypoint]:
    """The course for ``spec``: the same for the same spec, ``spec.length_m`` long to a millimetre."""
    rng = np.random.default_rng(spec.seed)
    points, stretches = _centreline(rng, spec)
    points, stretches = _trimmed(points, stretches, spec.length_m)
    lat, lon, _ = pymap3d.enu2geodetic(points[:, 0], points[:, 1], 0.0, *spec.origin, 0.0)
    limits = [*stretches, stretches[-1]]  # the last waypoint's limits govern no segment
    return [
        Waypoint(
            number,
            round(float(la), DEGREE_DIGITS),
            round(float(lo), DEGREE_DIGITS),
            stretch.offset_ft,
            stretch.speed_mph,
        )
        for number, (la, lo, stretch) in enumerate(zip(lat, lon, limits, strict=True), start=1)
    ]


def _centreline(rng: np.random.Generator, spec: CourseSpec) -> tuple[np.ndarray, list[_Stretch]]:
    """Waypoints in metres east and north of the first, past ``spec.length_m``, and each segment's
    stretch."""
    direction = rng.uniform(-math.pi, math.pi)
    heading = 0.0  # from ``direction``
    points = [np.zeros(2)]
    segments: list[_Stretch] = []
    length, straight_before, narrow_seen = 0.0, False, False
    stretch, stretch_ends_m = _Stretch(0.0, 0.0), 0.0
    while length < spec.length_m:
        # A course that has had no narrow stretch by a third of its length gets one now.
        must = not narrow_seen and length >= spec.length_m / 3
        if length >= stretch_ends_m or must:
            stretch = _draw_stretch(rng, spec, must)
            stretch_ends_m = length + rng.uniform(*STRETCH_M)
            narrow_seen |= 2 * stretch.offset_ft * FT_TO_M <= NARROW_WIDTH_M
        straight = not straight_before and rng.random() < STRAIGHT_CHANCE
        if straight:
            steps = [(0.0, rng.uniform(*STRAIGHT_M))]
        else:
            turn = _draw_turn(rng, heading)
            radius = rng.uniform(*BEND_RADIUS_M)
            chords = math.ceil(abs(turn) / math.radians(CHORD_TURN_DEG))
            chord = 2.0 * radius * math.sin(abs(turn) / chords / 2.0)
            # Each chord points half its turn on: the waypoints lie on the arc.
            steps = [(turn / chords, chord)] * chords
        for turn_step, step_m in steps:
            yaw = direction + heading + turn_step / 2.0
            points.append(points[-1] + step_m * np.array([math.cos(yaw), math.sin(yaw)]))
            heading += turn_step
            segments.append(stretch)
            length += step_m
        straight_before = straight
    return np.array(points), segments


def _draw_stretch(rng: np.random.Generator, spec: CourseSpec, must_be_narrow: bool) -> _Stretch:
    low, high = _offset_bounds_ft(spec.min_width_m, spec.max_width_m)
    narrow_top = _offset_bounds_ft(NARROW_WIDTH_M, NARROW_WIDTH_M)[1]
    if high <= narrow_top:  # every width allowed is narrow
        narrow = True
    elif low > narrow_top:  # none is
        narrow = False
    else:
        narrow = must_be_narrow or rng.random() < NARROW_SHARE
    bounds = (low, min(high, narrow_top)) if narrow else (max(low, round(narrow_top + OFFSET_STEP_FT, 2)), high)
    offset = round(round(rng.uniform(*bounds) / OFFSET_STEP_FT) * OFFSET_STEP_FT, 2)
    limits = NARROW_LIMITS_MPH if narrow else WIDE_LIMITS_MPH
    return _Stretch(min(max(offset, bounds[0]), bounds[1]), float(rng.choice(limits)))


def _offset_bounds_ft(min_width_m: float, max_width_m: float) -> tuple[float, float]:
    """The lowest and highest offsets on the step whose total widths lie within the bounds."""
    low = math.ceil(round(min_width_m / 2 / FT_TO_M / OFFSET_STEP_FT, 6)) * OFFSET_STEP_FT
    high = math.floor(round(max_width_m / 2 / FT_TO_M / OFFSET_STEP_FT, 6)) * OFFSET_STEP_FT
    return round(low, 2), round(high, 2)


def _draw_turn(rng: np.random.Generator, heading: float) -> float:
    """A bend's turn (radians, left positive) that keeps the heading within MAX_HEADING_DEG."""
    limit = math.radians(MAX_HEADING_DEG)
    low, high = (math.radians(d) for d in BEND_TURN_DEG)
    sign = 1.0 if rng.random() < 0.5 else -1.0
    if sign * heading + low > limit:  # no room that way: turn back
        sign = -sign
    return sign * min(rng.uniform(low, high), limit - sign * heading)


def _trimmed(points: np.ndarray, segments: list[_Stretch], length_m: float) -> tuple[np.ndarray, list[_Stretch]]:
    """The polyline cut at ``length_m`` of arc length (its last point moved back along its segment)."""
    steps = np.hypot(*np.diff(points, axis=0).T)
    ends = np.cumsum(steps)
    last = min(int(np.searchsorted(ends, length_m)), len(steps) - 1)  # the segment holding the end
    fraction = (length_m - (ends[last] - steps[last])) / steps[last]
    end = points[last] + fraction * (points[last + 1] - points[last])
    return np.vstack([points[: last + 1], end]), segments[: last + 1]


def cut_course(waypoints: Sequence[Waypoint], from_m: float, length_m: float) -> list[Waypoint]:
    """Whole waypoints of a course, numbered from 1: from the waypoint nearest ``from_m`` along
    it to the one nearest ``length_m`` on from there (at least one segment)."""
    course = Course(waypoints)
    s = np.concatenate([[0.0], np.cumsum(course.segment_length_m)])
    if not 0.0 <= from_m < s[-1]:
        raise ValueError(f"--from-m {from_m:g} is not within the course's {s[-1]:.1f} m")
    if not length_m > 0.0:
        raise ValueError(f"--length-m must be positive, got {length_m:g}")
    first = int(np.argmin(np.abs(s[:-1] - from_m)))
    end = min(s[first] + length_m, s[-1])  # past the end: to the end
    last = first + 1 + int(np.argmin(np.abs(s[first + 1 :] - end)))
    return [replace(w, number=n) for n, w in enumerate(waypoints[first : last + 1], start=1)]


def rddf_text(waypoints: Sequence[Waypoint], comments: Sequence[str] = ()) -> str:
    """An RDDF file's text: ``comments`` as ``#`` lines, then the waypoints, with the phase-line
    fields when any waypoint has a phase line."""
    phases = any(w.phase_line is not None for w in waypoints)
    lines = [f"# {comment}" for comment in comments]
    for w in waypoints:
        fields = [str(w.number), *map(_number, (w.lat_deg, w.lon_deg, w.lateral_offset_ft, w.speed_limit_mph))]
        if phases:
            fields += [str(v) for v in w.phase_line] if w.phase_line else ["####"] * 3
        lines.append(",".join(fields))
    return "\n".join(lines) + "\n"


def _number(value: float) -> str:
    """Shortest text that reads back as the same float."""
    return str(int(value)) if value.is_integer() else repr(value)


def corridor_widths_m(waypoints: Sequence[Waypoint]) -> np.ndarray:
    """Each segment's total corridor width."""
    return np.array([2.0 * w.lateral_offset_ft * FT_TO_M for w in waypoints[:-1]])


def narrow_length_m(waypoints: Sequence[Waypoint]) -> float:
    """How much of the course is narrow (at most NARROW_WIDTH_M wide)."""
    course = Course(waypoints)
    return float(course.segment_length_m[corridor_widths_m(waypoints) <= NARROW_WIDTH_M + 1e-9].sum())
