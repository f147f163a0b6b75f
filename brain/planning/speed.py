"""Target speeds along a planned path: the lowest of every cap, then acceleration and braking limits.

Caps per point: the course's desired speed (RDDF limit, its own curvature and its end, from
`CoursePath.speed_mps`), the path's own curvature (lateral acceleration limit), clearance to
caution cells, the footprint cost there, the steering rate, the health monitor's limit, and
slow mode or a searched path's top speed. Then the
profile is made reachable: forwards from the current speed with the acceleration limit and
backwards with the braking limit, ending at ``final_speed_mps``. With v^2 running over arc
length, each pass is a running minimum of ``cap^2 -/+ 2 a s`` and is exact for uneven spacing.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def arc_length(points: FloatArray) -> FloatArray:
    """Distance along the polyline at each of its points (N x 2 -> N)."""
    step = np.diff(np.asarray(points, dtype=float).reshape(-1, 2), axis=0)
    return np.concatenate([[0.0], np.cumsum(np.hypot(step[:, 0], step[:, 1]))])


def curvature(points: FloatArray, window_m: float, signed: bool = False) -> FloatArray:
    """Turning per metre at each point (unsigned, or positive to the left when ``signed``), over
    the vertices within ``window_m`` of path.

    Turning happens at vertices; the turn of the vertices in the window is divided by the path
    they stand for (half of each neighbouring segment), or by the window when that is shorter:
    densely sampled curves come out exact and a shortcut's corner (all its turn at one vertex
    between long segments) is spread over no more than the window.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(points) < 3:
        return np.zeros(len(points))
    step = np.diff(points, axis=0)
    heading = np.arctan2(step[:, 1], step[:, 0])
    turn = np.zeros(len(points))
    turn[1:-1] = np.angle(np.exp(1j * np.diff(heading)))
    if not signed:
        turn = np.abs(turn)
    length = np.hypot(step[:, 0], step[:, 1])
    share = (np.append(length, 0.0) + np.insert(length, 0, 0.0)) / 2.0
    along = arc_length(points)
    total_turn = np.concatenate([[0.0], np.cumsum(turn)])
    total_share = np.concatenate([[0.0], np.cumsum(share)])
    low = np.searchsorted(along, along - window_m / 2.0, side="left")
    high = np.searchsorted(along, along + window_m / 2.0, side="right")
    span = np.minimum(total_share[high] - total_share[low], window_m)
    return (total_turn[high] - total_turn[low]) / np.maximum(span, 1e-9)


def steering_rate_cap(
    points: FloatArray, window_m: float, wheelbase_m: float, max_steering_rate_radps: float
) -> FloatArray:
    """Speed at each point at which the steering keeps up with the path: its wheel angle
    atan(wheelbase x curvature) changes by d/ds per metre, so by d/ds x v per second, and the
    actuator turns at most ``max_steering_rate_radps`` (a searched path swings from lock to lock)."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(points) < 3:
        return np.full(len(points), np.inf)
    wheel = np.arctan(wheelbase_m * curvature(points, window_m, signed=True))
    along = np.concatenate([[0.0], np.cumsum(np.maximum(np.diff(arc_length(points)), 1e-6))])
    # Within half a window of either end the curvature is averaged over part of a window: hold
    # the angle there instead, or a path that starts on a curve would seem to swing into it.
    inner = (along >= window_m / 2) & (along <= along[-1] - window_m / 2)
    if inner.any():
        wheel = np.interp(along, along[inner], wheel[inner])
    with np.errstate(divide="ignore"):
        return max_steering_rate_radps / np.abs(np.gradient(wheel, along))


def clearance_cap(clearance_m: FloatArray, least_m: float, speed_at_least_mps: float, gain: float) -> FloatArray:
    """Speed allowed at each clearance to a caution cell: ``speed_at_least`` at ``least_m``,
    ``gain`` m/s more per metre beyond (inf clearance: no cap)."""
    with np.errstate(invalid="ignore"):
        return speed_at_least_mps + gain * np.maximum(np.asarray(clearance_m, dtype=float) - least_m, 0.0)


def reachable(
    along_m: FloatArray,
    cap_mps: FloatArray,
    start_speed_mps: float,
    final_speed_mps: float,
    max_accel_mps2: float,
    max_decel_mps2: float,
) -> FloatArray:
    """The highest speeds under ``cap_mps`` that start at most at ``start_speed_mps`` (accelerating
    from it within the limit), brake within the limit for every lower cap ahead, and end at no
    more than ``final_speed_mps``. ``cap_mps`` may hold several profiles along its last axis."""
    along = np.asarray(along_m, dtype=float)
    cap = np.array(cap_mps, dtype=float)
    if cap.shape[-1] == 0:
        return cap
    if np.any(np.diff(along) < 0.0):
        raise ValueError("arc lengths must not decrease")
    cap[..., 0] = np.minimum(cap[..., 0], start_speed_mps)
    cap[..., -1] = np.minimum(cap[..., -1], final_speed_mps)
    squared = np.maximum(cap, 0.0) ** 2
    ramp = 2.0 * max_accel_mps2 * along
    squared = np.minimum.accumulate(squared - ramp, axis=-1) + ramp
    back = 2.0 * max_decel_mps2 * (along[-1] - along)
    squared = np.flip(np.minimum.accumulate(np.flip(squared - back, -1), axis=-1), -1) + back
    # The running sums round; the caps themselves are exact, so hold to them.
    return np.minimum(np.sqrt(np.maximum(squared, 0.0)), np.maximum(cap, 0.0))


def travel_time_s(along_m: FloatArray, speed_mps: FloatArray, floor_mps: float = 0.5) -> FloatArray:
    """Time to drive the profile(s) ``speed_mps`` (last axis along ``along_m``), accelerating
    evenly between points; speeds below ``floor_mps`` count as it (a stop is not forever)."""
    mean = np.maximum((speed_mps[..., 1:] + speed_mps[..., :-1]) / 2.0, floor_mps)
    return np.sum(np.diff(np.asarray(along_m, dtype=float)) / mean, axis=-1)
