"""An RDDF course in a local East-North-Up frame: corridor geometry and a 1 m path with desired speeds.

Segment *i* runs from waypoint *i* to *i + 1* and takes waypoint *i*'s lateral boundary offset and
speed limit. Its band is every point within the offset of the segment (a capsule); the corridor is
the union of the bands. Positions are metres east and north of the origin (the first waypoint
unless given), on the WGS84 tangent plane through it, converted by pymap3d.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import pymap3d
from numpy.typing import ArrayLike, NDArray

from brain.rddf import Waypoint, load_rddf

FT_TO_M = 0.3048
MPH_TO_MPS = 0.44704
WGS84 = pymap3d.Ellipsoid.from_name("wgs84")

DEFAULT_SPACING_M = 1.0
DEFAULT_MAX_LATERAL_ACCEL_MPS2 = 2.0
DEFAULT_MAX_DECEL_MPS2 = 2.0
DEFAULT_MAX_ACCEL_MPS2 = 1.5
DEFAULT_TURN_WINDOW_M = 8.0

MIN_SEGMENT_M = 1e-3  # shorter segments (repeated waypoints) have no heading; the path skips them
_CHUNK_ELEMENTS = 1 << 20  # points x segments evaluated at once by the corridor queries

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class GeodeticOrigin:
    """Where the local frame's axes meet: WGS84 latitude and longitude, height above the ellipsoid."""

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0


class Corridor:
    """The union of capsules: points within ``half_width_m[i]`` of the segment ``start_m[i]``-``end_m[i]``.

    Queries take scalars or arrays of any matching shape and answer in kind.
    """

    def __init__(self, start_m: ArrayLike, end_m: ArrayLike, half_width_m: ArrayLike) -> None:
        self.start_m = _frozen(np.array(start_m, dtype=float).reshape(-1, 2))
        self.end_m = _frozen(np.array(end_m, dtype=float).reshape(-1, 2))
        self.half_width_m = _frozen(np.array(half_width_m, dtype=float).reshape(-1))
        if not len(self.start_m) == len(self.end_m) == len(self.half_width_m) > 0:
            raise ValueError("a corridor needs one start, end and half width per segment, and a segment")
        if np.any(self.half_width_m <= 0.0):
            raise ValueError("half widths must be positive")
        direction = self.end_m - self.start_m
        self._direction = direction
        self._length2 = np.einsum("ij,ij->i", direction, direction)

    def distance_to_edge(self, east_m: ArrayLike, north_m: ArrayLike) -> Any:
        """Signed distance to the corridor's edge in metres: positive inside, negative outside, 0 on it.

        Outside it is exactly minus the distance to the corridor. Inside it is the largest clearance to
        the edge of a band containing the point: exact except where bands overlap, where it can
        understate the clearance to the union's edge (never overstate it).
        """
        east, north = np.broadcast_arrays(np.asarray(east_m, dtype=float), np.asarray(north_m, dtype=float))
        clearance = self._clearance(east.ravel(), north.ravel()).reshape(east.shape)
        return float(clearance) if clearance.ndim == 0 else clearance

    def contains(self, east_m: ArrayLike, north_m: ArrayLike) -> Any:
        """True where a point lies in the corridor, boundary included."""
        inside = np.asarray(self.distance_to_edge(east_m, north_m)) >= 0.0
        return bool(inside) if inside.ndim == 0 else inside

    def bounds_m(self) -> tuple[float, float, float, float]:
        """(min east, min north, max east, max north) of the corridor."""
        ends = np.concatenate([self.start_m, self.end_m])
        radius = np.concatenate([self.half_width_m, self.half_width_m])[:, None]
        low = (ends - radius).min(axis=0)
        high = (ends + radius).max(axis=0)
        return float(low[0]), float(low[1]), float(high[0]), float(high[1])

    def _clearance(self, east: FloatArray, north: FloatArray) -> FloatArray:
        result = np.empty(east.shape)
        chunk = max(1, _CHUNK_ELEMENTS // len(self.half_width_m))
        for first in range(0, len(east), chunk):
            part = slice(first, first + chunk)
            result[part] = self._chunk_clearance(east[part], north[part])
        return result

    def _chunk_clearance(self, east: FloatArray, north: FloatArray) -> FloatArray:
        # Rows are points, columns segments: closest point on each segment, then its distance.
        rel_e = east[:, None] - self.start_m[None, :, 0]
        rel_n = north[:, None] - self.start_m[None, :, 1]
        along = rel_e * self._direction[:, 0] + rel_n * self._direction[:, 1]
        fraction = np.divide(along, self._length2, out=np.zeros_like(along), where=self._length2 > 0.0)
        np.clip(fraction, 0.0, 1.0, out=fraction)
        distance = np.hypot(rel_e - fraction * self._direction[:, 0], rel_n - fraction * self._direction[:, 1])
        return (self.half_width_m - distance).max(axis=1)


@dataclass(frozen=True)
class CoursePath:
    """The course resampled at even arc-length steps, with the desired speed at each point.

    ``speed_limit_mps`` is the RDDF limit a point must respect (the slowest segment within one step,
    so the vehicle is slow enough when it crosses into a slower segment), ``curvature_1pm`` the
    smoothed unsigned curvature the lateral-acceleration limit was applied to, ``segment`` the
    index of the segment (= its start waypoint) each point lies on.
    """

    east_m: FloatArray
    north_m: FloatArray
    s_m: FloatArray
    speed_mps: FloatArray
    half_width_m: FloatArray
    speed_limit_mps: FloatArray
    curvature_1pm: FloatArray
    segment: NDArray[np.intp]

    @property
    def spacing_m(self) -> float:
        """Arc length between consecutive points."""
        return float(self.s_m[1] - self.s_m[0])

    @property
    def length_m(self) -> float:
        """Arc length from the first point to the last."""
        return float(self.s_m[-1])

    def drive_time_s(self) -> float:
        """Time to drive the path at the desired speeds, accelerating evenly between points."""
        return float(np.sum(2.0 * np.diff(self.s_m) / (self.speed_mps[:-1] + self.speed_mps[1:])))


class Course:
    """RDDF waypoints placed in the local ENU frame, with their segments' limits in SI units."""

    def __init__(self, waypoints: Sequence[Waypoint], origin: GeodeticOrigin | None = None) -> None:
        if len(waypoints) < 2:
            raise ValueError(f"a course needs at least 2 waypoints, got {len(waypoints)}")
        self.waypoints = tuple(waypoints)
        first = self.waypoints[0]
        self.origin = origin or GeodeticOrigin(first.lat_deg, first.lon_deg)
        lat = np.array([w.lat_deg for w in self.waypoints])
        lon = np.array([w.lon_deg for w in self.waypoints])
        # RDDFs carry no heights: waypoints sit at the origin's height, so "up" is the earth's drop.
        east, north, up = pymap3d.geodetic2enu(lat, lon, self.origin.alt_m, *self._origin_args(), ell=WGS84)
        self.east_m = _frozen(np.asarray(east, dtype=float))
        self.north_m = _frozen(np.asarray(north, dtype=float))
        self.up_m = _frozen(np.asarray(up, dtype=float))
        segments = self.waypoints[:-1]
        self.half_width_m = _frozen(np.array([w.lateral_offset_ft * FT_TO_M for w in segments]))
        self.speed_limit_mps = _frozen(np.array([w.speed_limit_mph * MPH_TO_MPS for w in segments]))
        self.segment_length_m = _frozen(np.hypot(np.diff(self.east_m), np.diff(self.north_m)))
        self._check_segments()

    @classmethod
    def from_file(cls, path: str | Path, origin: GeodeticOrigin | None = None) -> Course:
        """Load an RDDF file (raises `brain.rddf.RddfError`) and place it."""
        return cls(load_rddf(path), origin)

    @property
    def length_m(self) -> float:
        """Length of the centreline through all waypoints."""
        return float(self.segment_length_m.sum())

    @cached_property
    def corridor(self) -> Corridor:
        """The drivable area: each segment's band of its start waypoint's lateral offset."""
        points = np.column_stack([self.east_m, self.north_m])
        return Corridor(points[:-1], points[1:], self.half_width_m)

    def to_enu(self, lat_deg: ArrayLike, lon_deg: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(east_m, north_m) of WGS84 positions at the origin's height, e.g. GPS fixes."""
        east, north, _ = pymap3d.geodetic2enu(
            np.asarray(lat_deg, dtype=float),
            np.asarray(lon_deg, dtype=float),
            self.origin.alt_m,
            *self._origin_args(),
            ell=WGS84,
        )
        return np.asarray(east), np.asarray(north)

    def to_geodetic(
        self, east_m: ArrayLike, north_m: ArrayLike, up_m: ArrayLike = 0.0
    ) -> tuple[FloatArray, FloatArray]:
        """(lat_deg, lon_deg) of local positions.

        ``up_m`` 0 is the tangent plane, which rises above the ground away from the origin (a few mm in
        horizontal position 5 km out); `Course.up_m` holds the waypoints' exact values.
        """
        lat, lon, _ = pymap3d.enu2geodetic(
            np.asarray(east_m, dtype=float),
            np.asarray(north_m, dtype=float),
            np.asarray(up_m, dtype=float),
            *self._origin_args(),
            ell=WGS84,
        )
        return np.asarray(lat), np.asarray(lon)

    def interpolate(
        self,
        spacing_m: float = DEFAULT_SPACING_M,
        max_lateral_accel_mps2: float = DEFAULT_MAX_LATERAL_ACCEL_MPS2,
        max_decel_mps2: float = DEFAULT_MAX_DECEL_MPS2,
        max_accel_mps2: float = DEFAULT_MAX_ACCEL_MPS2,
        turn_window_m: float = DEFAULT_TURN_WINDOW_M,
        initial_speed_mps: float = 0.0,
        final_speed_mps: float = 0.0,
    ) -> CoursePath:
        """Resample the centreline every ``spacing_m`` (evened out to end on the last waypoint).

        The desired speed is the RDDF limit, capped by ``sqrt(max_lateral_accel / curvature)`` where
        the curvature is the heading change at the corners spread over ``turn_window_m`` of path,
        then limited so the vehicle accelerates from ``initial_speed_mps`` and slows for every
        slower part ahead (and stops at ``final_speed_mps``) within its acceleration limits.
        """
        _check_positive(
            spacing_m=spacing_m,
            max_lateral_accel_mps2=max_lateral_accel_mps2,
            max_decel_mps2=max_decel_mps2,
            max_accel_mps2=max_accel_mps2,
            turn_window_m=turn_window_m,
        )
        if initial_speed_mps < 0.0 or final_speed_mps < 0.0:
            raise ValueError("initial and final speeds must not be negative")
        s, east, north, segment = self._resample(spacing_m)
        step = float(s[1])
        speed_limit = self._speed_limits_at(s, step)
        curvature = _smoothed_curvature(east, north, step, turn_window_m)
        with np.errstate(divide="ignore"):
            turn_limit = np.sqrt(max_lateral_accel_mps2 / curvature)
        cap = np.minimum(speed_limit, turn_limit)
        cap[0] = min(cap[0], initial_speed_mps)
        cap[-1] = min(cap[-1], final_speed_mps)
        return CoursePath(
            east_m=_frozen(east),
            north_m=_frozen(north),
            s_m=_frozen(s),
            speed_mps=_frozen(_accel_limited(cap, step, max_accel_mps2, max_decel_mps2)),
            half_width_m=_frozen(self.half_width_m[segment]),
            speed_limit_mps=_frozen(speed_limit),
            curvature_1pm=_frozen(curvature),
            segment=_frozen(segment),
        )

    def _drivable_segments(self) -> tuple[NDArray[np.intp], FloatArray]:
        """Indices of the segments with a length, and the arc length at each of their ends."""
        segments = np.flatnonzero(self.segment_length_m >= MIN_SEGMENT_M)
        return segments, np.concatenate([[0.0], np.cumsum(self.segment_length_m[segments])])

    def _resample(self, spacing_m: float) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.intp]]:
        """Arc length, east, north and segment of evenly spaced points from the first waypoint to the last."""
        segments, knots_s = self._drivable_segments()
        # At least two steps, so every step has an end away from a standstill at either end.
        steps = max(2, round(knots_s[-1] / spacing_m))
        s = np.linspace(0.0, knots_s[-1], steps + 1)
        index = np.clip(np.searchsorted(knots_s, s, side="right") - 1, 0, len(segments) - 1)
        segment = segments[index]
        fraction = (s - knots_s[index]) / self.segment_length_m[segment]
        east = self.east_m[segment] + fraction * (self.east_m[segment + 1] - self.east_m[segment])
        north = self.north_m[segment] + fraction * (self.north_m[segment + 1] - self.north_m[segment])
        return s, east, north, segment

    def _speed_limits_at(self, s: FloatArray, step: float) -> FloatArray:
        """Each point's RDDF limit: the lowest of the segments within one step of it, boundaries included."""
        segments, knots_s = self._drivable_segments()
        limit = np.full(s.shape, np.inf)
        reach = step * (1.0 - 1e-9)  # a point exactly one step before a boundary stays with its own segment
        for start, end, value in zip(knots_s[:-1], knots_s[1:], self.speed_limit_mps[segments], strict=True):
            first = np.searchsorted(s, start - reach, side="left")
            last = np.searchsorted(s, end + reach, side="right")
            np.minimum(limit[first:last], value, out=limit[first:last])
        return limit

    def _origin_args(self) -> tuple[float, float, float]:
        return self.origin.lat_deg, self.origin.lon_deg, self.origin.alt_m

    def _check_segments(self) -> None:
        if np.any(self.half_width_m <= 0.0):
            raise ValueError("every segment needs a positive lateral offset")
        if np.any(self.speed_limit_mps <= 0.0):
            raise ValueError("every segment needs a positive speed limit (0 mph is for the last waypoint only)")
        if self.length_m < MIN_SEGMENT_M:
            raise ValueError("all waypoints are at the same place: the course has no length")


def _check_positive(**values: float) -> None:
    for name, value in values.items():
        if not value > 0.0:
            raise ValueError(f"{name} must be positive, got {value}")


def _smoothed_curvature(east: FloatArray, north: FloatArray, step: float, window_m: float) -> FloatArray:
    """Unsigned heading change per metre, averaged over a window centred on each point."""
    heading = np.arctan2(np.diff(north), np.diff(east))
    turn = np.zeros(east.shape)
    turn[1:-1] = np.abs(np.angle(np.exp(1j * np.diff(heading))))  # wrapped to [0, pi]
    width = 2 * round(window_m / (2.0 * step)) + 1
    # Unsigned, so the two bends of an S inside one window add up instead of cancelling.
    # "full" then the centred slice: mode "same" grows the result when the window outsizes the path.
    summed = np.convolve(turn, np.ones(width), mode="full")[width // 2 : width // 2 + len(turn)]
    return summed / (width * step)


def _accel_limited(cap_mps: FloatArray, step: float, max_accel_mps2: float, max_decel_mps2: float) -> FloatArray:
    """Highest speeds under ``cap_mps`` reachable forwards and stoppable backwards within the limits.

    v[k+1]^2 <= v[k]^2 + 2 a step is a running minimum of cap^2 - 2 a step k, so both passes are exact
    and vectorised.
    """
    squared = cap_mps**2
    ramp = 2.0 * step * np.arange(len(squared))
    squared = np.minimum.accumulate(squared - max_accel_mps2 * ramp) + max_accel_mps2 * ramp
    backward = squared[::-1]
    backward = np.minimum.accumulate(backward - max_decel_mps2 * ramp) + max_decel_mps2 * ramp
    return np.sqrt(np.maximum(backward[::-1], 0.0))


def _frozen(array: NDArray[Any]) -> NDArray[Any]:
    array.setflags(write=False)
    return array
