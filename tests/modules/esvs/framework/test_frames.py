"""The shared-memory frame ring: private copies of the newest complete frame, torn copies
rejected, the name unlinked by its writer, and readers that follow a restarted writer."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator

import numpy as np
import pytest

from modules.esvs.frames import RingError, RingReader, RingWriter, _attach
from tests.conftest import ROOT
from tests.modules.esvs.framework.rings import HEIGHT, WIDTH, pair, ring_name_fixture, unique_name, unlink


@pytest.fixture
def ring_name() -> Iterator[str]:
    yield from ring_name_fixture()


class FakeTime:
    def __init__(self) -> None:
        self.t_ns = 1_000_000_000

    def __call__(self) -> int:
        return self.t_ns

    def advance(self, seconds: float) -> None:
        self.t_ns += int(seconds * 1e9)


def test_reader_gets_a_private_copy_of_the_newest_frame(ring_name: str) -> None:
    writer = RingWriter(ring_name, HEIGHT, WIDTH, slots=3)
    reader = RingReader(ring_name)
    try:
        assert reader.latest() is None  # attached, nothing written yet
        for value in range(5):
            writer.write(*pair(value), t_exposure_ns=1000 + value)
        frame = reader.latest()
        assert frame is not None
        assert (frame.seq, frame.t_exposure_ns, frame.generation) == (5, 1004, writer.generation)
        assert frame.left[0, 0] == 4 and frame.right[-1, -1] == 5
        writer.write(*pair(99), t_exposure_ns=2000)
        assert frame.left[0, 0] == 4, "a copy must not change when the writer moves on"
        newest = reader.newest()
        assert newest is not None and (newest.seq, newest.t_exposure_ns) == (6, 2000)
    finally:
        reader.close()
        writer.close()


def test_a_frame_the_writer_lapped_is_gone_and_one_it_is_overwriting_is_torn(ring_name: str) -> None:
    writer = RingWriter(ring_name, HEIGHT, WIDTH, slots=2)
    reader = RingReader(ring_name)
    try:
        for value in range(3):  # seq 3 reuses seq 1's slot
            writer.write(*pair(value), t_exposure_ns=value)
        assert reader.read(writer.generation, 1) is None
        frame = reader.read(writer.generation, 2)
        assert frame is not None and frame.left[0, 0] == 1
        # The writer has begun seq 4 in seq 2's slot (begin written, images half copied).
        views = writer._views
        assert views is not None
        views.words[1][0] = 4
        views.left[1][:10] = 200
        assert reader.read(writer.generation, 2) is None
        assert reader.torn == 1
        assert reader.latest() is not None and reader.latest().seq == 3  # type: ignore[union-attr]
        assert reader.read(writer.generation + 2, 3) is None  # another writer's life
    finally:
        reader.close()
        writer.close()


def test_the_writer_unlinks_and_readers_detach_when_it_closes(ring_name: str) -> None:
    writer = RingWriter(ring_name, HEIGHT, WIDTH)
    reader = RingReader(ring_name)
    writer.write(*pair(1), t_exposure_ns=1)
    assert reader.latest() is not None
    writer.close()
    assert reader.latest() is None and not reader.attached
    with pytest.raises(FileNotFoundError):
        _attach(ring_name)


def test_a_reader_started_before_the_camera_attaches_when_it_appears(ring_name: str) -> None:
    clock = FakeTime()
    reader = RingReader(ring_name, retry_s=0.1, now_ns=clock)
    assert reader.latest() is None and not reader.attached
    writer = RingWriter(ring_name, HEIGHT, WIDTH)
    try:
        writer.write(*pair(7), t_exposure_ns=70)
        assert reader.latest() is None  # the next attempt is not due yet
        clock.advance(0.1)
        frame = reader.latest()
        assert frame is not None and frame.left[0, 0] == 7
    finally:
        reader.close()
        writer.close()


def test_a_reader_follows_a_writer_that_died_and_restarted(ring_name: str) -> None:
    clock = FakeTime()
    reader = RingReader(ring_name, stale_s=0.5, now_ns=clock)
    first = RingWriter(ring_name, HEIGHT, WIDTH)
    first.write(*pair(1), t_exposure_ns=10)
    assert reader.latest() is not None
    # The camera process is killed: nobody closes its ring, and its resource tracker unlinks it.
    unlink(ring_name)
    second = RingWriter(ring_name, HEIGHT, WIDTH)
    try:
        second.write(*pair(2), t_exposure_ns=20)
        clock.advance(0.4)
        stale = reader.latest()
        assert stale is not None and stale.generation == first.generation  # not silent long enough yet
        clock.advance(0.2)
        frame = reader.latest()
        assert frame is not None
        assert (frame.generation, frame.seq, frame.left[0, 0]) == (second.generation, 1, 2)
        assert reader.attaches == 2
    finally:
        reader.close()
        second.close()
        first.close(unlink=False)


def test_the_pacing_reader_tells_the_writer_when_it_grabs(ring_name: str) -> None:
    clock = FakeTime()
    reader = RingReader(ring_name, now_ns=clock)
    reader.trigger(100_000_000)  # not attached yet: nothing to tell
    writer = RingWriter(ring_name, HEIGHT, WIDTH)
    try:
        assert writer.trigger() is None
        reader.newest()  # attaches
        reader.trigger(100_000_000)
        assert writer.trigger() == (clock.t_ns, 100_000_000)
        clock.advance(0.1)
        reader.trigger(50_000_000)  # the round was retimed
        assert writer.trigger() == (clock.t_ns, 50_000_000)
        with pytest.raises(ValueError, match="period"):
            reader.trigger(0)
    finally:
        reader.close()
        writer.close()
    again = RingWriter(ring_name, HEIGHT, WIDTH)
    try:
        assert again.trigger() is None  # a new ring starts untriggered
    finally:
        again.close()


def test_a_new_writer_reclaims_a_dead_writers_ring_but_not_a_live_ones(ring_name: str) -> None:
    live = RingWriter(ring_name, HEIGHT, WIDTH)
    try:
        with pytest.raises(RingError, match="live process"):
            _other_process_writer(ring_name)
    finally:
        live.close(unlink=False)  # leaves the segment behind, as a killed writer would
    dead_pid = _finished_pid()
    segment = _attach(ring_name)
    segment.buf[24:28] = dead_pid.to_bytes(4, "little")
    segment.close()
    again = RingWriter(ring_name, HEIGHT, WIDTH)
    again.write(*pair(3), t_exposure_ns=3)
    again.close()


def test_a_reader_process_exiting_leaves_the_ring_in_place(ring_name: str) -> None:
    writer = RingWriter(ring_name, HEIGHT, WIDTH)
    try:
        writer.write(*pair(5), t_exposure_ns=5)
        code = (
            "from modules.esvs.frames import RingReader\n"
            f"frame = RingReader({ring_name!r}).latest()\n"
            "assert frame is not None and frame.left[0, 0] == 5\n"
        )
        subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, capture_output=True, timeout=60)
        segment = _attach(ring_name)  # still there: the reader's exit did not unlink it
        segment.close()
    finally:
        writer.close()


def test_bad_names_sizes_and_images_are_refused() -> None:
    with pytest.raises(RingError):
        RingWriter("a/b", HEIGHT, WIDTH)
    with pytest.raises(RingError):
        RingReader("")
    with pytest.raises(RingError):
        RingWriter(unique_name(), HEIGHT, WIDTH, slots=1)
    name = unique_name()
    writer = RingWriter(name, 4, 6)
    try:
        with pytest.raises(ValueError, match="grey uint8"):
            writer.write(np.zeros((4, 6), np.float32), np.zeros((4, 6), np.uint8), 0)
        with pytest.raises(ValueError, match="grey uint8"):
            writer.write(*pair(1), t_exposure_ns=0)  # full-size images into a 4 x 6 ring
    finally:
        writer.close()
    with pytest.raises(RingError, match="closed"):
        writer.write(*pair(1, 4, 6), t_exposure_ns=0)


def _other_process_writer(name: str) -> None:
    """Create a writer under ``name`` while pretending to be another process."""
    import os
    from unittest import mock

    with mock.patch.object(os, "getpid", return_value=os.getpid() + 1):
        RingWriter(name, HEIGHT, WIDTH)


def _finished_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid
