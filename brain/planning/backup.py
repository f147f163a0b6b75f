"""Backing up: the way out of a standing place the forward planner cannot leave.

The vehicle's own recent positions while it drove forwards are known drivable: it came from
there. A back-up path runs from where the vehicle stands back along that trail, newest first, for
a few metres; where the trail runs out (a vehicle that has not driven yet), straight on behind it
in the direction the trail last went, or behind the vehicle. Every point keeps the footprint's
half width plus a margin inside the corridor, and the straight part also clear of every hazard
cell the map knows of. The path is driven backwards (Path.reverse) slowly, ending at rest.

Sans-IO: the brain adds a position each planning cycle while driving forwards and asks for a
path when its stall watch says to back up.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

TRAIL_SPACING_M = 0.25
TRAIL_KEPT_M = 30.0
MIN_BACK_UP_M = 1.0  # a shorter way back is not worth the gear changes


@dataclass(frozen=True)
class BackUpSettings:
    length_m: float = 4.0
    speed_mps: float = 1.0
    clearance_m: float = 0.9  # rear axle to the corridor's edge: the rear corners (0.72 m) plus a margin
    # Along the trail, what the vehicle kept driving it forwards (the planner's corridor clearance):
    # backing over the same track sweeps the same ground. A vehicle that crept along a corridor's
    # edge to a dead end must be able to back out the way it came.
    trail_clearance_m: float = 0.7


@dataclass(frozen=True)
class BackUp:
    """A way back: its points in the order of travel (the vehicle's position first), and how many
    trail positions it runs over (the trail ends where the back-up does)."""

    points: tuple[tuple[float, float], ...]
    trail_used: int

    @property
    def length_m(self) -> float:
        xy = np.asarray(self.points)
        return float(np.hypot(*np.diff(xy, axis=0).T).sum())

    def speeds(self, speed_mps: float) -> tuple[float, ...]:
        return (speed_mps,) * (len(self.points) - 1) + (0.0,)


class Trail:
    """Where the vehicle's rear axle has been while driving forwards, a point every ``spacing_m``."""

    def __init__(self, spacing_m: float = TRAIL_SPACING_M, kept_m: float = TRAIL_KEPT_M) -> None:
        self.spacing_m = spacing_m
        self.points: deque[tuple[float, float]] = deque(maxlen=max(2, round(kept_m / spacing_m)))

    def add(self, east_m: float, north_m: float) -> None:
        if self.points:
            last_east, last_north = self.points[-1]
            if math.hypot(east_m - last_east, north_m - last_north) < self.spacing_m:
                return
        self.points.append((east_m, north_m))

    def drop_newest(self, count: int) -> None:
        """Forget the newest ``count`` positions: the vehicle backed up over them."""
        for _ in range(min(count, len(self.points))):
            self.points.pop()


Test = Callable[[FloatArray, FloatArray], NDArray[np.bool_]]
Distance = Callable[[FloatArray, FloatArray], FloatArray]


def back_up(
    trail: Trail,
    east_m: float,
    north_m: float,
    yaw_rad: float,
    to_edge: Distance,
    free: Test,
    settings: BackUpSettings,
) -> BackUp | None:
    """The way back from the pose, or None if there is less than MIN_BACK_UP_M of it.
    ``to_edge(e, n)``: the points' distance inside the corridor's edge, which must be the trail
    clearance on the trail and the clearance beyond it; ``free(e, n)``: the map shows no hazard
    around them (asked only beyond the trail)."""
    points = [(east_m, north_m)]
    length = 0.0
    used = 0
    trail_xy = np.array(list(reversed(trail.points)), dtype=float).reshape(-1, 2)
    on_trail = to_edge(trail_xy[:, 0], trail_xy[:, 1]) >= settings.trail_clearance_m
    for (east, north), ok in zip(trail_xy, on_trail, strict=True):
        if length >= settings.length_m or not ok:
            break
        used += 1
        step = math.hypot(east - points[-1][0], north - points[-1][1])
        if step < 0.5 * trail.spacing_m:
            continue  # the vehicle stands on it
        points.append((float(east), float(north)))
        length += step
    if length < settings.length_m and used == len(trail_xy):

        def inside(east: FloatArray, north: FloatArray) -> NDArray[np.bool_]:
            return to_edge(east, north) >= settings.clearance_m

        length += _straight_on(points, yaw_rad, settings.length_m - length, trail.spacing_m, inside, free)
    if length < MIN_BACK_UP_M:
        return None
    return BackUp(tuple(points), used)


def _straight_on(
    points: list[tuple[float, float]], yaw_rad: float, wanted_m: float, spacing_m: float, inside: Test, free: Test
) -> float:
    """Extend ``points`` straight back (the way they last went, else behind the vehicle) as far as
    every point on the way is inside and free; the length added."""
    if len(points) >= 2:
        heading = math.atan2(points[-1][1] - points[-2][1], points[-1][0] - points[-2][0])
    else:
        heading = yaw_rad + math.pi
    steps = np.minimum(np.arange(1, math.ceil(wanted_m / spacing_m - 1e-9) + 1) * spacing_m, wanted_m)
    east = points[-1][0] + steps * math.cos(heading)
    north = points[-1][1] + steps * math.sin(heading)
    ok = inside(east, north) & free(east, north)
    count = len(ok) if ok.all() else int(np.argmin(ok))
    points.extend(zip(east[:count].tolist(), north[:count].tolist(), strict=True))
    return float(steps[count - 1]) if count else 0.0
