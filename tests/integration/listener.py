"""A test's own presence on the bus: a synchronised clock, subscriptions, and a bounded wait."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from protocol.auth import load_keyring
from rascal.runtime.bus import Bus
from rascal.runtime.clock import SharedClock
from rascal.runtime.timeclient import TimeClient

TIME_REQUEST_PERIOD_S = 0.1


class Listener:
    """Opens the test's bus with a shared clock, keeps it synchronised while waiting, and runs
    periodic callbacks (e.g. a test's own publisher) between polls."""

    def __init__(self, bus_url: str, key_file: Path, source_id: int) -> None:
        self.clock = SharedClock()
        self.bus = Bus.open(bus_url, source_id=source_id, clock=self.clock, keyring=load_keyring(key_file))
        time_client = TimeClient(self.bus, self.clock)
        # (period, callback, [next due]): keeping the clock synchronised is the first of them.
        self._periodic: list[tuple[float, Callable[[], None], list[float]]] = [
            (TIME_REQUEST_PERIOD_S, time_client.request, [0.0])
        ]

    def every(self, period_s: float, fn: Callable[[], None]) -> None:
        self._periodic.append((period_s, fn, [0.0]))

    def subscribe(self, channel: str, handler: Callable[[Any, Any], None]) -> None:
        self.bus.subscribe(channel, handler)

    def wait_until(self, done: Callable[[], bool], timeout_s: float) -> bool:
        """Poll until ``done()`` or ``timeout_s``; True if done."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if done():
                return True
            now = time.monotonic()
            for period_s, fn, next_due in self._periodic:
                if now >= next_due[0]:
                    fn()
                    next_due[0] = now + period_s
            self.bus.poll(0.005)
        return done()

    def close(self) -> None:
        self.bus.close()
