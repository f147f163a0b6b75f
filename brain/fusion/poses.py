"""Pose history: where the vehicle was at any recent ``t_meas_ns``.

Each descriptor is placed with the vehicle pose at its own measurement time, not the newest pose:
at 10 m/s a lidar message 50 ms older than the newest pose would otherwise land half a metre off.
Navigation states are kept in time order; a lookup interpolates between the two that bracket the
time (position linearly, yaw along the shorter arc), and extrapolates with the nearest state's
velocity and yaw rate by at most ``max_extrapolation_ns``. Anything further out is refused and
counted, so a stale or future-stamped message is an explicit outcome, never a silently wrong pose.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from typing import NamedTuple

from brain.pose import Pose
from protocol.messages import NavQuality, VehicleState
from rascal.runtime.angles import wrap_angle

COVARIANCE_SIZE = 25  # VehicleState.covariance: row-major 5x5 over east, north, yaw, speed, yaw rate
YAW_VARIANCE_AT = 12
MAX_OFFSET_M = 1e7  # a local ENU position beyond 10,000 km from the origin is garbage, not a place


def heading_std_rad(state: VehicleState) -> float:
    """The state's claimed heading uncertainty; 0 (taken as exact) when its covariance is not the
    5x5 of finite numbers the message defines, so a navigator that leaves it out changes nothing."""
    covariance = state.covariance
    if len(covariance) != COVARIANCE_SIZE or not all(map(math.isfinite, covariance)):
        return 0.0
    return math.sqrt(max(covariance[YAW_VARIANCE_AT], 0.0))


@dataclass
class PoseStats:
    """What the history did with states and lookups, for a heartbeat's detail line."""

    added: int = 0
    invalid: int = 0  # states with NavQuality.INVALID or non-finite fields, not stored
    stale: int = 0  # states older than the span kept, not stored
    interpolated: int = 0
    extrapolated: int = 0
    too_old: int = 0  # lookups before the oldest state by more than the extrapolation limit
    too_new: int = 0  # lookups after the newest state by more than the extrapolation limit
    empty: int = 0  # lookups with no state at all


class _Entry(NamedTuple):
    east_m: float
    north_m: float
    yaw_rad: float
    vel_east_mps: float
    vel_north_mps: float
    yaw_rate_radps: float


class PoseHistory:
    """Navigation states keyed by ``t_meas_ns``, the newest ``span_ns`` of them kept."""

    def __init__(self, span_ns: int = 3_000_000_000, max_extrapolation_ns: int = 100_000_000) -> None:
        if span_ns <= 0 or max_extrapolation_ns < 0:
            raise ValueError("pose history needs a positive span and a non-negative extrapolation limit")
        self.span_ns = span_ns
        self.max_extrapolation_ns = max_extrapolation_ns
        self.stats = PoseStats()
        self._times: list[int] = []
        self._entries: list[_Entry] = []

    def __len__(self) -> int:
        return len(self._times)

    @property
    def newest_ns(self) -> int | None:
        return self._times[-1] if self._times else None

    @property
    def oldest_ns(self) -> int | None:
        return self._times[0] if self._times else None

    def newest(self) -> Pose | None:
        if not self._entries:
            return None
        entry = self._entries[-1]
        return Pose(entry.east_m, entry.north_m, entry.yaw_rad)

    def add(self, t_meas_ns: int, state: VehicleState) -> bool:
        """Store a navigation state; False (and counted) when it is unusable or older than the
        span kept. A state older than the newest is inserted in order; one with the same time
        replaces the stored one."""
        fields = (state.east_m, state.north_m, state.yaw_rad, state.vel_east_mps, state.vel_north_mps)
        if (
            state.quality == NavQuality.INVALID
            or not all(math.isfinite(v) for v in (*fields, state.yaw_rate_radps))
            or max(abs(state.east_m), abs(state.north_m)) > MAX_OFFSET_M
        ):
            self.stats.invalid += 1
            return False
        if self._times and t_meas_ns < self._times[-1] - self.span_ns:
            self.stats.stale += 1
            return False
        entry = _Entry(*fields, state.yaw_rate_radps)
        index = bisect.bisect_left(self._times, t_meas_ns)
        if index < len(self._times) and self._times[index] == t_meas_ns:
            self._entries[index] = entry
        else:
            self._times.insert(index, t_meas_ns)
            self._entries.insert(index, entry)
        self.stats.added += 1
        self._trim()
        return True

    def at(self, t_meas_ns: int) -> Pose | None:
        """The pose at ``t_meas_ns``, or None (counted) when it lies outside the history by more
        than the extrapolation limit."""
        times = self._times
        if not times:
            self.stats.empty += 1
            return None
        if t_meas_ns > times[-1]:
            return self._extrapolate(-1, t_meas_ns, "too_new")
        if t_meas_ns < times[0]:
            return self._extrapolate(0, t_meas_ns, "too_old")
        index = bisect.bisect_left(times, t_meas_ns)
        after = self._entries[index]
        if times[index] == t_meas_ns:
            self.stats.interpolated += 1
            return Pose(after.east_m, after.north_m, after.yaw_rad)
        before = self._entries[index - 1]
        fraction = (t_meas_ns - times[index - 1]) / (times[index] - times[index - 1])
        self.stats.interpolated += 1
        return Pose(
            before.east_m + fraction * (after.east_m - before.east_m),
            before.north_m + fraction * (after.north_m - before.north_m),
            wrap_angle(before.yaw_rad + fraction * wrap_angle(after.yaw_rad - before.yaw_rad)),
        )

    def _extrapolate(self, index: int, t_meas_ns: int, refusal: str) -> Pose | None:
        dt_ns = t_meas_ns - self._times[index]
        if abs(dt_ns) > self.max_extrapolation_ns:
            setattr(self.stats, refusal, getattr(self.stats, refusal) + 1)
            return None
        entry = self._entries[index]
        dt = dt_ns * 1e-9
        self.stats.extrapolated += 1
        return Pose(
            entry.east_m + entry.vel_east_mps * dt,
            entry.north_m + entry.vel_north_mps * dt,
            wrap_angle(entry.yaw_rad + entry.yaw_rate_radps * dt),
        )

    def _trim(self) -> None:
        cutoff = self._times[-1] - self.span_ns
        drop = bisect.bisect_left(self._times, cutoff)
        if drop:
            del self._times[:drop]
            del self._entries[:drop]
