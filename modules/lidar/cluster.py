"""Horizontal scan -> compact obstacle descriptors.

Consecutive returns are grouped while neighbouring points stay close; a cluster's points are then
explained as either the visible arc of a cylinder (circle fit) or the visible faces of a box (an
L-shape fit), and described as an upright box in the vehicle frame.

What "position" means: for a cylinder, its centre. For a box, the centre of a rectangle whose
near faces are the faces the lidar sees; where each face ends is bounded by its outermost return
and by the first ray past the cluster, which returned nothing from it. A side the lidar cannot
see at all (or only at a grazing angle) is assumed as long as the longer visible side, at most
``assumed_depth_max_m``: exact for square footprints, off by half the difference of the sides
otherwise. A large box seen from one side is therefore its visible face plus that assumed depth,
not its unobservable centre. Clusters of fewer than ``shape_min_points`` returns (an object
spanning a few ray spacings) cannot be told apart as arcs or corners and get the compact
estimate of :func:`_compact`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from modules.lidar.scan import Scan
from protocol.messages import Obstacle


@dataclass(frozen=True)
class ClusterParams:
    """How returns are grouped and described."""

    break_distance_m: float = 0.5  # neighbouring returns farther apart than this start a new cluster...
    break_spacing_factor: float = 3.0  # ...or than this many ray spacings at their range, if larger
    min_points: int = 2  # smaller clusters are dropped
    shape_min_points: int = 5  # fewer returns cannot tell an arc from a corner: compact estimate
    end_uncertainty_spacings: float = 2.0  # a face end known no better than this is assumed instead
    fit_tolerance_m: float = 0.03  # RMS residual above which neither a circle nor an L explains a cluster
    assumed_depth_max_m: float = 2.0  # cap on the assumed length of an unseen side: a long face is not a deep box
    face_tolerance_m: float = 0.05  # a point this close to a fitted face line lies on it
    confidence_points: float = 5.0  # confidence = 1 - exp(-points / this)


@dataclass(frozen=True)
class Cluster:
    """Consecutive returns of one object, in the sensor frame."""

    points: np.ndarray  # (n, 2)
    bearings_rad: np.ndarray  # (n,)
    ranges_m: np.ndarray  # (n,)


@dataclass(frozen=True)
class Footprint:
    """A cluster's estimated footprint in the sensor frame: an oriented rectangle, or for a
    cylinder (and a compact estimate) a square whose orientation says nothing (``round``)."""

    x_m: float
    y_m: float
    length_m: float  # along yaw
    width_m: float  # across yaw
    yaw_rad: float
    round: bool = False


class _Fit(NamedTuple):
    footprint: Footprint
    rms_m: float  # RMS distance of the points to the fitted shape
    straight: bool = False  # the points are one straight face, which no cylinder wide enough to fit shows


def describe_scan(scan: Scan, params: ClusterParams | None = None) -> tuple[Obstacle, ...]:
    """Every cluster of ``scan`` as an Obstacle in the vehicle frame, nearest first."""
    params = params or ClusterParams()
    step = scan.spec.resolution_rad
    descriptors = []
    for cluster in split(scan, params):
        footprint = fit(cluster, step, params)
        descriptors.append(to_vehicle(footprint, cluster, scan, params))
    return tuple(sorted(descriptors, key=lambda o: o.range_m))


def split(scan: Scan, params: ClusterParams) -> list[Cluster]:
    """Consecutive returns (in bearing order) grouped by point distance; tiny groups dropped.
    The break distance grows with range so that an object far away, whose returns lie a ray
    spacing or more apart, is not shattered into single points."""
    if not scan.returns.size:
        return []
    index, points = scan.points_sensor()
    ranges = scan.ranges_m[index]
    bearings = scan.bearings_rad[index]
    gaps = np.hypot(*np.diff(points, axis=0).T)
    limit = np.maximum(params.break_distance_m, params.break_spacing_factor * ranges[:-1] * scan.spec.resolution_rad)
    cuts = np.flatnonzero(gaps > limit) + 1
    starts, ends = np.r_[0, cuts], np.r_[cuts, index.size]
    return [
        Cluster(points[a:b], bearings[a:b], ranges[a:b])
        for a, b in zip(starts, ends, strict=True)
        if b - a >= params.min_points
    ]


def fit(cluster: Cluster, step_rad: float, params: ClusterParams) -> Footprint:
    """The footprint that best explains ``cluster``: a circle or a rectangle, whichever fits its
    points with the smaller residual, as long as one fits within ``fit_tolerance_m``; else, and
    for clusters too small to tell an arc from a corner, the compact estimate."""
    if len(cluster.points) < params.shape_min_points:
        return _compact(cluster, step_rad)
    rectangle = _rectangle(cluster, step_rad, params)
    candidates = [rectangle]
    if rectangle is None or not rectangle.straight:
        candidates.append(_circle(cluster))
    fits = [
        candidate for candidate in candidates if candidate is not None and candidate.rms_m <= params.fit_tolerance_m
    ]
    if not fits:
        return _compact(cluster, step_rad)
    return min(fits, key=lambda candidate: candidate.rms_m).footprint


def to_vehicle(footprint: Footprint, cluster: Cluster, scan: Scan, params: ClusterParams) -> Obstacle:
    """The sensor-frame footprint as a vehicle-frame Obstacle. ``range_m`` is the distance from
    the vehicle origin to the nearest return; ``height_m`` is the scan-plane height, a lower
    bound (a planar lidar cannot see how tall something is, only that it reaches the plane)."""
    mount = scan.mount
    centre = mount.to_vehicle(np.array([[footprint.x_m, footprint.y_m]]))[0]
    points = mount.to_vehicle(cluster.points)
    # A round footprint's square is sent square to the vehicle: lanes past it run along the
    # vehicle's x axis, and a square turned by theta reaches r (cos theta + sin theta) across them
    # (the two lidars' squares, at their +-15 deg mounts and fused together, reached 0.13 m beyond
    # a shrub's radius each side; turned to face the lidar close beside one, 0.25 m).
    turned = 0.0 if footprint.round else footprint.yaw_rad + mount.yaw_rad
    yaw, length, width = _normalise(turned, footprint.length_m, footprint.width_m)
    return Obstacle(
        x_m=float(centre[0]),
        y_m=float(centre[1]),
        length_m=float(length),
        width_m=float(width),
        height_m=float(mount.z_m),
        yaw_rad=float(yaw),
        confidence=float(1.0 - math.exp(-len(points) / params.confidence_points)),
        range_m=float(np.hypot(points[:, 0], points[:, 1]).min()),
    )


def _normalise(yaw: float, length: float, width: float) -> tuple[float, float, float]:
    """A rectangle has four equivalent (yaw, length, width); report the one with yaw in
    [-pi/4, pi/4), so length is the extent nearest to the vehicle's x axis."""
    quarter = math.floor((yaw + math.pi / 4) / (math.pi / 2))
    yaw -= quarter * math.pi / 2
    if quarter % 2:
        length, width = width, length
    return yaw, length, width


def _compact(cluster: Cluster, step_rad: float) -> Footprint:
    """Centre on the middle bearing, pushed back from the nearest return by half the lateral
    extent; returned as a square that size. Exact for a circle or a square seen from afar (their
    centre lies half their silhouette's width behind their nearest point), whatever the square's
    orientation, so it needs no shape fit."""
    middle = (cluster.bearings_rad[0] + cluster.bearings_rad[-1]) / 2
    u = np.array((math.cos(middle), math.sin(middle)))
    v = np.array((-u[1], u[0]))
    along, lateral = cluster.points @ u, cluster.points @ v
    # Each silhouette edge lies between the outermost return and the next ray: half a spacing out.
    size = float(lateral.max() - lateral.min() + cluster.ranges_m.mean() * step_rad)
    centre = (along.min() + size / 2) * u + (lateral.max() + lateral.min()) / 2 * v
    return Footprint(float(centre[0]), float(centre[1]), size, size, 0.0, round=True)


def _circle(cluster: Cluster) -> _Fit | None:
    """Least-squares circle and its RMS residual, or None when the fit is not a plausible
    cylinder: a radius larger than the visible chord (the points are nearly straight: a face), or
    a centre in front of the points (a concave arc). The algebraic (Kasa) fit, solved in closed
    form about the points' mean: its bias on short noisy arcs does not matter here, because a
    cylinder shows the lidar nearly half its circumference (over 3,000 simulated cylinders,
    Gauss-Newton refinement moved 99% of the centres by less than 1 cm, none by more than 2 cm)."""
    points = cluster.points
    n = len(points)
    mean = points.sum(axis=0) / n
    u, v = points[:, 0] - mean[0], points[:, 1] - mean[1]
    suu, svv, suv = float(u @ u), float(v @ v), float(u @ v)
    uu, vv = u * u, v * v
    det = suu * svv - suv * suv
    if det <= 1e-12:
        return None
    cu_rhs, cv_rhs = 0.5 * float(u @ uu + u @ vv), 0.5 * float(v @ vv + v @ uu)
    centre = mean + np.array(((svv * cu_rhs - suv * cv_rhs) / det, (suu * cv_rhs - suv * cu_rhs) / det))
    squared = ((points - centre) ** 2).sum(axis=1)
    radius = math.sqrt(float(squared.sum()) / n)
    residual = np.sqrt(squared) - radius
    chord = math.dist(points[0], points[-1])
    if not 0 < radius <= chord or math.hypot(*centre) <= cluster.ranges_m.min():
        return None
    footprint = Footprint(float(centre[0]), float(centre[1]), 2 * radius, 2 * radius, 0.0, round=True)
    return _Fit(footprint, math.sqrt(float(residual @ residual) / n))


def _rectangle(cluster: Cluster, step_rad: float, params: ClusterParams) -> _Fit | None:
    """Oriented rectangle from an L-shape fit, and the RMS distance of the points to its fitted
    faces; None when the points surround the sensor (no rectangle seen from outside fits).
    The near faces are where the points are; where each face ends is bounded by its outermost
    return and by the first ray past the cluster, which found nothing (see :func:`_face_length`)."""
    points = cluster.points
    e1, e2, rms, straight = _l_shape_axes(points, params)
    a, b = points @ e1, points @ e2
    a_side, a_near, a_far = _faces(a)
    b_side, b_near, b_far = _faces(b)
    if a_side == 0 and b_side == 0:
        return None
    first, last = float(cluster.bearings_rad[0]), float(cluster.bearings_rad[-1])
    spacing = float(cluster.ranges_m.mean() * step_rad)
    if a_side == 0 or b_side == 0:
        # The sensor sits in front of one face, the only one visible: both its ends are
        # silhouette ends, and the depth behind it is assumed.
        if a_side == 0:
            axis, normal, span, depth_of, face, side = e1, e2, a, b, b_near, b_side
        else:
            axis, normal, span, depth_of, face, side = e2, e1, b, a, a_near, a_side
        out = 1.0 if span[0] > span[-1] else -1.0  # away from the face, past its first return
        ends = (
            span[0] + out * _face_length(first, -step_rad, (normal, face), axis, span[0], out, 0.0, spacing, params),
            span[-1] - out * _face_length(last, step_rad, (normal, face), axis, span[-1], -out, 0.0, spacing, params),
        )
        start, stop = float(min(ends)), float(max(ends))
        depth = max(float(np.ptp(depth_of)), min(stop - start, params.assumed_depth_max_m))
        centre = (start + stop) / 2 * axis + (face + side * depth / 2) * normal
        along, across = (stop - start, depth) if a_side == 0 else (depth, stop - start)
    else:
        # The sensor faces a corner and sees the two faces meeting there: face B (on b = b_near,
        # running along e1) ends at one silhouette ray, face A (on a = a_near) at the other.
        measured_a, measured_b = abs(a_far - a_near), abs(b_far - b_near)
        assumed = min(max(measured_a, measured_b), params.assumed_depth_max_m)
        b_ends_last = a_side * a[-1] > a_side * a[0]
        b_ray, a_ray = ((last, step_rad), (first, -step_rad)) if b_ends_last else ((first, -step_rad), (last, step_rad))
        # A face with fewer than two returns has no line of its own (it is drawn through the other
        # face's last return), so the empty ray says nothing reliable about its end.
        tolerance = params.face_tolerance_m
        along, across = max(measured_a, assumed), max(measured_b, assumed)
        if np.count_nonzero(np.abs(b - b_near) <= tolerance) >= 2:
            along = _face_length(*b_ray, (e2, b_near), e1, a_near, a_side, measured_a, spacing, params, assumed)
        if np.count_nonzero(np.abs(a - a_near) <= tolerance) >= 2:
            across = _face_length(*a_ray, (e1, a_near), e2, b_near, b_side, measured_b, spacing, params, assumed)
        centre = (a_near + a_side * along / 2) * e1 + (b_near + b_side * across / 2) * e2
    yaw = math.atan2(e1[1], e1[0])
    footprint = Footprint(float(centre[0]), float(centre[1]), float(along), float(across), yaw)
    return _Fit(footprint, rms, straight)


def _face_length(
    edge_bearing: float,
    step_rad: float,
    line: tuple[np.ndarray, float],
    axis: np.ndarray,
    start: float,
    side: float,
    measured: float,
    spacing: float,
    params: ClusterParams,
    assumed: float = 0.0,
) -> float:
    """Length of a visible face on ``line`` (normal, offset) from ``start`` along ``side * axis``.
    Its end lies between its outermost return (at ``measured``) and where the first empty ray,
    one step past the cluster's edge bearing, crosses its line. When that interval is short the
    half-way ray splits it; when the face grazes the rays the interval is long and the crossing
    hypersensitive to the fitted line, so ``assumed`` is used, kept inside the interval."""
    normal, offset = line
    missed = max(_reach(edge_bearing + step_rad, normal, offset, axis, start, side), measured)
    if missed - measured <= params.end_uncertainty_spacings * spacing:
        return _clamp(_reach(edge_bearing + step_rad / 2, normal, offset, axis, start, side), measured, missed)
    return _clamp(assumed, measured, missed)


def _l_shape_axes(points: np.ndarray, params: ClusterParams) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """Rectangle axes (e1, e2) of the points, the RMS distance of the points to the fitted face
    lines, and whether they are one straight face: all within ``face_tolerance_m`` of a line;
    else two perpendicular faces, points[:k] and points[k:] (the corner itself lies between two
    returns). For a split, the normal n of face 1 minimises n' (S1 + R' S2 R) n, where S are the
    faces' scatter matrices and R turns face 2's normal into face 1's; the minimum (the smallest
    eigenvalue) is the sum of squared distances, and the split is the k that minimises it."""
    centred = points - points.sum(axis=0) / len(points)
    x, y = centred[:, 0], centred[:, 1]
    direction, squares = _principal(float(x @ x), float(x @ y), float(y @ y))
    normal = np.array((-direction[1], direction[0]))
    straight = len(points) < 3 or float(np.abs(centred @ normal).max()) <= params.face_tolerance_m
    if not straight:
        direction, squares = _best_corner(x, y)
        normal = np.array((-direction[1], direction[0]))
    return direction, normal, math.sqrt(max(squares, 0.0) / len(points)), straight


def _best_corner(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float]:
    """Over every split k in [1, n-1]: face 1's direction for the split with the smallest joint
    residual, and that residual (a sum of squares). Prefix sums give every split's scatter
    matrices at once."""
    n = len(x)
    moments = np.empty((n + 1, 6))
    moments[0] = 0.0
    np.cumsum(np.column_stack((np.ones(n), x, y, x * x, x * y, y * y)), axis=0, out=moments[1:])
    k = np.arange(1, n)
    h_xx, h_xy, h_yy = _centred_moments(moments[k])  # points[:k]
    t_xx, t_xy, t_yy = _centred_moments(moments[n] - moments[k])  # points[k:]
    # S1 + R' S2 R, with R' [[xx, xy], [xy, yy]] R = [[yy, -xy], [-xy, xx]].
    p, q, r = h_xx + t_yy, h_xy - t_xy, h_yy + t_xx
    smallest = (p + r) / 2 - np.sqrt(((p - r) / 2) ** 2 + q**2)
    best = int(np.argmin(smallest))
    return _principal(float(p[best]), float(q[best]), float(r[best]))


def _principal(xx: float, xy: float, yy: float) -> tuple[np.ndarray, float]:
    """Major axis of the symmetric matrix [[xx, xy], [xy, yy]] and its smallest eigenvalue."""
    angle = 0.5 * math.atan2(2 * xy, xx - yy)
    smallest = (xx + yy) / 2 - math.hypot((xx - yy) / 2, xy)
    return np.array((math.cos(angle), math.sin(angle))), smallest


def _centred_moments(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(xx, xy, yy) scatter about the mean from rows of (count, x, y, xx, xy, yy) sums."""
    count, sx, sy, sxx, sxy, syy = sums.T
    return sxx - sx * sx / count, sxy - sx * sy / count, syy - sy * sy / count


def _faces(coordinates: np.ndarray) -> tuple[int, float, float]:
    """Along one axis (sensor at 0): which way the object extends from its near face (+1, -1, or
    0 when the sensor is level with the object, seeing only faces of the other axis), the near
    face's coordinate and the farthest point's."""
    low, high = float(coordinates.min()), float(coordinates.max())
    if low > 0:
        return 1, low, high
    if high < 0:
        return -1, high, low
    return 0, 0.0, 0.0


def _reach(bearing: float, normal: np.ndarray, offset: float, axis: np.ndarray, start: float, side: float) -> float:
    """How far along ``axis`` (in direction ``side`` from ``start``) the ray from the sensor at
    ``bearing`` meets the line ``p @ normal == offset``; inf when it never meets it ahead."""
    # Scalar arithmetic: on two-vectors it is several times faster than numpy's.
    dx, dy = math.cos(bearing), math.sin(bearing)
    dot = dx * float(normal[0]) + dy * float(normal[1])
    if abs(dot) < 1e-9 or offset / dot <= 0:
        return math.inf
    return side * (offset / dot * (dx * float(axis[0]) + dy * float(axis[1])) - start)


def _clamp(value: float, low: float, high: float) -> float:
    return max(low, min(high, value))
