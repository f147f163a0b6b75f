"""Helpers for frame-ring tests: unique ring names, cleaned up afterwards, and test pairs."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from contextlib import suppress
from multiprocessing.shared_memory import SharedMemory

import numpy as np

from modules.esvs.frames import _untracked

HEIGHT, WIDTH = 490, 656


def unique_name() -> str:
    return f"rascal-test-{uuid.uuid4().hex[:12]}"


def unlink(name: str) -> None:
    """Remove a ring a test left behind (e.g. one whose writer was killed)."""
    with suppress(FileNotFoundError), _untracked():
        segment = SharedMemory(name=name)
        segment.close()
        segment.unlink()


def ring_name_fixture() -> Iterator[str]:
    name = unique_name()
    try:
        yield name
    finally:
        unlink(name)


def pair(value: int, height: int = HEIGHT, width: int = WIDTH) -> tuple[np.ndarray, np.ndarray]:
    """A recognisable pair: left filled with ``value``, right with ``value + 1`` (mod 256)."""
    left = np.full((height, width), value % 256, dtype=np.uint8)
    right = np.full((height, width), (value + 1) % 256, dtype=np.uint8)
    return left, right
