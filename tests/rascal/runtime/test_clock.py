"""The master's clock: real time at its start, then the monotonic clock, so a step of the host's
wall clock does not step shared time."""

from __future__ import annotations

import time

import pytest

from rascal.runtime.clock import MasterClock

MS = 1_000_000


def test_the_master_starts_at_real_time() -> None:
    clock = MasterClock()
    assert abs(clock.now_ns() - time.time_ns()) < 5 * MS
    assert clock.to_shared(123) == 123 and clock.synced


def test_a_wall_clock_step_on_the_master_host_does_not_step_shared_time(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = MasterClock()
    before = clock.now_ns()
    kernel_stamp_before = time.time_ns()  # a receive timestamp: CLOCK_REALTIME, as the kernel stamps
    local_before = clock.from_realtime(kernel_stamp_before)
    real_time_ns = time.time_ns
    monkeypatch.setattr(time, "time_ns", lambda: real_time_ns() + 5_000 * MS)  # NTP steps it 5 s on
    after = clock.now_ns()
    assert 0 <= after - before < 50 * MS
    # A datagram stamped by the kernel after the step lands where it arrived on shared time.
    kernel_stamp_after = time.time_ns()
    assert 0 <= clock.from_realtime(kernel_stamp_after) - local_before < 50 * MS
