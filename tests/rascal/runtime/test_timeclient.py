"""The time client over a real loopback bus: it asks at its callers' rate until the estimate has
settled, then twice a second, and stays synced."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from protocol.auth import load_keyring
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock, SharedClock
from rascal.runtime.timeclient import SETTLED_REQUEST_PERIOD_NS, TimeClient, TimeMaster
from rascal.runtime.timesync import SyncState

CALL_PERIOD_S = 0.1  # as Runtime calls request()
SETTLE_LIMIT_S = 10.0
WATCH_S = 2.5  # after settling


def test_requests_slow_down_once_the_estimate_settles_and_it_stays_synced(bus_url: str, key_file: Path) -> None:
    keyring = load_keyring(key_file)
    master_bus = Bus.open(bus_url, source_id=1, clock=MasterClock(), keyring=keyring)
    clock = SharedClock()
    client_bus = Bus.open(bus_url, source_id=7, clock=clock, keyring=keyring)
    master, client = TimeMaster(master_bus), TimeClient(client_bus, clock)
    answered_at: list[float] = []
    try:
        start = time.monotonic()
        settled_at = None
        # Until settled (a loaded machine may take longer than the 0.8 s of eight calls), then on.
        while time.monotonic() - start < (SETTLE_LIMIT_S if settled_at is None else settled_at + WATCH_S):
            before = master.answered
            client.request()
            end = time.monotonic() + CALL_PERIOD_S
            while time.monotonic() < end:
                master_bus.poll(0.005)
                client_bus.poll(0.005)
            answered_at += [time.monotonic() - start] * (master.answered - before)
            if settled_at is None and client.settled(clock.local_ns()):
                settled_at = time.monotonic() - start
        status = clock.estimator.status(clock.local_ns())
    finally:
        master_bus.close()
        client_bus.close()
    assert settled_at is not None, f"not settled within {SETTLE_LIMIT_S} s: {status}"
    before_settling = [t for t in answered_at if t <= settled_at]
    after_settling = [t for t in answered_at if t > settled_at + 0.2]
    assert len(before_settling) >= 8  # every call, until a full step window agreed
    calls_after = (WATCH_S - 0.2) / CALL_PERIOD_S
    slow_share = CALL_PERIOD_S / (SETTLED_REQUEST_PERIOD_NS / 1e9)
    assert len(after_settling) <= calls_after * slow_share + 1, answered_at
    assert status.state == SyncState.SYNCED and status.error_bound_ns < 1_000_000, status


def test_a_client_restarted_with_its_wall_clock_stepped_back_synchronises_at_once(
    bus_url: str, key_file: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Its sequence numbers (wall-clock based) now lie 10 s behind the master's replay window,
    and an unsynchronised client cannot pass a freshness test: TIME_SYNC has no window, so the
    master still answers and the client synchronises within a second (SPEC.md section 10)."""
    keys = load_keyring(key_file)
    master_bus = Bus.open(bus_url, source_id=1, clock=MasterClock(), keyring=keys)
    TimeMaster(master_bus)

    def sync(clock: SharedClock, client: TimeClient, timeout_s: float) -> float:
        start = time.monotonic()
        while not clock.synced and time.monotonic() - start < timeout_s:
            client.request()
            for bus in (master_bus, client.bus):
                bus.poll(0.01)
        return time.monotonic() - start

    first_clock = SharedClock()
    first = Bus.open(bus_url, source_id=12, clock=first_clock, keyring=keys)
    assert sync(first_clock, TimeClient(first, first_clock), 5.0) < 5.0
    first.close()
    stepped_back_ns = time.time_ns() - 10_000_000_000
    with monkeypatch.context() as patch:
        patch.setattr(time, "time_ns", lambda: stepped_back_ns)
        clock = SharedClock()
        restarted = Bus.open(bus_url, source_id=12, clock=clock, keyring=keys)
    assert sync(clock, TimeClient(restarted, clock), 2.0) < 1.0
    assert not master_bus.rejects
    for bus in (master_bus, restarted):
        bus.close()
