"""Standing still before the finish: noticed, named, and acted on.

A vehicle that stops short of the finish is either blocked (the planner finds nothing reachable
ahead: a wall across the corridor) or stalled (the planner has a way, yet the vehicle stands: a
path it cannot start along, a search that keeps ending at its own nose). Neither may go unsaid:
a blocked corridor is reported within ``blocked_after_s`` of stopping, and a stall after
``stall_after_s`` starts a recovery (the planner forgets its path and plans afresh from the
standing pose), repeated every ``stall_after_s`` while it lasts. Where the brain has a way back
(``can_back_up``), standing that long blocked, or still stalled after a re-plan, backs the
vehicle up instead (then it plans afresh from there): at most BACKUPS_PER_PLACE times around one
standing place, so a dead end cannot make it shuttle for ever. Standing on the operator's order,
or at the finish, is neither.

Sans-IO: feed ``update`` once a planning cycle; it returns the events to report.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from protocol.messages import Path, Severity

STANDING_MPS = 0.1  # the stall: below 0.1 m/s
MOVING_M = 1.0  # driven this far from where it stood: moving again
BACKUPS_PER_PLACE = 3
PLACE_M = 8.0  # stands this close to where a back-up started are the same place (a back-up is 6 m)


def leads_on(path: Path, east_m: float, north_m: float) -> bool:
    """Whether ``path`` takes a vehicle standing at (east, north) anywhere: on from its point
    nearest the vehicle, it reaches MOVING_M away and asks for a speed on the way. A path that
    ends at the nose (a partial candidate or a kept path run out against a wall) is no way ahead,
    whatever mode made it."""
    points = path.points
    away = [math.hypot(point.east_m - east_m, point.north_m - north_m) for point in points]
    nearest = min(range(len(points)), key=away.__getitem__, default=0)
    for k in range(nearest, len(points)):
        if away[k] >= MOVING_M:
            return any(point.speed_mps >= STANDING_MPS for point in points[nearest:k])
    return False


class Standing(enum.Enum):
    MOVING = "moving"
    STANDING = "standing"  # not yet long enough to say why
    BLOCKED = "blocked"
    STALLED = "stalled"
    BACKING = "backing"  # backing up: the brain says when it is done


@dataclass(frozen=True)
class StallEvent:
    severity: Severity
    code: str
    text: str
    recover: bool = False  # the brain should make the planner start afresh
    back_up: bool = False  # ... after backing up


class StallWatch:
    """Watches speed and station each cycle against what the planner says."""

    def __init__(self, finish_m: float, blocked_after_s: float = 3.0, stall_after_s: float = 5.0) -> None:
        if not (blocked_after_s > 0 and stall_after_s > 0):
            raise ValueError("stall watch: the delays must be positive")
        self.finish_m = finish_m
        self.blocked_after_s = blocked_after_s
        self.stall_after_s = stall_after_s
        self.state = Standing.MOVING
        self.recoveries = 0
        self._since_ns = 0  # when it stood still
        self._station_m = 0.0  # where it stood
        self._last_recovery_ns = 0
        self._places: list[tuple[float, int]] = []  # (station, back-ups) of the places backed up from

    def update(
        self,
        now_ns: int,
        speed_mps: float,
        station_m: float,
        way_ahead: bool,
        held_by_operator: bool,
        can_back_up: bool = False,
    ) -> list[StallEvent]:
        """One cycle: the vehicle's speed (a magnitude: backing is moving) and station, whether the
        planner has a path that goes anywhere (``way_ahead``), whether the operator holds it, and
        whether the brain has a way back."""
        if self.state is Standing.BACKING:
            return []
        standing = speed_mps < STANDING_MPS and not held_by_operator and station_m < self.finish_m
        if self.state is Standing.MOVING:
            if standing:
                self.state, self._since_ns, self._station_m = Standing.STANDING, now_ns, station_m
            return []
        if not standing or abs(station_m - self._station_m) > MOVING_M:
            return self._moving_again(now_ns, station_m)
        stood_s = (now_ns - self._since_ns) / 1e9
        if not way_ahead and stood_s >= self.blocked_after_s and self.state is not Standing.BLOCKED:
            self.state = Standing.BLOCKED
            text = f"corridor blocked at s={station_m:.0f} m: nothing reachable ahead; standing for {stood_s:.0f} s"
            return [StallEvent(Severity.CRITICAL, "corridor_blocked", text)]
        if stood_s < self.stall_after_s or (now_ns - self._last_recovery_ns) / 1e9 < self.stall_after_s:
            return []
        if can_back_up and (not way_ahead or self.state is Standing.STALLED) and self._back_up_allowed(station_m):
            return [self._back_up(now_ns, station_m, stood_s)]
        if way_ahead:
            self.state, self._last_recovery_ns = Standing.STALLED, now_ns
            self.recoveries += 1
            text = (
                f"standing for {stood_s:.0f} s at s={station_m:.0f} m with a way ahead: "
                f"recovery {self.recoveries}, planning afresh from here"
            )
            return [StallEvent(Severity.WARNING, "stalled", text, recover=True)]
        return []

    def backed_up(self) -> None:
        """The back-up is over: what comes next is judged afresh."""
        self.state = Standing.MOVING

    def _place(self, station_m: float) -> int | None:
        """The index of the place backed up from that ``station_m`` is part of, if any."""
        return next((k for k, (place, _count) in enumerate(self._places) if abs(station_m - place) <= PLACE_M), None)

    def _back_up_allowed(self, station_m: float) -> bool:
        index = self._place(station_m)
        return index is None or self._places[index][1] < BACKUPS_PER_PLACE

    def _back_up(self, now_ns: int, station_m: float, stood_s: float) -> StallEvent:
        index = self._place(station_m)
        if index is None:
            self._places.append((station_m, 0))
            index = len(self._places) - 1
        place, count = self._places[index]
        count += 1
        self._places[index] = (place, count)
        was, self.state, self._last_recovery_ns = self.state, Standing.BACKING, now_ns
        self.recoveries += 1
        text = (
            f"standing for {stood_s:.0f} s at s={station_m:.0f} m ({was.value}): backing up, "
            f"{count} of {BACKUPS_PER_PLACE} here, then planning afresh"
        )
        return StallEvent(Severity.WARNING, "backing_up", text, recover=True, back_up=True)

    def _moving_again(self, now_ns: int, station_m: float) -> list[StallEvent]:
        was, stood_s = self.state, (now_ns - self._since_ns) / 1e9
        self.state = Standing.MOVING
        if was in (Standing.BLOCKED, Standing.STALLED):
            text = f"moving again at s={station_m:.0f} m after standing {stood_s:.0f} s ({was.value})"
            return [StallEvent(Severity.INFO, "moving_again", text)]
        return []
