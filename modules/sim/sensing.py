"""What every simulated sensor does with the truth: one measurement per new true pose, as the
scenario's faults allow.

A sensor's faults are looked up at the truth's scenario time and course progress, so every
sensor process applies them together however late it started. Combined: silence (or an outage)
wins; a stuck sensor repeats its last output under the new time stamp (nothing until it had
one), the way a stuck driver keeps handing out its last buffer; noise factors multiply; jumps
(the GPS's) add. The lidars and the cameras run ``SensedTruth``; the navigation sensors, several
models in one process each with its own clock, use ``fault_effect`` and ``StuckGate``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Generic, NamedTuple, TypeVar

from modules.sim.world import FaultKind, SensorFault, World
from protocol.messages import SimTruth
from rascal.runtime.rtdb import Latest, Validity

T = TypeVar("T")


class FaultEffect(NamedTuple):
    """What the active faults do to one sensor's next output."""

    kinds: frozenset[FaultKind]
    silent: bool
    stuck: bool
    noise_scale: float
    jumps: tuple[SensorFault, ...]


def fault_effect(schedule: World, sensor: str, t_s: float, progress_m: float) -> FaultEffect:
    """Combine the faults of ``sensor`` active at ``t_s`` and ``progress_m``."""
    active = schedule.faults_for(sensor, t_s, progress_m)
    kinds = frozenset(fault.kind for fault in active)
    return FaultEffect(
        kinds=kinds,
        silent=bool(kinds & {FaultKind.SILENCE, FaultKind.OUTAGE}),
        stuck=FaultKind.STUCK in kinds,
        noise_scale=math.prod(fault.magnitude for fault in active if fault.kind is FaultKind.NOISE),
        jumps=tuple(fault for fault in active if fault.kind is FaultKind.JUMP),
    )


NO_FAULT = fault_effect(World(), "", 0.0, 0.0)


class StuckGate(Generic[T]):
    """The output gate the faults set: nothing when silent, the last output when stuck."""

    def __init__(self) -> None:
        self.last: T | None = None

    def emit(self, effect: FaultEffect, measurement: Callable[[], T]) -> T | None:
        """The output to send: ``measurement()`` (made only when it will be sent), or what the
        faults make of it."""
        if effect.silent:
            return None
        if effect.stuck:
            return self.last
        self.last = measurement()
        return self.last


class SensedTruth(Generic[T]):
    """One simulated sensor's loop: read the newest truth, and at most once per new true pose,
    measure from it as the faults allow."""

    def __init__(self, truth: Latest[SimTruth], world: World, sensor: str) -> None:
        self.truth = truth
        self.world = world
        self.sensor = sensor
        self.gate: StuckGate[T] = StuckGate()
        self.effect = NO_FAULT  # the faults of the last pose judged
        self._last_t_ns: int | None = None

    def step(self, now_ns: int, measure: Callable[[SimTruth, int, float], T]) -> tuple[T, int] | None:
        """``(output, t_meas_ns)`` to send for the newest true pose, or None: no fresh pose, the
        same pose as last time, or silenced. ``measure(truth, t_meas_ns, noise_scale)``."""
        reading = self.truth.read(now_ns)
        if reading.validity is not Validity.FRESH or reading.envelope is None:
            return None
        t_meas_ns = reading.envelope.t_meas_ns
        if t_meas_ns == self._last_t_ns:
            return None
        self._last_t_ns = t_meas_ns
        truth: SimTruth = reading.value
        self.effect = fault_effect(self.world, self.sensor, truth.scenario_time_s, truth.progress_m)
        output = self.gate.emit(self.effect, lambda: measure(truth, t_meas_ns, self.effect.noise_scale))
        return None if output is None else (output, t_meas_ns)

    @property
    def fault_names(self) -> str:
        """The active faults, for a heartbeat ("" when none)."""
        return ",".join(sorted(kind.value for kind in self.effect.kinds))
