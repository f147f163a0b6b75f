"""The shared-memory frame ring between the camera (the frame grabber) and the ESVS vision workers.

One writer, any number of readers, no locks. The writer fills slots in turn; each slot carries a
sequence number written *before* the images (``begin``) and again *after* them (``end``): a
seqlock. A reader reads ``end``, copies the images, then reads ``begin``; only if both equal the
sequence it wanted was the slot left alone while it copied. Readers always take a private copy
(CAMBADA: each process works on its own copy of the newest frame), so the writer never waits.

The one reader that paces the camera (the ESVS round) writes its *trigger* into the header at each
grab: when it grabbed (CLOCK_MONOTONIC) and how often it grabs. A camera that sees a live trigger
renders one frame per grab, finished just before it, as a camera on an external trigger line
exposes on demand; with none it runs free at its own frame rate.

Layout (native little-endian words, 8-byte aligned)::

    header (64 B)  0 magic "RSTEREO1" | 8 version u32 | 12 slots u32 | 16 height u32 | 20 width u32
                   24 writer pid u32 | 28 closed u32 | 32 generation u64 | 40 latest seq u64
                   48 trigger: latest grab ns u64 | 56 trigger: grab period ns u64 (0: none)
    slot k at 64 + k * stride:
                   0 begin seq | 8 end seq | 16 t_exposure_ns (shared time) | 24 written_ns
                   (CLOCK_MONOTONIC) | 32 left image (height x width grey u8) | right image

Sequences start at 1 in each writer's life; a restarted writer makes a new segment with a new
random ``generation``. A reader that sees no new frame for ``stale_s`` looks the name up again
and follows a new generation, so it survives the camera process restarting. Consistency relies
on the CPU keeping stores in program order (x86-64 does); the writer unlinks the segment when
it stops, and a writer that finds a dead writer's segment under its name reclaims it.
"""

from __future__ import annotations

import os
import struct
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from multiprocessing import resource_tracker
from multiprocessing.shared_memory import SharedMemory
from typing import NamedTuple

import numpy as np

MAGIC = b"RSTEREO1"
VERSION = 1
HEADER_BYTES = 64
SLOT_HEADER_BYTES = 32
DEFAULT_SLOTS = 4
_HEADER_FIELDS = struct.Struct("<8sIIIIII")  # magic, version, slots, height, width, pid, closed
_GENERATION, _LATEST, _GRAB, _GRAB_PERIOD = 4, 5, 6, 7  # uint64 word indices in the header
_BEGIN, _END, _EXPOSURE, _WRITTEN = 0, 1, 2, 3  # int64 word indices in a slot header
_READ_ATTEMPTS = 4


class RingError(RuntimeError):
    """The ring cannot be created or attached (bad name, size, or another live writer)."""


class Trigger(NamedTuple):
    """The pacing reader's grabs, as it last announced them."""

    grab_ns: int  # CLOCK_MONOTONIC of its latest grab
    period_ns: int  # how often it grabs


class FrameInfo(NamedTuple):
    """Which frame is newest, read from the headers only."""

    generation: int
    seq: int
    t_exposure_ns: int
    written_ns: int


@dataclass(frozen=True)
class Frame:
    """A private copy of one stereo pair from the ring."""

    generation: int
    seq: int
    t_exposure_ns: int  # shared time the pair was exposed
    written_ns: int  # CLOCK_MONOTONIC when the writer finished the slot (one clock per host)
    left: np.ndarray
    right: np.ndarray

    def info(self) -> FrameInfo:
        return FrameInfo(self.generation, self.seq, self.t_exposure_ns, self.written_ns)


def check_name(name: str) -> str:
    if not name or "/" in name or len(name) > 200 or not name.isprintable():
        raise RingError(f"frame ring name must be 1-200 printable characters without '/', got {name!r}")
    return name


def slot_stride(height: int, width: int) -> int:
    raw = SLOT_HEADER_BYTES + 2 * height * width
    return (raw + 63) // 64 * 64


def ring_bytes(slots: int, height: int, width: int) -> int:
    return HEADER_BYTES + slots * slot_stride(height, width)


class _Views:
    """numpy views over a mapped ring; dropped before the mapping is closed (an exported buffer
    would make SharedMemory.close() fail)."""

    def __init__(self, shm: SharedMemory, slots: int, height: int, width: int) -> None:
        buf = shm.buf
        self.header = np.ndarray((8,), dtype="<u8", buffer=buf, offset=0)
        stride = slot_stride(height, width)
        image = height * width
        self.words: list[np.ndarray] = []
        self.left: list[np.ndarray] = []
        self.right: list[np.ndarray] = []
        for k in range(slots):
            base = HEADER_BYTES + k * stride
            self.words.append(np.ndarray((4,), dtype="<i8", buffer=buf, offset=base))
            first = base + SLOT_HEADER_BYTES
            self.left.append(np.ndarray((height, width), dtype=np.uint8, buffer=buf, offset=first))
            self.right.append(np.ndarray((height, width), dtype=np.uint8, buffer=buf, offset=first + image))


@contextmanager
def _untracked() -> Iterator[None]:
    """Python < 3.13 registers *attached* segments with the resource tracker, which unlinks them
    when the attaching process exits: a reader would delete the camera's ring. Attach (and unlink
    a dead writer's segment) without telling it."""
    register, unregister = resource_tracker.register, resource_tracker.unregister
    resource_tracker.register = resource_tracker.unregister = lambda name, rtype: None  # type: ignore[assignment]
    try:
        yield
    finally:
        resource_tracker.register, resource_tracker.unregister = register, unregister  # type: ignore[assignment]


def _attach(name: str) -> SharedMemory:
    with _untracked():
        return SharedMemory(name=name, create=False)


def _read_header(shm: SharedMemory) -> tuple[bytes, int, int, int, int, int, int]:
    if shm.size < HEADER_BYTES:
        return b"", 0, 0, 0, 0, 0, 0
    return _HEADER_FIELDS.unpack_from(shm.buf, 0)


def _alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class RingWriter:
    """The camera side: creates the named ring and writes stereo pairs into it."""

    def __init__(self, name: str, height: int, width: int, slots: int = DEFAULT_SLOTS) -> None:
        check_name(name)
        if slots < 2 or height <= 0 or width <= 0:
            raise RingError(f"frame ring needs >= 2 slots and a positive image size, got {slots}, {height}x{width}")
        self.name, self.height, self.width, self.slots = name, height, width, slots
        size = ring_bytes(slots, height, width)
        try:
            self._shm = SharedMemory(name=name, create=True, size=size)
        except FileExistsError:
            self._reclaim(name)
            self._shm = SharedMemory(name=name, create=True, size=size)
        self._views: _Views | None = _Views(self._shm, slots, height, width)
        self.generation = int.from_bytes(os.urandom(8), "little") | 1
        self.seq = 0
        header = self._views.header
        header[_GENERATION] = self.generation
        header[_LATEST] = header[_GRAB] = header[_GRAB_PERIOD] = 0
        # The magic goes in last: a reader attaching meanwhile sees no ring yet, not a half one.
        _HEADER_FIELDS.pack_into(self._shm.buf, 0, b"\0" * 8, VERSION, slots, height, width, os.getpid(), 0)
        self._shm.buf[0:8] = MAGIC

    @staticmethod
    def _reclaim(name: str) -> None:
        """A segment under our name: take it over if its writer is gone, refuse if it lives."""
        try:
            old = _attach(name)
        except FileNotFoundError:
            return
        try:
            magic, _version, _slots, _h, _w, pid, _closed = _read_header(old)
            if magic != MAGIC:
                raise RingError(f"shared memory {name!r} exists and is not a frame ring; remove /dev/shm/{name}")
            if pid != os.getpid() and _alive(pid):
                raise RingError(f"frame ring {name!r} is being written by live process {pid}")
            with _untracked():
                old.unlink()
        finally:
            old.close()

    def write(self, left: np.ndarray, right: np.ndarray, t_exposure_ns: int) -> int:
        """Publish one pair exposed at ``t_exposure_ns`` (shared time); returns its sequence."""
        views = self._views
        if views is None:
            raise RingError(f"frame ring {self.name!r} is closed")
        shape = (self.height, self.width)
        for label, image in (("left", left), ("right", right)):
            if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.shape != shape:
                raise ValueError(f"{label} image must be grey uint8 {shape}, got {getattr(image, 'shape', image)!r}")
        seq = self.seq + 1
        k = (seq - 1) % self.slots
        words = views.words[k]
        words[_BEGIN] = seq  # from here on, a reader of this slot's previous frame sees it torn
        views.left[k][...] = left
        views.right[k][...] = right
        words[_EXPOSURE] = t_exposure_ns
        words[_WRITTEN] = time.monotonic_ns()
        words[_END] = seq
        views.header[_LATEST] = seq
        self.seq = seq
        return seq

    def trigger(self) -> Trigger | None:
        """The pacing reader's grabs, None before it has announced any."""
        views = self._views
        if views is None:
            raise RingError(f"frame ring {self.name!r} is closed")
        grab_ns, period_ns = int(views.header[_GRAB]), int(views.header[_GRAB_PERIOD])
        return Trigger(grab_ns, period_ns) if period_ns > 0 else None

    def close(self, unlink: bool = True) -> None:
        """Mark the ring closed (readers detach at once) and remove the name."""
        if self._views is None:
            return
        struct.pack_into("<I", self._shm.buf, 28, 1)
        self._views = None
        self._shm.close()
        if unlink:
            with suppress(FileNotFoundError):
                self._shm.unlink()


class RingReader:
    """A vision side: private copies of the newest frame; never blocks the writer or waits.

    Attaching is lazy and retried; ``now_ns`` (CLOCK_MONOTONIC by default) paces the retries and
    the stale check that follows a restarted writer."""

    def __init__(
        self,
        name: str,
        *,
        stale_s: float = 0.5,
        retry_s: float = 0.1,
        now_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.name = check_name(name)
        self._stale_ns = int(stale_s * 1e9)
        self._retry_ns = int(retry_s * 1e9)
        self._now_ns = now_ns
        self._shm: SharedMemory | None = None
        self._views: _Views | None = None
        self.generation = 0
        self.slots = 0
        self.shape = (0, 0)
        self._next_attempt_ns = 0
        self._last_seq = 0
        self._last_progress_ns = 0
        self.attaches = 0  # how many times a ring was attached (more than one: the writer restarted)
        self.torn = 0  # copies discarded because the writer overwrote the slot meanwhile

    @property
    def attached(self) -> bool:
        return self._views is not None

    def newest(self) -> FrameInfo | None:
        """The newest complete frame's sequence and times, without copying the images."""
        views = self._ready()
        if views is None:
            return None
        for _ in range(_READ_ATTEMPTS):
            seq = int(views.header[_LATEST])
            if seq == 0:
                return None
            words = views.words[(seq - 1) % self.slots]
            end = int(words[_END])
            exposure, written = int(words[_EXPOSURE]), int(words[_WRITTEN])
            if end == seq and int(words[_BEGIN]) == seq:
                return FrameInfo(self.generation, seq, exposure, written)
            self.torn += 1
        return None

    def latest(self) -> Frame | None:
        """A private copy of the newest complete frame (None if there is none yet)."""
        views = self._ready()
        if views is None:
            return None
        for _ in range(_READ_ATTEMPTS):
            seq = int(views.header[_LATEST])
            if seq == 0:
                return None
            frame = self._copy(views, seq)
            if frame is not None:
                return frame
        return None

    def trigger(self, period_ns: int) -> None:
        """Announce a grab now, one of a series every ``period_ns``, to the writer: the pacing
        reader's call (one per ring), right after each grab. Nothing while detached."""
        if period_ns <= 0:
            raise ValueError(f"a trigger period must be positive, got {period_ns}")
        views = self._views
        if views is not None:
            views.header[_GRAB_PERIOD] = period_ns
            views.header[_GRAB] = self._now_ns()

    def read(self, generation: int, seq: int) -> Frame | None:
        """A private copy of frame ``seq`` of ``generation`` if the ring still holds it."""
        views = self._ready()
        if views is None or generation != self.generation or seq <= 0:
            return None
        return self._copy(views, seq)

    def _copy(self, views: _Views, seq: int) -> Frame | None:
        k = (seq - 1) % self.slots
        words = views.words[k]
        if int(words[_END]) != seq:
            return None
        exposure, written = int(words[_EXPOSURE]), int(words[_WRITTEN])
        left, right = views.left[k].copy(), views.right[k].copy()
        if int(words[_BEGIN]) != seq:
            self.torn += 1
            return None
        return Frame(self.generation, seq, exposure, written, left, right)

    def _ready(self) -> _Views | None:
        """The current mapping, after following a closed or silent writer to a new segment."""
        now = self._now_ns()
        views = self._views
        if views is not None and self._shm is not None:
            closed = struct.unpack_from("<I", self._shm.buf, 28)[0]
            seq = int(views.header[_LATEST])
            if closed:
                self._detach()
            elif seq != self._last_seq:
                self._last_seq, self._last_progress_ns = seq, now
            elif now - self._last_progress_ns >= self._stale_ns and now >= self._next_attempt_ns:
                self._next_attempt_ns = now + self._stale_ns
                self._follow()
        if self._views is None and now >= self._next_attempt_ns:
            self._next_attempt_ns = now + self._retry_ns
            self._attach_new()
        return self._views

    def _follow(self) -> None:
        """No progress for a while: if the name now holds another generation, switch to it."""
        try:
            shm = _attach(self.name)
        except (FileNotFoundError, ValueError, OSError):
            return
        header = _read_header(shm)
        generation = struct.unpack_from("<Q", shm.buf, 32)[0] if header[0] == MAGIC else 0
        if header[0] == MAGIC and generation != self.generation:
            shm.close()
            self._detach()
            self._attach_new()
        else:
            shm.close()

    def _attach_new(self) -> None:
        try:
            shm = _attach(self.name)
        except (FileNotFoundError, ValueError, OSError):
            return
        magic, version, slots, height, width, _pid, closed = _read_header(shm)
        if magic != MAGIC or version != VERSION or closed or slots < 2 or shm.size < ring_bytes(slots, height, width):
            shm.close()
            return
        self._shm = shm
        self._views = _Views(shm, slots, height, width)
        self.slots, self.shape = slots, (height, width)
        self.generation = int(self._views.header[_GENERATION])
        self._last_seq = int(self._views.header[_LATEST])
        self._last_progress_ns = self._now_ns()
        self.attaches += 1

    def _detach(self) -> None:
        self._views = None
        if self._shm is not None:
            self._shm.close()
            self._shm = None

    def close(self) -> None:
        self._detach()
