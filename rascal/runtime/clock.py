"""Clocks. Logic never reads the system clock directly; it is handed one of these.

Every clock has a *local* timeline (what this process can read) and maps it to *shared* time,
the time service's timeline: int64 nanoseconds since the Unix epoch.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol

from rascal.runtime.timesync import TimeSyncEstimator


class Clock(Protocol):
    def now_ns(self) -> int:
        """Shared time now."""

    def local_ns(self) -> int:
        """This process's local time now (the input to time synchronisation)."""

    def to_shared(self, local_ns: int) -> int:
        """Convert a local timestamp taken earlier to shared time."""

    def from_realtime(self, realtime_ns: int) -> int:
        """Convert a CLOCK_REALTIME stamp (a kernel receive timestamp) to the local timeline."""

    @property
    def synced(self) -> bool:
        """Whether shared time is known well enough to judge other nodes' timestamps."""


class MonotonicLocal:
    """A local timeline immune to wall-clock steps, anchored near real time at start so that
    an unsynchronised node on the master's host is already close to shared time."""

    def __init__(self) -> None:
        self._anchor = time.time_ns() - time.monotonic_ns()

    def __call__(self) -> int:
        return time.monotonic_ns() + self._anchor


class MasterClock:
    """The time master's clock. Shared time is real time as read when the master started, carried
    on by the monotonic clock: NTP still disciplines its rate, but a step of the host's wall clock
    (NTP, or a VM's agent, setting it) does not step the whole fleet's time. Every client would
    first see that step as stale or future messages, and then take a step window to follow it."""

    synced = True

    def __init__(self) -> None:
        self._local = MonotonicLocal()

    def now_ns(self) -> int:
        return self._local()

    def local_ns(self) -> int:
        return self._local()

    def to_shared(self, local_ns: int) -> int:
        return local_ns

    def from_realtime(self, realtime_ns: int) -> int:
        return _realtime_to_local(realtime_ns, self._local)


class SkewedLocal:
    """A deliberately wrong local timeline (offset and drift) for tests and fault injection."""

    def __init__(self, offset_ns: int, drift_ppm: float, base: MonotonicLocal | None = None) -> None:
        self._base = base or MonotonicLocal()
        self._origin = self._base()
        self._offset_ns = offset_ns
        self._rate = 1.0 + drift_ppm * 1e-6

    def __call__(self) -> int:
        elapsed = self._base() - self._origin
        return self._origin + self._offset_ns + int(elapsed * self._rate)


class SharedClock:
    """A client's view of shared time: its local timeline corrected by a TimeSyncEstimator."""

    def __init__(
        self, estimator: TimeSyncEstimator | None = None, local: MonotonicLocal | SkewedLocal | None = None
    ) -> None:
        self.estimator = estimator or TimeSyncEstimator()
        self.local_ns = local or MonotonicLocal()

    def now_ns(self) -> int:
        return self.estimator.to_shared(self.local_ns())

    def to_shared(self, local_ns: int) -> int:
        return self.estimator.to_shared(local_ns)

    def from_realtime(self, realtime_ns: int) -> int:
        return _realtime_to_local(realtime_ns, self.local_ns)

    @property
    def synced(self) -> bool:
        return self.estimator.synced


class ManualClock:
    """A clock tests set by hand."""

    synced = True

    def __init__(self, t_ns: int = 1_700_000_000_000_000_000) -> None:
        self.t_ns = t_ns

    def now_ns(self) -> int:
        return self.t_ns

    def local_ns(self) -> int:
        return self.t_ns

    def to_shared(self, local_ns: int) -> int:
        return local_ns

    def from_realtime(self, realtime_ns: int) -> int:
        return realtime_ns

    def advance(self, dt_ns: int) -> None:
        self.t_ns += dt_ns


def _realtime_to_local(realtime_ns: int, local: Callable[[], int]) -> int:
    # The two timelines differ by a constant (or, skewed, slowly): read both now.
    return realtime_ns + local() - time.time_ns()
