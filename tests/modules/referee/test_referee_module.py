"""The referee process over an in-process bus: truth and paths are judged in the order they came."""

from __future__ import annotations

import uuid
from typing import Any

import pytest

from modules.referee.module import Referee, RefereeConfig
from protocol import channels
from protocol.auth import Keyring
from protocol.messages import Path as PlannedPath
from protocol.messages import PathPoint, SimTruth
from protocol.transport import MemTransport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import ManualClock
from rascal.runtime.module import RUN_DIR_ENV, Runtime


class Recorder:
    """Stands in for the measures: what it was fed, in order."""

    def __init__(self) -> None:
        self.fed: list[Any] = []

    def on_truth(self, truth: SimTruth) -> None:
        self.fed.append(truth)

    def on_path(self, path: PlannedPath) -> None:
        self.fed.append(path)


def test_truth_and_paths_are_judged_in_arrival_order_when_the_referee_looks(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(RUN_DIR_ENV, raising=False)  # no file to write: only the judging is watched
    hub, keyring, clock = uuid.uuid4().hex, Keyring.generate(), ManualClock()
    referee = Referee(RefereeConfig(), Runtime(Bus(MemTransport(hub), 6, keyring, clock), clock))
    referee.on_start()
    recorder = Recorder()
    referee.measures = recorder  # type: ignore[assignment]
    sim, brain = Bus(MemTransport(hub), 5, keyring, clock), Bus(MemTransport(hub), 30, keyring, clock)
    sent: list[Any] = []
    for k in range(6):
        clock.advance(10_000_000)
        truth = SimTruth(float(k), 0.0, 0.0, 1.0, 0.0, 0.0, float(k), 0, scenario_time_s=k * 0.01)
        sim.publish(channels.SIM_TRUTH, truth)
        sent.append(truth)
        if k % 2:
            clock.advance(1_000_000)
            path = PlannedPath(k, (PathPoint(0.0, 0.0, 1.0), PathPoint(float(k), 1.0, 1.0)), False)
            brain.publish(channels.PATH, path)
            sent.append(path)
        referee.bus.poll()
    assert recorder.fed == []  # nothing judged until the referee looks...
    referee.write()
    assert recorder.fed == sent  # ...then everything, in order
    referee.write()
    assert recorder.fed == sent
