"""A vision worker process: takes a private copy of a frame from the ring, runs its part of the
vision pipeline, and sends the result back to the ESVS process over a pipe.

Two ways to be activated:

* **by the round** (``period_ns == 0``; monolithic mode): each ``Process`` request names the
  frame the round grabbed; the worker copies that frame (or the newest, if the ring has moved
  past it) and runs the whole pipeline;
* **by its own timer** (CAMBADA mode): activations at ``epoch_ns + offset_ns + k * period_ns``
  of CLOCK_MONOTONIC, as CAMBADA's RTAI tasks triggered each process with period and offset;
  each activation takes the newest frame, or reports itself idle if it already saw that frame.

A worker starts as a standby: it says ``Hello`` and waits for ``Activate``, so the watchdog can
keep a spare ready to take over at once. Every activation ends in one ``Report`` (the watchdog's
sign of life and the jitter record). A
worker exits when the ESVS end of the pipe closes, so it never outlives its process; an
exception in the vision code ends the process too, and the watchdog starts a new one
(crash-only, as RASCAL's watchdog rebooted the DSP).
"""

from __future__ import annotations

import ctypes
import os
import time
from dataclasses import dataclass, field, replace
from multiprocessing.connection import Connection
from typing import NamedTuple

import cv2

from modules.esvs import scheduling
from modules.esvs.cambada import detect_lanes, detect_obstacles
from modules.esvs.frames import Frame, RingReader
from modules.esvs.geometry import RASCAL_RIG, StereoRig
from modules.esvs.vision.pipeline import VisionParams, process
from protocol.messages import LaneBorders, ObstacleList

ROLES = ("vision", "obstacles", "lanes")
FAULTS = ("hang", "crash")
CRASH_EXIT_CODE = 70
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)


@dataclass(frozen=True)
class WorkerSpec:
    role: str  # vision (whole pipeline), obstacles or lanes
    ring_name: str
    params: VisionParams = field(default_factory=VisionParams)
    rig: StereoRig = RASCAL_RIG
    policy: str = "none"  # scheduling: fifo, nice or none
    priority: int = 20
    nice: int = 0
    period_ns: int = 0  # 0: activated by the round's Process requests
    offset_ns: int = 0
    epoch_ns: int = 0  # CLOCK_MONOTONIC origin of the activation grid

    def __post_init__(self) -> None:
        if self.role not in ROLES:
            raise ValueError(f"worker role must be one of {ROLES}, not {self.role!r}")
        if self.period_ns < 0 or self.offset_ns < 0:
            raise ValueError("worker period and offset must not be negative")
        scheduling.check(self.policy, self.priority)

    @property
    def periodic(self) -> bool:
        return self.period_ns > 0

    def activation_at_or_after(self, t_ns: int) -> int:
        """The first grid instant at or after ``t_ns`` (only for periodic workers)."""
        first = self.epoch_ns + self.offset_ns
        if t_ns <= first:
            return first
        k = -(-(t_ns - first) // self.period_ns)
        return first + k * self.period_ns


# -- ESVS -> worker ---------------------------------------------------------------------------


class Process(NamedTuple):
    """Work on this frame now (round-activated workers)."""

    generation: int
    seq: int


class SetParams(NamedTuple):
    params: VisionParams


class Retime(NamedTuple):
    """A new activation grid (periodic workers), after the round period changed."""

    period_ns: int
    offset_ns: int
    epoch_ns: int


class Activate(NamedTuple):
    """Start working: every worker starts as a standby (imported, attached, idle) until told."""


class Inject(NamedTuple):
    """Fault injection for tests of the watchdog: ``hang`` sleeps ``seconds`` in the next
    activation, ``crash`` exits at once."""

    fault: str
    seconds: float = 60.0


# -- worker -> ESVS ---------------------------------------------------------------------------


class Hello(NamedTuple):
    pid: int
    scheduling: str


class Report(NamedTuple):
    """One activation. ``seq`` 0 means it found no new frame (idle)."""

    role: str
    activated_ns: int  # CLOCK_MONOTONIC
    finished_ns: int
    generation: int
    seq: int
    t_exposure_ns: int
    frame_written_ns: int
    obstacles: ObstacleList | None
    lanes: LaneBorders | None
    compute_s: float


def run_worker(spec: WorkerSpec, conn: Connection) -> None:
    """Process entry point."""
    granted = scheduling.apply(spec.policy, spec.priority, spec.nice)
    # One core per worker (CAMBADA's processes were single-threaded): OpenCV's own thread pool
    # would let one real-time worker take every core from the round and the camera.
    cv2.setNumThreads(1)
    keep_freed_memory()
    reader = RingReader(spec.ring_name)
    worker = _Worker(spec, reader, conn)
    try:
        conn.send(Hello(os.getpid(), granted))
        worker.run()
    except (EOFError, BrokenPipeError, ConnectionResetError):
        pass  # the ESVS process is gone or replaced us: nothing left to work for
    finally:
        reader.close()


def keep_freed_memory() -> None:
    """Have glibc's malloc keep freed memory rather than hand it back to the kernel: every frame
    allocates and frees the same few megabytes of arrays, and memory handed back comes back as
    page faults (about 1000 a frame, 3 ms of kernel time). Elsewhere (no glibc) nothing changes."""
    try:
        mallopt = ctypes.CDLL(None).mallopt  # this process's own symbols, libc's among them
    except AttributeError:
        return
    mallopt(_M_TRIM_THRESHOLD, 256 << 20)  # setting either also stops glibc's own adjustment of both
    mallopt(_M_MMAP_THRESHOLD, 32 << 20)  # the largest glibc takes: every frame array from the heap


class _Worker:
    def __init__(self, spec: WorkerSpec, reader: RingReader, conn: Connection) -> None:
        self.spec = spec
        self.reader = reader
        self.conn = conn
        self.last_frame = (0, 0)
        self.fault: Inject | None = None

    def run(self) -> None:
        while not isinstance(message := self.conn.recv(), Activate):
            self._control(message)  # a standby keeps its parameters and timing current
        if self.spec.periodic:
            self._run_periodic()
        else:
            self._run_triggered()

    def _run_triggered(self) -> None:
        while True:
            message = self.conn.recv()
            if isinstance(message, Process):
                activated = time.monotonic_ns()
                frame = self.reader.read(message.generation, message.seq) or self.reader.latest()
                self._activation(activated, frame)
            else:
                self._control(message)

    def _run_periodic(self) -> None:
        due = self.spec.activation_at_or_after(time.monotonic_ns())
        while True:
            delay = due - time.monotonic_ns()
            if delay > 0:
                time.sleep(delay / 1e9)
            activated = time.monotonic_ns()
            while self.conn.poll():
                message = self.conn.recv()
                self._control(message)
                if isinstance(message, Retime):
                    due = self.spec.activation_at_or_after(activated)
            if activated < due:
                continue  # a Retime moved the grid later
            frame = self.reader.latest()
            if frame is not None and (frame.generation, frame.seq) == self.last_frame:
                frame = None  # nothing new since the last activation: no new measurement
            self._activation(activated, frame)
            # Keep to the grid; activations an overrun swallowed are skipped, not run late.
            due = self.spec.activation_at_or_after(max(due + self.spec.period_ns, time.monotonic_ns()))

    def _control(self, message: object) -> None:
        if isinstance(message, SetParams):
            self.spec = replace(self.spec, params=message.params)
        elif isinstance(message, Retime):
            self.spec = replace(
                self.spec, period_ns=message.period_ns, offset_ns=message.offset_ns, epoch_ns=message.epoch_ns
            )
        elif isinstance(message, Inject):
            self.fault = message
        elif not isinstance(message, Activate):
            raise TypeError(f"vision worker: unexpected message {message!r}")

    def _activation(self, activated_ns: int, frame: Frame | None) -> None:
        fault, self.fault = self.fault, None
        if fault is not None and fault.fault == "crash":
            os._exit(CRASH_EXIT_CODE)
        if fault is not None and fault.fault == "hang":
            time.sleep(fault.seconds)
        rig = self.spec.rig
        if frame is not None and frame.left.shape != (rig.height_px, rig.width_px):
            frame = None  # a camera of another size: nothing this rig can measure (the ESVS reports it)
        obstacles = lanes = None
        compute_s = 0.0
        if frame is not None:
            self.last_frame = (frame.generation, frame.seq)
            start = time.perf_counter()
            obstacles, lanes = self._detect(frame)
            compute_s = time.perf_counter() - start
        generation, seq, exposure, written = frame.info() if frame is not None else (0, 0, 0, 0)
        report = Report(
            self.spec.role,
            activated_ns,
            time.monotonic_ns(),
            generation,
            seq,
            exposure,
            written,
            obstacles,
            lanes,
            compute_s,
        )
        self.conn.send(report)

    def _detect(self, frame: Frame) -> tuple[ObstacleList | None, LaneBorders | None]:
        spec = self.spec
        if spec.role == "obstacles":
            return detect_obstacles(frame.left, frame.right, spec.rig, spec.params)[0], None
        if spec.role == "lanes":
            return None, detect_lanes(frame.left, frame.right, spec.rig, spec.params)[0]
        obstacles, lanes, _stats = process(frame.left, frame.right, spec.rig, spec.params)
        return obstacles, lanes
