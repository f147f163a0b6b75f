"""The course's centre path as a station/lateral frame: ENU <-> (s, d).

``s`` is the arc length along the centre path (`brain.corridor.CoursePath`), ``d`` the signed
lateral offset, left of the direction of travel positive: the point ``d`` metres along the unit
normal at ``s``. Each vertex's normal is perpendicular to the path's mean direction over a
window of path around it, and normals are interpolated along a segment, so (s, d) -> ENU is
continuous through the corners (a plain per-segment normal would tear offset paths apart at the
outside of every bend), and offsets on the inside of a sharp RDDF corner do not fold back on
themselves until they grow to a fair part of the window (the default 16 m keeps 5 m offsets
moving forwards round a right angle). On the inside of a bend several stations can reach one point;
the inverse returns the smallest offset. It solves, per segment, for the station whose
interpolated normal passes through the point: a quadratic in the segment fraction.

The centre path's corners can be rounded (``rounding_m``): each point becomes the mean of the
path within half that distance either side. An RDDF corner is a vertex whose turn the course's
speed profile spreads over its turn window; the polyline itself turns all at once, and a path
along it would have to slow far below that speed (or be cut by control). Averaged over twice
that window, the corner's curvature stays within what the course's speed assumes up to 90
degrees, for a cut of 1.6 m into a 47 degree corner (2.8 m into a right angle). Stations stay
the course's.

Locating the vehicle searches only a window around its previous station, so a course that loops
back near itself cannot make the station jump to a distant part of it.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brain.corridor import CoursePath

FloatArray = NDArray[np.float64]

_CHUNK_ELEMENTS = 1 << 18  # points x segments solved at once
_ROOT_SLACK = 1e-9  # segment fractions this far outside [0, 1] still count as on the segment
DEFAULT_NORMAL_WINDOW_M = 16.0


class CorridorFrame:
    """Station/lateral coordinates along a `CoursePath` (at least two points)."""

    def __init__(
        self, path: CoursePath, normal_window_m: float = DEFAULT_NORMAL_WINDOW_M, rounding_m: float = 0.0
    ) -> None:
        if not normal_window_m > 0 or not rounding_m >= 0:
            raise ValueError("the normal window must be positive and the rounding not negative")
        east = np.asarray(path.east_m, dtype=float)
        north = np.asarray(path.north_m, dtype=float)
        if east.shape != north.shape or east.ndim != 1 or len(east) < 2:
            raise ValueError("a corridor frame needs a centre path of at least two points")
        rounded_e, rounded_n = _rounded(east, north, np.asarray(path.s_m, dtype=float), rounding_m)
        # How far rounding moved each point off the course's own line (0 without rounding).
        self.cut_m = np.hypot(rounded_e - east, rounded_n - north)
        east, north = rounded_e, rounded_n
        self.path = path
        self.points = np.column_stack([east, north])
        self.s_m = np.asarray(path.s_m, dtype=float)
        step = np.diff(self.points, axis=0)
        self.segment_length_m = np.hypot(step[:, 0], step[:, 1])
        if np.any(self.segment_length_m <= 0.0) or np.any(np.diff(self.s_m) <= 0.0):
            raise ValueError("the centre path has repeated points")
        self.tangent = step / self.segment_length_m[:, None]
        # Stations are the course's arc length: across a corner the path's chord is shorter than its
        # station step, so positions within a segment go by the fraction of the station step.
        self.station_step_m = np.diff(self.s_m)
        self.normal = self._vertex_normals(normal_window_m)
        # A chord across an RDDF corner cuts inside it: by at most the height of the isosceles
        # triangle with the chord as base and the station step as its two other sides together.
        self.chord_sag_m = np.sqrt(np.maximum(self.station_step_m**2 - self.segment_length_m**2, 0.0)) / 2.0

    @property
    def length_m(self) -> float:
        return float(self.s_m[-1])

    def to_enu(self, s_m: ArrayLike, d_m: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """ENU of frame coordinates; stations beyond either end extend the end segment straight."""
        s, d = np.broadcast_arrays(np.asarray(s_m, dtype=float), np.asarray(d_m, dtype=float))
        index, fraction = self._segment_of(s)
        centre_e, centre_n = self.to_centre(s)
        normal = self._normal_at(index, np.clip(fraction, 0.0, 1.0))
        return centre_e + d * normal[..., 0], centre_n + d * normal[..., 1]

    def cross_sections(self, s_m: ArrayLike, d_m: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """ENU of every offset in ``d_m`` at every station in ``s_m`` (shape len(s) x len(d)):
        `to_enu` on the outer product, computing each station's centre and normal once."""
        s = np.asarray(s_m, dtype=float).reshape(-1)
        d = np.asarray(d_m, dtype=float).reshape(-1)
        centre_e, centre_n = self.to_enu(s, np.zeros_like(s))
        index, fraction = self._segment_of(s)
        normal = self._normal_at(index, np.clip(fraction, 0.0, 1.0))
        return centre_e[:, None] + normal[:, None, 0] * d, centre_n[:, None] + normal[:, None, 1] * d

    def band_box(self, s_from_m: float, s_to_m: float, margin_m: float) -> tuple[float, float, float, float]:
        """(min east, min north, max east, max north) of a box holding every point within the
        corridor plus ``margin_m`` between two stations: the centre path there, widened by the
        widest half width and the furthest rounding cut (the RDDF's line is that far off it)."""
        first, last = (int(i) for i in self._segment_of(np.array([s_from_m, s_to_m]))[0])
        ends = np.column_stack(self.to_enu(np.array([s_from_m, s_to_m]), np.zeros(2)))
        points = np.vstack([ends, self.points[first + 1 : last + 1]])
        vertices = slice(first, last + 2)
        radius = float(np.max(self.path.half_width_m[vertices]) + np.max(self.cut_m[vertices])) + margin_m
        low, high = points.min(axis=0) - radius, points.max(axis=0) + radius
        return float(low[0]), float(low[1]), float(high[0]), float(high[1])

    def heading_at(self, s_m: ArrayLike) -> FloatArray:
        """Direction of travel of the frame (perpendicular to its interpolated normal), radians from east."""
        index, fraction = self._segment_of(np.asarray(s_m, dtype=float))
        normal = self._normal_at(index, np.clip(fraction, 0.0, 1.0))
        return np.arctan2(-normal[..., 0], normal[..., 1])

    def speed_at(self, s_m: ArrayLike) -> FloatArray:
        """The course's desired speed (`CoursePath.speed_mps`) interpolated at stations."""
        return np.interp(np.asarray(s_m, dtype=float), self.s_m, self.path.speed_mps)

    def half_width_at(self, s_m: ArrayLike) -> FloatArray:
        """Corridor half width at stations: the narrower of the two path points around each."""
        s = np.asarray(s_m, dtype=float)
        width = np.asarray(self.path.half_width_m, dtype=float)
        index = np.clip(np.searchsorted(self.s_m, s, side="right") - 1, 0, len(width) - 2)
        return np.minimum(width[index], width[index + 1])

    def sure_half_width_at(self, s_m: ArrayLike) -> FloatArray:
        """Offsets within this of the centre path are surely in the corridor at those stations:
        the point is |d| from the centre path, which is within a chord's sag (and the rounding's
        cut) of the RDDF line."""
        s = np.asarray(s_m, dtype=float)
        index = np.clip(np.searchsorted(self.s_m, s, side="right") - 1, 0, len(self.chord_sag_m) - 1)
        cut = np.maximum(self.cut_m[index], self.cut_m[index + 1])
        return self.half_width_at(s) - self.chord_sag_m[index] - cut

    def locate(
        self,
        east_m: ArrayLike,
        north_m: ArrayLike,
        near_s_m: float | None = None,
        behind_m: float = 15.0,
        ahead_m: float = 60.0,
    ) -> tuple[FloatArray, FloatArray]:
        """(s, d) of ENU points: the solution with the smallest |d| among the segments within
        ``[near_s_m - behind_m, near_s_m + ahead_m]`` (the whole path when ``near_s_m`` is None).

        A point beyond the searched stretch (behind its first segment or ahead of its last) gets
        the end segment's straight extension, so the answer never leaves the window by more than
        the point's own distance from it.
        """
        east, north = np.broadcast_arrays(np.asarray(east_m, dtype=float), np.asarray(north_m, dtype=float))
        if near_s_m is None:
            first, last = 0, len(self.segment_length_m)
        else:
            if not np.isfinite(near_s_m) or behind_m < 0 or ahead_m < 0:
                raise ValueError("locate needs a finite station and non-negative search distances")
            first = int(np.clip(np.searchsorted(self.s_m, near_s_m - behind_m, side="right") - 1, 0, None))
            last = int(np.clip(np.searchsorted(self.s_m, near_s_m + ahead_m, side="left"), first + 1, None))
            last = min(last, len(self.segment_length_m))
            first = min(first, last - 1)
        flat = np.column_stack([east.ravel(), north.ravel()])
        s = np.empty(len(flat))
        d = np.empty(len(flat))
        chunk = max(1, _CHUNK_ELEMENTS // (last - first))
        for start in range(0, len(flat), chunk):
            part = slice(start, start + chunk)
            s[part], d[part] = self._locate_chunk(flat[part], first, last)
        return s.reshape(east.shape), d.reshape(east.shape)

    def locate_start(self, east_m: float, north_m: float, yaw_rad: float, reach_m: float = 20.0) -> float:
        """The station of a vehicle with no previous station (a start, or a restarted brain):
        where the course passes within ``reach_m`` more than once (it crosses or doubles back
        on itself), the pass whose direction agrees with the vehicle's heading, earliest first.
        Without a pass that near, the nearest solution on the whole course."""
        distance = np.hypot(self.points[:, 0] - east_m, self.points[:, 1] - north_m)
        near = np.flatnonzero(distance <= reach_m)
        if len(near) == 0:
            return float(self.locate(east_m, north_m)[0])
        passes = np.split(near, np.flatnonzero(np.diff(near) > 1) + 1)
        choices = []
        for run in passes:
            hint = float(self.s_m[run[np.argmin(distance[run])]])
            station = float(self.locate(east_m, north_m, hint, reach_m, reach_m)[0])
            agrees = math.cos(float(self.heading_at(station)) - yaw_rad) > 0.0
            choices.append((not agrees, station))
        return min(choices)[1]

    def _locate_chunk(self, points: FloatArray, first: int, last: int) -> tuple[FloatArray, FloatArray]:
        segments = slice(first, last)
        start = self.points[segments]  # (k, 2)
        chord = self.tangent[segments] * self.segment_length_m[segments, None]
        n0 = self.normal[first:last]
        dn = self.normal[first + 1 : last + 1] - n0
        q = points[:, None, :] - start[None, :, :]  # (m, k, 2)
        # cross(q - t chord, n0 + t dn) = 0 is a t^2 + b t + c = 0.
        a = -_cross(chord, dn)[None, :] * np.ones(len(points))[:, None]
        b = _cross(q, dn[None]) - _cross(chord, n0)[None, :]
        c = _cross(q, n0[None])
        best_d = np.full(len(points), np.inf)
        best_s = np.full(len(points), np.nan)
        for t in _roots(a, b, c):
            valid = (t >= -_ROOT_SLACK) & (t <= 1.0 + _ROOT_SLACK)
            t = np.clip(np.where(valid, t, 0.0), 0.0, 1.0)
            normal = n0[None] + t[..., None] * dn[None]
            norm = np.hypot(normal[..., 0], normal[..., 1])
            valid &= norm > 1e-9
            offset = q - t[..., None] * chord[None]
            d = (offset[..., 0] * normal[..., 0] + offset[..., 1] * normal[..., 1]) / np.where(valid, norm, 1.0)
            d = np.where(valid, d, np.inf)
            column = np.argmin(np.abs(d), axis=1)
            rows = np.arange(len(points))
            candidate = d[rows, column]
            better = np.abs(candidate) < np.abs(best_d)
            best_d = np.where(better, candidate, best_d)
            station = self.s_m[first + column] + t[rows, column] * self.station_step_m[first + column]
            best_s = np.where(better, station, best_s)
        # Points beyond either end of the searched stretch (a vehicle just behind the start line)
        # belong to the end's straight extension when it is nearer than any segment's solution:
        # a far segment can always "solve" for a point, with a large offset.
        ext_s, ext_d = self._extend(points, first, last)
        beyond = (ext_s < self.s_m[first]) | (ext_s > self.s_m[last])
        use = ~np.isfinite(best_d) | (beyond & (np.abs(ext_d) < np.abs(best_d)))
        best_s[use], best_d[use] = ext_s[use], ext_d[use]
        return best_s, best_d

    def _extend(self, points: FloatArray, first: int, last: int) -> tuple[FloatArray, FloatArray]:
        """Points in no segment's reach: project onto the straight extension of the nearer end."""
        head, tail = self.points[first], self.points[last]
        use_tail = np.hypot(*(points - tail).T) < np.hypot(*(points - head).T)
        anchor = np.where(use_tail[:, None], tail, head)
        tangent = np.where(use_tail[:, None], self.tangent[last - 1], self.tangent[first])
        normal = np.where(use_tail[:, None], self.normal[last], self.normal[first])
        rel = points - anchor
        station = np.where(use_tail, self.s_m[last], self.s_m[first]) + np.einsum("ij,ij->i", rel, tangent)
        return station, np.einsum("ij,ij->i", rel, normal)

    def _segment_of(self, s: FloatArray) -> tuple[NDArray[np.intp], FloatArray]:
        index = np.clip(np.searchsorted(self.s_m, s, side="right") - 1, 0, len(self.segment_length_m) - 1)
        return index, (s - self.s_m[index]) / self.station_step_m[index]

    def _vertex_normals(self, window_m: float) -> FloatArray:
        """Left unit normals at the vertices, perpendicular to the path's mean direction over
        ``window_m`` around each: the chord from half a window behind to half ahead (the integral
        of the tangent is the displacement). On straight stretches that is the segment's own
        normal; through a bend the normals turn gradually, so offsets on the inside do not fold
        over until they exceed the window over the bend's angle."""
        half = window_m / 2.0
        behind = np.column_stack(self.to_centre(np.maximum(self.s_m - half, self.s_m[0])))
        ahead = np.column_stack(self.to_centre(np.minimum(self.s_m + half, self.s_m[-1])))
        chord = ahead - behind
        norm = np.hypot(chord[:, 0], chord[:, 1])
        own = np.concatenate([self.tangent, self.tangent[-1:]])  # a U-turn within the window: no mean direction
        direction = np.where((norm > 1e-6 * window_m)[:, None], chord / np.maximum(norm, 1e-12)[:, None], own)
        return np.column_stack([-direction[:, 1], direction[:, 0]])

    def to_centre(self, s_m: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """ENU of centre-path points at stations (the polyline; straight beyond the ends)."""
        s = np.asarray(s_m, dtype=float)
        index, fraction = self._segment_of(s)
        centre = self.points[index] + (fraction * self.segment_length_m[index])[..., None] * self.tangent[index]
        return centre[..., 0], centre[..., 1]

    def _normal_at(self, index: NDArray[np.intp], fraction: FloatArray) -> FloatArray:
        start = self.normal[index]
        normal = start + fraction[..., None] * (self.normal[index + 1] - start)
        norm = np.sqrt(normal[..., 0] ** 2 + normal[..., 1] ** 2)
        degenerate = norm <= 1e-9
        if degenerate.any():
            # Opposite vertex normals (a U-turn in one step) cancel halfway: take the segment's own.
            tangent = self.tangent[index[degenerate]]
            normal[degenerate] = np.column_stack([-tangent[:, 1], tangent[:, 0]])
            norm[degenerate] = 1.0
        return normal / norm[..., None]


def _rounded(east: FloatArray, north: FloatArray, s: FloatArray, window_m: float) -> tuple[FloatArray, FloatArray]:
    """Each point replaced by the mean of the path's points within ``window_m / 2`` of station
    either side (the path continued straight past its ends, so the ends stay put)."""
    half = round(window_m / 2.0 / max(float(np.mean(np.diff(s))), 1e-9))
    if half < 1:
        return east, north
    steps = np.arange(1, half + 1)
    kernel = np.full(2 * half + 1, 1.0 / (2 * half + 1))
    out = []
    for v in (east, north):
        extended = np.concatenate([v[0] - (v[1] - v[0]) * steps[::-1], v, v[-1] + (v[-1] - v[-2]) * steps])
        out.append(np.convolve(extended, kernel, mode="valid"))
    return out[0], out[1]


def _cross(u: FloatArray, v: FloatArray) -> FloatArray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _roots(a: FloatArray, b: FloatArray, c: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Both real roots of a t^2 + b t + c (NaN where there are none), stable when a is tiny."""
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = b * b - 4.0 * a * c
        root = np.sqrt(np.where(disc >= 0.0, disc, np.nan))
        q = -0.5 * (b + np.copysign(root, b))
        linear = np.abs(a) <= 1e-12 * np.maximum(np.abs(b), 1e-300)
        first = np.where(linear, -c / b, c / q)
        second = np.where(linear, np.nan, q / a)
    return first, second
