"""The fairness rule: whatever a scenario puts on the course leaves a lane to drive through.

Every obstacle and terrain hazard must leave a free lane at least the vehicle's width + 1.0 m
wide inside the corridor, from the start to the finish (issue 23). The rule is checked on
cross-sections of the corridor: stations every 0.25 m of arc length along the RDDF centreline,
each a line along the left normal across its own segment's band (-half width .. +half width),
plus a fan of them at every corner, so the outside of a bend is looked at too. A station stands
for the strip of ground within half a step of its line, so nothing thin slips between two
stations: what the obstacles' footprints and the hazards' extents (not expanded) cover of the
strip is blocked across the line. What is left must hold a free interval of the lane's width
that overlaps the lane at the station before by the lane's width, so the lane is one strip a
vehicle can follow, not a gap here and another on the far side of the road 0.25 m on. Where the
course itself is narrower than the lane, the lane needed is the whole corridor.

The scenario loader applies the rule to every scenario and the scenario generator to what it
places, so both agree on what fair means.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from brain.corridor import MIN_SEGMENT_M, Course
from modules.sim.vehicle import VehicleParams
from modules.sim.world import Shape, World

LANE_MARGIN_M = 1.0  # free room beside the vehicle that a fair lane must have, in total
LANE_WIDTH_M = VehicleParams().width_m + LANE_MARGIN_M
STATION_STEP_M = 0.25
_EPS_M = 1e-9  # rounding slack when comparing widths

FloatArray = NDArray[np.float64]
Interval = tuple[float, float]


@dataclass(frozen=True)
class Stations:
    """Cross-sections of the corridor: a centre point, its left normal and its half width,
    ordered along the course (a corner's fan shares the corner's arc length)."""

    s_m: FloatArray
    east_m: FloatArray
    north_m: FloatArray
    normal_east: FloatArray
    normal_north: FloatArray
    half_width_m: FloatArray
    strip_m: float  # each station stands for the course within this much of it, along the course

    @classmethod
    def along(cls, course: Course, step_m: float = STATION_STEP_M) -> Stations:
        """Stations at most ``step_m`` apart on each segment, and on the outer arc of each corner."""
        segments = np.flatnonzero(course.segment_length_m >= MIN_SEGMENT_M)
        start = np.column_stack([course.east_m[segments], course.north_m[segments]])
        end = np.column_stack([course.east_m[segments + 1], course.north_m[segments + 1]])
        length = course.segment_length_m[segments]
        knots = np.concatenate([[0.0], np.cumsum(length)])
        heading = np.arctan2(end[:, 1] - start[:, 1], end[:, 0] - start[:, 0])
        half = course.half_width_m[segments]
        rows = [
            _segment_stations(start, end, length, knots[:-1], heading, half, step_m),
            _corner_fans(end[:-1], knots[1:-1], heading, half, step_m),
            _stations_at(end[-1:], knots[-1:], heading[-1:], half[-1:], np.array([2.0 * len(segments)])),
        ]
        order_key, s, east, north, yaw, width = (np.concatenate(column) for column in zip(*rows, strict=True))
        order = np.argsort(order_key, kind="stable")
        normal = -np.sin(yaw[order]), np.cos(yaw[order])
        return cls(s[order], east[order], north[order], *normal, width[order], step_m / 2)

    def __len__(self) -> int:
        return len(self.s_m)


# Rows of stations: (order key, s, east, north, heading, half width); the key interleaves each
# segment's stations (2 i), its end corner's fan (2 i + 1) and the finish (2 n).
_Rows = tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]


def _stations_at(point: FloatArray, s: FloatArray, heading: FloatArray, half: FloatArray, key: FloatArray) -> _Rows:
    return key, s, point[:, 0], point[:, 1], heading, half


def _segment_stations(
    start: FloatArray,
    end: FloatArray,
    length: FloatArray,
    s0: FloatArray,
    heading: FloatArray,
    half: FloatArray,
    step_m: float,
) -> _Rows:
    counts = np.ceil(length / step_m).astype(int)
    segment = np.repeat(np.arange(len(counts)), counts)
    j = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    fraction = j / counts[segment]
    point = start[segment] + fraction[:, None] * (end[segment] - start[segment])
    s = s0[segment] + fraction * length[segment]
    return _stations_at(point, s, heading[segment], half[segment], 2.0 * segment)


def _corner_fans(corner: FloatArray, s: FloatArray, heading: FloatArray, half: FloatArray, step_m: float) -> _Rows:
    """At each corner, normals turning from the segment before's to the one after's (that one
    excluded: it is the next segment's first station), at most ``step_m`` apart on the outer arc."""
    turn = np.angle(np.exp(1j * np.diff(heading)))
    # The corner's disc of the wider band's radius lies inside both bands' union.
    radius = np.maximum(half[:-1], half[1:])
    counts = np.where(np.abs(turn) > 1e-6, np.ceil(np.abs(turn) * radius / step_m), 0).astype(int)
    fan = np.repeat(np.arange(len(counts)), counts)
    i = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    yaw = heading[:-1][fan] + turn[fan] * i / np.maximum(counts[fan], 1)
    return _stations_at(corner[fan], s[fan], yaw, radius[fan], 2.0 * fan + 1.0)


@dataclass(frozen=True)
class Blocker:
    """Ground no lane may cross: a circle of ``radius_m`` (> 0), or else a rectangle."""

    name: str
    is_hazard: bool
    east_m: float
    north_m: float
    radius_m: float = 0.0
    yaw_rad: float = 0.0
    half_length_m: float = 0.0
    half_width_m: float = 0.0

    @property
    def reach_m(self) -> float:
        """Radius of a circle around the centre that holds the whole outline."""
        return self.radius_m or math.hypot(self.half_length_m, self.half_width_m)


def blockers(world: World) -> list[Blocker]:
    """The world's obstacle footprints and hazard extents."""
    found = []
    for o in world.obstacles:
        if o.shape is Shape.CYLINDER:
            found.append(Blocker(o.name, False, o.east_m, o.north_m, radius_m=o.radius_m))
        else:
            found.append(Blocker(o.name, False, o.east_m, o.north_m, 0.0, o.yaw_rad, o.length_m / 2, o.width_m / 2))
    for h in world.hazards:
        found.append(Blocker(h.name, True, h.east_m, h.north_m, 0.0, h.yaw_rad, h.length_m / 2, h.width_m / 2))
    return found


@dataclass(frozen=True)
class Unfairness:
    """Where the lane ends: the station's arc length, the widest lane left there, and what blocks."""

    at_m: float
    widest_m: float
    need_m: float
    obstacles: tuple[str, ...]
    hazards: tuple[str, ...]

    def __str__(self) -> str:
        names = [
            f"{label}{'s' if len(group) > 1 else ''} {', '.join(repr(n) for n in group)}"
            for label, group in (("obstacle", self.obstacles), ("hazard", self.hazards))
            if group
        ]
        return (
            f"at {self.at_m:,.1f} m along the course the widest free lane is {self.widest_m:.2f} m, "
            f"needs {self.need_m:.2f} m: {' / '.join(names)}"
        )


def find_unfairness(stations: Stations, blocking: Sequence[Blocker], lane_m: float = LANE_WIDTH_M) -> Unfairness | None:
    """The first station where no lane of ``lane_m`` (or the whole corridor, where that is
    narrower) continues from the start, or None when the course is fair."""
    station, blocker, low, high = _blocked_intervals(stations, blocking)
    need = np.minimum(lane_m, 2.0 * stations.half_width_m)
    lane: list[Interval] = [(-math.inf, math.inf)]  # before the start the lane may be anywhere
    previous, involved = -1, blocker[:0]  # the station ``lane`` is at, and what blocks there
    bounds = np.flatnonzero(np.diff(station)) + 1
    groups = np.split(np.arange(len(station)), bounds) if len(station) else []
    checkpoints = [(int(station[group[0]]), group) for group in groups] + [(len(stations), None)]
    for k, group in checkpoints:
        if k > previous + 1:
            # Stations with nothing on them: the lane widens to the whole corridor.
            clear = previous + 1
            lane, widest = _continue(lane, [_whole(stations, clear)], need[max(previous, 0)], need[clear])
            if not lane:
                return _report(stations, clear, widest, need, blocking, involved)
            previous, lane = k - 1, [_whole(stations, k - 1)]
        if group is None:
            break
        free = _free(low[group], high[group], float(stations.half_width_m[k]))
        lane, widest = _continue(lane, free, need[max(previous, 0)], need[k])
        if not lane:
            # What blocks the station before shaped the lane that could not go on: name it too.
            before = involved if previous == k - 1 else blocker[:0]
            return _report(stations, k, widest, need, blocking, np.concatenate([before, blocker[group]]))
        previous, involved = k, blocker[group]
    return None


def _whole(stations: Stations, k: int) -> Interval:
    half = float(stations.half_width_m[k])
    return -half, half


def _blocked_intervals(
    stations: Stations, blocking: Sequence[Blocker]
) -> tuple[NDArray[np.intp], NDArray[np.intp], FloatArray, FloatArray]:
    """(station, blocker, low, high): how far across the course each blocker reaches within each
    station's strip, as offsets from the centreline clipped to the band; sorted by station."""
    station, blocker = _candidates(stations, blocking)
    shapes = _Shapes(blocking, blocker)
    frame = _Frame(
        shapes.east - stations.east_m[station],
        shapes.north - stations.north_m[station],
        stations.normal_east[station],
        stations.normal_north[station],
    )
    low, high = _rect_strip_spans(shapes, frame, stations.strip_m)
    circle_low, circle_high = _circle_strip_spans(shapes.radius, frame, stations.strip_m)
    circle = shapes.radius > 0.0
    low, high = np.where(circle, circle_low, low), np.where(circle, circle_high, high)
    band = stations.half_width_m[station]
    low, high = np.maximum(low, -band), np.minimum(high, band)
    keep = low <= high
    order = np.lexsort((low[keep], station[keep]))
    return station[keep][order], blocker[keep][order], low[keep][order], high[keep][order]


def _candidates(stations: Stations, blocking: Sequence[Blocker]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """(station, blocker) pairs whose strip may reach the blocker (bounding circles)."""
    order = np.argsort(stations.east_m, kind="stable")
    east = stations.east_m[order]
    widest = float(stations.half_width_m.max())
    pairs_station, pairs_blocker = [], []
    for j, b in enumerate(blocking):
        reach = b.reach_m + stations.strip_m
        first = np.searchsorted(east, b.east_m - reach - widest)
        window = order[first : np.searchsorted(east, b.east_m + reach + widest, "right")]
        near = np.hypot(stations.east_m[window] - b.east_m, stations.north_m[window] - b.north_m)
        hits = window[near <= stations.half_width_m[window] + reach]
        pairs_station.append(hits)
        pairs_blocker.append(np.full(len(hits), j))
    if not pairs_station:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    return np.concatenate(pairs_station).astype(np.intp), np.concatenate(pairs_blocker).astype(np.intp)


class _Shapes:
    """The blocker of each (station, blocker) pair, as arrays."""

    def __init__(self, blocking: Sequence[Blocker], blocker: NDArray[np.intp]) -> None:
        rows = [(b.east_m, b.north_m, b.radius_m, b.yaw_rad, b.half_length_m, b.half_width_m) for b in blocking]
        columns = np.array(rows).reshape(-1, 6)[blocker].T
        self.east, self.north, self.radius, yaw, self.half_length, self.half_width = columns
        self.cos, self.sin = np.cos(yaw), np.sin(yaw)


class _Frame:
    """Each pair's blocker centre relative to its station, and the station's normal."""

    def __init__(self, rel_east: FloatArray, rel_north: FloatArray, n_east: FloatArray, n_north: FloatArray) -> None:
        self.rel_east, self.rel_north = rel_east, rel_north
        self.n_east, self.n_north = n_east, n_north

    def along_across(self, east: FloatArray, north: FloatArray) -> tuple[FloatArray, FloatArray]:
        """A point given relative to the blocker's centre, along and across the station's cross-section."""
        x, y = self.rel_east + east, self.rel_north + north
        return x * self.n_north - y * self.n_east, x * self.n_east + y * self.n_north


def _circle_strip_spans(radius: FloatArray, frame: _Frame, strip_m: float) -> tuple[FloatArray, FloatArray]:
    """A circle's reach across a strip: its full width where its centre is in the strip, else the
    chord on the strip's nearer edge; empty spans come out as low > high."""
    zero = np.zeros_like(radius)
    along, across = frame.along_across(zero, zero)
    outside = np.maximum(np.abs(along) - strip_m, 0.0)
    half = np.sqrt(np.maximum(radius**2 - outside**2, 0.0))
    hit = outside <= radius
    return np.where(hit, across - half, np.inf), np.where(hit, across + half, -np.inf)


def _rect_strip_spans(shapes: _Shapes, frame: _Frame, strip_m: float) -> tuple[FloatArray, FloatArray]:
    """A rectangle's reach across a strip. The rectangle cut by the strip is a convex polygon with
    the rectangle's corners inside the strip and its crossings of the strip's two edges for
    corners, so its extent across is the hull of those."""
    low, high = np.full(len(shapes.east), np.inf), np.full(len(shapes.east), -np.inf)
    for edge in (-strip_m, strip_m):
        edge_low, edge_high = _rect_line_span(shapes, frame, edge)
        low, high = np.minimum(low, edge_low), np.maximum(high, edge_high)
    for x_sign, y_sign in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        x, y = x_sign * shapes.half_length, y_sign * shapes.half_width
        along, across = frame.along_across(x * shapes.cos - y * shapes.sin, x * shapes.sin + y * shapes.cos)
        inside = np.abs(along) <= strip_m
        low = np.where(inside, np.minimum(low, across), low)
        high = np.where(inside, np.maximum(high, across), high)
    return low, high


def _rect_line_span(shapes: _Shapes, frame: _Frame, edge_m: float) -> tuple[FloatArray, FloatArray]:
    """Where the cross-section line ``edge_m`` along from the station runs inside the rectangle:
    the slab test, one slab per rectangle axis; (inf, -inf) where it misses."""
    # The line's origin relative to the rectangle's centre; its direction is the normal.
    origin_east = edge_m * frame.n_north - frame.rel_east
    origin_north = -edge_m * frame.n_east - frame.rel_north
    low, high = np.full(len(shapes.east), -np.inf), np.full(len(shapes.east), np.inf)
    for axis_east, axis_north, half in (
        (shapes.cos, shapes.sin, shapes.half_length),
        (-shapes.sin, shapes.cos, shapes.half_width),
    ):
        offset = origin_east * axis_east + origin_north * axis_north
        rate = frame.n_east * axis_east + frame.n_north * axis_north
        flat = np.abs(rate) < 1e-12
        safe = np.where(flat, 1.0, rate)
        a, b = (-half - offset) / safe, (half - offset) / safe
        inside = np.abs(offset) <= half
        low = np.maximum(low, np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(a, b)))
        high = np.minimum(high, np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(a, b)))
    missed = low > high
    return np.where(missed, np.inf, low), np.where(missed, -np.inf, high)


def _free(low: FloatArray, high: FloatArray, half: float) -> list[Interval]:
    """The gaps between blocked intervals (sorted by low) in the band -half..half."""
    free, edge = [], -half
    for lo, hi in zip(low.tolist(), high.tolist(), strict=True):
        if lo > edge:
            free.append((edge, lo))
        edge = max(edge, hi)
    if edge < half:
        free.append((edge, half))
    return free


def _continue(
    lane: list[Interval], free: list[Interval], need_before: float, need: float
) -> tuple[list[Interval], float]:
    """The free intervals wide enough for the lane that overlap it by the lane's width, and the
    widest continuation there is (how far short it falls, when none is kept)."""
    kept, widest = [], 0.0
    overlap_need = min(need_before, need)
    for lo, hi in free:
        overlap = max((min(hi, top) - max(lo, bottom) for bottom, top in lane), default=0.0)
        widest = max(widest, min(overlap, hi - lo))
        if hi - lo >= need - _EPS_M and overlap >= overlap_need - _EPS_M:
            kept.append((lo, hi))
    return kept, widest


def _report(
    stations: Stations,
    k: int,
    widest: float,
    need: FloatArray,
    blocking: Sequence[Blocker],
    involved: NDArray[np.intp],
) -> Unfairness:
    names = [blocking[j] for j in np.unique(involved)]  # in the scenario's order
    return Unfairness(
        at_m=float(stations.s_m[k]),
        widest_m=widest,
        need_m=float(need[k]),
        obstacles=tuple(b.name for b in names if not b.is_hazard),
        hazards=tuple(b.name for b in names if b.is_hazard),
    )
