"""The path interface: where the vehicle is relative to the planned path (RASCAL II.C).

A :class:`TrackedPath` is the geometry of one Path message (ENU polyline with target speeds);
a :class:`PathTracker` follows one reference point of the vehicle along it. The closest point is
searched only in a window around the previous one, so the tracker never jumps to a distant part
of a path that happens to pass close by (a hairpin, a crossing); only a new path is searched
whole, and even then among segments heading the vehicle's way, taking the earliest of the
nearly-closest ones.

Sign conventions: cross-track error is positive when the vehicle is LEFT of the path (looking
along it); headings are ENU yaw, counter-clockwise from east; curvature is positive for a left turn.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from protocol.messages import PathPoint
from rascal.runtime.angles import wrap_angle

FloatArray = NDArray[np.float64]
MIN_SEGMENT_M = 1e-3  # shorter steps are duplicates: they have no heading
NEW_PATH_TIE_M = 1.0  # on a new path, the earliest segment this close to the nearest one wins
DEFAULT_HEADING_SMOOTHING_M = 1.0
_SMOOTHING_SAMPLES = 9


class PathError(ValueError):
    """A path the controller cannot follow; the message says why."""


class Projection(NamedTuple):
    """The vehicle reference point seen from the path."""

    s_m: float  # arc length of the closest point (negative before the start, > length past the end)
    east_m: float  # the closest point
    north_m: float
    cross_track_m: float  # signed distance, left of the path positive
    heading_rad: float  # path heading at s
    curvature_1pm: float  # path curvature at s, left turn positive
    speed_mps: float  # target speed at s
    beyond_end_m: float  # how far past the last point (0 while on the path)


class TrackedPath:
    """Immutable geometry of one planned path: arc length, smoothed heading, curvature, speeds."""

    def __init__(
        self,
        east_m: Sequence[float],
        north_m: Sequence[float],
        speed_mps: Sequence[float],
        heading_smoothing_m: float = DEFAULT_HEADING_SMOOTHING_M,
    ) -> None:
        """``heading_smoothing_m``: the reference heading at s is the mean path heading over
        s +- this, so a sharp polyline corner starts turning the wheels a little before it."""
        if not (math.isfinite(heading_smoothing_m) and heading_smoothing_m >= 0.0):
            raise PathError(f"heading_smoothing_m must be finite and not negative, got {heading_smoothing_m!r}")
        east = np.asarray(east_m, dtype=np.float64)
        north = np.asarray(north_m, dtype=np.float64)
        speed = np.asarray(speed_mps, dtype=np.float64)
        if not (east.ndim == north.ndim == speed.ndim == 1 and len(east) == len(north) == len(speed)):
            raise PathError("east, north and speed must be 1-D sequences of equal length")
        if not (np.all(np.isfinite(east)) and np.all(np.isfinite(north)) and np.all(np.isfinite(speed))):
            raise PathError("path has non-finite coordinates or speeds")
        if np.any(speed < 0.0):
            raise PathError(f"path has a negative target speed ({float(speed.min()):.2f} m/s)")
        # Drop repeated points: a zero-length step has no direction.
        keep = np.ones(len(east), dtype=bool)
        if len(east) > 1:
            keep[1:] = np.hypot(np.diff(east), np.diff(north)) >= MIN_SEGMENT_M
        east, north, speed = east[keep], north[keep], speed[keep]
        if len(east) < 2:
            raise PathError(f"path needs at least 2 distinct points, got {len(east)}")
        self.east = east
        self.north = north
        self.speed = speed
        self.dx = np.diff(east)
        self.dy = np.diff(north)
        self.seg_len = np.hypot(self.dx, self.dy)
        self.s = np.concatenate([[0.0], np.cumsum(self.seg_len)])
        self.seg_heading = np.arctan2(self.dy, self.dx)
        # Heading as a continuous function of arc length: segment headings (unwrapped) placed at
        # segment midpoints and interpolated, so a corner turns the reference over a segment
        # instead of stepping it, and curvature is its slope. A step in the reference heading
        # is a step in the Stanley command that the rate-limited steering can only follow late,
        # and the lag overshoots the corner (0.8 m instead of 0.3 m on a 48 degree RDDF bend).
        self.s_mid = self.s[:-1] + 0.5 * self.seg_len
        self.heading_unwrapped = np.unwrap(self.seg_heading)
        if heading_smoothing_m > 0.0 and self.segments > 1:
            offsets = np.linspace(-heading_smoothing_m, heading_smoothing_m, _SMOOTHING_SAMPLES)
            # The mean of the true (piecewise constant) heading around each midpoint.
            at = self.s_mid[:, None] + offsets[None, :]
            segment = np.clip(np.searchsorted(self.s, at, side="right") - 1, 0, self.segments - 1)
            self.heading_unwrapped = self.heading_unwrapped[segment].mean(axis=1)

    @classmethod
    def from_points(
        cls, points: Sequence[PathPoint], heading_smoothing_m: float = DEFAULT_HEADING_SMOOTHING_M
    ) -> TrackedPath:
        if len(points) == 0:
            raise PathError("path has no points")
        east = [p.east_m for p in points]
        return cls(east, [p.north_m for p in points], [p.speed_mps for p in points], heading_smoothing_m)

    @property
    def length_m(self) -> float:
        return float(self.s[-1])

    @property
    def segments(self) -> int:
        return len(self.seg_len)

    def point_at(self, s_m: float) -> tuple[float, float]:
        """ENU point at arc length ``s_m``; beyond either end, on the extension of the end segment."""
        if s_m <= 0.0:
            i, along = 0, s_m
        elif s_m >= self.s[-1]:
            i, along = self.segments - 1, s_m - self.s[-2]
        else:
            i = int(np.searchsorted(self.s, s_m, side="right")) - 1
            along = s_m - self.s[i]
        h = self.seg_heading[i]
        return float(self.east[i] + along * math.cos(h)), float(self.north[i] + along * math.sin(h))

    def _heading_unwrapped_at(self, s_m: float) -> float:
        return float(np.interp(s_m, self.s_mid, self.heading_unwrapped))

    def heading_at(self, s_m: float) -> float:
        return wrap_angle(self._heading_unwrapped_at(s_m))

    def curvature_at(self, s_m: float, half_window_m: float) -> float:
        """Heading change per metre over ``s_m +- half_window_m`` (the window smooths the corners
        of a polyline into a turn the vehicle can drive)."""
        s0 = max(s_m - half_window_m, float(self.s_mid[0]))
        s1 = min(s_m + half_window_m, float(self.s_mid[-1]))
        if s1 <= s0:
            return 0.0
        return (self._heading_unwrapped_at(s1) - self._heading_unwrapped_at(s0)) / (s1 - s0)

    def speed_at(self, s_m: float) -> float:
        return float(np.interp(s_m, self.s, self.speed))

    def project(self, east_m: float, north_m: float, lo: int, hi: int) -> tuple[int, float, float, float]:
        """Closest point to (east, north) on segments ``lo..hi-1``: (segment, fraction along it,
        distance, signed cross-track). The first and last segments extend beyond the path's ends."""
        ax = self.east[lo:hi]
        ay = self.north[lo:hi]
        dx = self.dx[lo:hi]
        dy = self.dy[lo:hi]
        length2 = self.seg_len[lo:hi] ** 2
        px = east_m - ax
        py = north_m - ay
        t = (px * dx + py * dy) / length2
        low = np.zeros_like(t)
        high = np.ones_like(t)
        if lo == 0:
            low[0] = -np.inf
        if hi == self.segments:
            high[-1] = np.inf
        t = np.clip(t, low, high)
        d2 = (px - t * dx) ** 2 + (py - t * dy) ** 2
        k = int(np.argmin(d2))
        distance = math.sqrt(float(d2[k]))
        cross = float(dx[k] * py[k] - dy[k] * px[k])  # z of segment x (point - start): left positive
        signed = math.copysign(distance, cross) if cross != 0.0 else 0.0
        return lo + k, float(t[k]), distance, signed

    def first_nearest_segment(self, east_m: float, north_m: float, yaw_rad: float) -> int:
        """Where a vehicle at this pose joins a new path: among segments heading within 90 degrees
        of its yaw (all of them if none does), the earliest one nearly as close as the closest."""
        px = east_m - self.east[:-1]
        py = north_m - self.north[:-1]
        t = np.clip((px * self.dx + py * self.dy) / self.seg_len**2, 0.0, 1.0)
        d = np.hypot(px - t * self.dx, py - t * self.dy)
        ahead = np.cos(self.seg_heading - yaw_rad) > 0.0
        if np.any(ahead):
            d = np.where(ahead, d, np.inf)
        first = int(np.flatnonzero(d <= float(d.min()) + NEW_PATH_TIE_M)[0])
        # From there, down the distance to the nearest point of that stretch of path.
        while first + 1 < len(d) and d[first + 1] <= d[first]:
            first += 1
        return first


class PathTracker:
    """Follows one reference point along the current path with a windowed closest-point search."""

    def __init__(
        self, window_back_m: float = 2.0, window_ahead_m: float = 6.0, curvature_window_m: float = 2.0
    ) -> None:
        if window_back_m < 0.0 or window_ahead_m <= 0.0 or curvature_window_m <= 0.0:
            raise ValueError("tracker windows must be positive (window_back_m may be 0)")
        self.window_back_m = window_back_m
        self.window_ahead_m = window_ahead_m
        self.curvature_window_m = curvature_window_m
        self.path: TrackedPath | None = None
        self._s_m: float | None = None  # arc length of the last closest point; None: not yet located

    def set_path(self, path: TrackedPath) -> None:
        """Follow ``path`` from now on; the next :meth:`locate` searches it whole."""
        self.path = path
        self._s_m = None

    def locate(self, east_m: float, north_m: float, yaw_rad: float, travelled_m: float = 0.0) -> Projection:
        """Project the reference point onto the path. ``travelled_m`` is how far the vehicle may
        have moved since the last call; the window ahead grows by it."""
        path = self.path
        if path is None:
            raise PathError("no path to locate on")
        if self._s_m is None:
            first = path.first_nearest_segment(east_m, north_m, yaw_rad)
            lo, hi = max(0, first - 1), min(path.segments, first + 2)
        else:
            lo = int(np.searchsorted(path.s, self._s_m - self.window_back_m, side="right")) - 1
            hi = int(np.searchsorted(path.s, self._s_m + self.window_ahead_m + max(0.0, travelled_m), side="left"))
            lo, hi = max(0, min(lo, path.segments - 1)), max(1, min(hi, path.segments))
            hi = max(hi, lo + 1)
        segment, t, _distance, cross_track = path.project(east_m, north_m, lo, hi)
        s = float(path.s[segment] + t * path.seg_len[segment])
        self._s_m = s
        point_east = float(path.east[segment] + t * path.dx[segment])
        point_north = float(path.north[segment] + t * path.dy[segment])
        return Projection(
            s_m=s,
            east_m=point_east,
            north_m=point_north,
            cross_track_m=cross_track,
            heading_rad=path.heading_at(s),
            curvature_1pm=path.curvature_at(s, self.curvature_window_m),
            speed_mps=path.speed_at(s),
            beyond_end_m=max(0.0, s - path.length_m),
        )

    def lookahead_point(self, projection: Projection, distance_m: float) -> tuple[float, float]:
        """The path point ``distance_m`` of arc length beyond the closest one."""
        if self.path is None:
            raise PathError("no path")
        return self.path.point_at(projection.s_m + distance_m)

    def speed_ahead(self, projection: Projection, distance_m: float) -> float:
        """Target speed ``distance_m`` of arc length beyond the closest point."""
        if self.path is None:
            raise PathError("no path")
        return self.path.speed_at(projection.s_m + distance_m)
