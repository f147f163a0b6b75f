"""The map on the wire: hazard probability as MapSnapshot (x255 uint8, row 0 south, zlib).

A snapshot is for viewers and logs, at a low rate. ``downsample`` merges k x k cells into one,
keeping the highest probability of each block so no hazard vanishes from a coarser picture.
Decoding checks everything a peer controls: sizes, the resolution, and the inflated length
(a small zlib body must not be able to expand without bound).
"""

from __future__ import annotations

import math
import zlib

import numpy as np
from numpy.typing import NDArray

from brain.grid import GridWindow
from protocol.messages import MapSnapshot

MAX_CELLS = 4096 * 4096


class SnapshotError(ValueError):
    """A MapSnapshot that cannot be decoded; the message says why."""


def encode_snapshot(
    window: GridWindow, hazard_probability: NDArray[np.floating], downsample: int = 1, level: int = 1
) -> MapSnapshot:
    """The snapshot of a probability layer laid out on ``window``."""
    if hazard_probability.shape != window.shape:
        raise ValueError(f"probability layer {hazard_probability.shape} does not match the window {window.shape}")
    if downsample < 1:
        raise ValueError(f"downsample must be a positive integer, got {downsample}")
    p = np.asarray(hazard_probability, dtype=np.float32)
    if downsample > 1:
        rows, cols = -(-window.rows // downsample), -(-window.cols // downsample)
        padded = np.zeros((rows * downsample, cols * downsample), dtype=np.float32)
        padded[: window.rows, : window.cols] = p
        p = padded.reshape(rows, downsample, cols, downsample).max(axis=(1, 3))
        window = GridWindow(window.origin_east_m, window.origin_north_m, window.resolution_m * downsample, rows, cols)
    cells = np.rint(np.clip(p, 0.0, 1.0) * 255.0).astype(np.uint8)
    return MapSnapshot(
        float(window.origin_east_m),
        float(window.origin_north_m),
        float(window.resolution_m),
        window.rows,
        window.cols,
        zlib.compress(cells.tobytes(), level),
    )


def decode_snapshot(snapshot: MapSnapshot) -> tuple[GridWindow, NDArray[np.float32]]:
    """The window and hazard probability (multiples of 1/255) a snapshot carries."""
    rows, cols = snapshot.rows, snapshot.cols
    if not (rows > 0 and cols > 0 and rows * cols <= MAX_CELLS):
        raise SnapshotError(f"map size {rows} x {cols} is outside 1..{MAX_CELLS} cells")
    values = (snapshot.origin_east_m, snapshot.origin_north_m, snapshot.resolution_m)
    if not all(math.isfinite(v) for v in values) or not snapshot.resolution_m > 0:
        raise SnapshotError(f"map origin and resolution must be finite and the resolution positive, got {values}")
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(snapshot.cells, rows * cols + 1)
    except zlib.error as exc:
        raise SnapshotError(f"map cells are not zlib data: {exc}") from exc
    if len(raw) != rows * cols or not inflater.eof:
        size = f"{len(raw)}{'' if inflater.eof else '+'}"
        raise SnapshotError(f"map cells inflate to {size} bytes, not {rows} x {cols} = {rows * cols}")
    window = GridWindow(snapshot.origin_east_m, snapshot.origin_north_m, snapshot.resolution_m, rows, cols)
    probability = np.frombuffer(raw, dtype=np.uint8).reshape(rows, cols).astype(np.float32) / np.float32(255.0)
    return window, probability
