"""Shared pieces of the worker, watchdog and module tests: a scene with obstacles and lane
stripes, a ring that holds its frames, and a bounded wait that keeps the watchdog running."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from modules.esvs.frames import RingWriter
from modules.esvs.watchdog import Watchdog
from modules.esvs.worker import Report
from protocol.messages import Severity
from tests.modules.esvs.vision.scenes import Box, Scene, Stripe, rendered

SCENE = Scene(
    boxes=(Box(16.6, 2.5, 1.0, 1.0, 1.2), Box(26.6, -2.0, 1.5, 1.0, 1.0)),
    stripes=(Stripe(4.0, 0.0, 0.0), Stripe(-4.0, 0.0, 0.0)),
    seed=11,
)


def scene_pair() -> tuple[np.ndarray, np.ndarray]:
    left, right, _ = rendered(SCENE)
    return left, right


def write_frames(writer: RingWriter, count: int = 1, t0_ns: int = 1_000_000_000) -> list[int]:
    """``count`` frames of the scene (exposed 1 ms apart); returns their sequence numbers."""
    left, right = scene_pair()
    return [writer.write(left, right, t0_ns + writer.seq * 1_000_000) for _ in range(count)]


class Events:
    """A HealthEvent sink for a Watchdog or module."""

    def __init__(self) -> None:
        self.items: list[tuple[Severity, str, str]] = []

    def __call__(self, severity: Severity, code: str, text: str) -> None:
        self.items.append((severity, code, text))

    def codes(self) -> list[str]:
        return [code for _severity, code, _text in self.items]


def pump(watchdog: Watchdog, done: Callable[[list[Report]], bool], timeout_s: float = 20.0) -> list[Report]:
    """Run the watchdog every 5 ms until ``done(reports so far)``; fails the test on timeout."""
    reports: list[Report] = []
    deadline = time.monotonic() + timeout_s
    while not done(reports):
        assert time.monotonic() < deadline, f"timed out; reports so far: {[(r.role, r.seq) for r in reports]}"
        reports += watchdog.check()
        time.sleep(0.005)
    return reports
