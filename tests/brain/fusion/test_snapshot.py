"""MapSnapshot: the hazard layer survives the wire to within 1/255, and bad snapshots are refused."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from brain.fusion import SnapshotError, decode_snapshot, encode_snapshot
from brain.grid import GridWindow
from protocol.codec import Codec, decode_body
from protocol.messages import MapSnapshot, Sensor
from tests.brain.fusion.helpers import box, obstacles, parked

WINDOW = GridWindow(-31.4, 1022.6, 0.2, rows=150, cols=600)


def test_round_trip_through_the_wire_codec() -> None:
    rng = np.random.default_rng(7)
    probability = rng.random(WINDOW.shape, dtype=np.float32)
    snapshot = encode_snapshot(WINDOW, probability)
    (window, decoded) = decode_snapshot(snapshot)
    assert window == WINDOW
    assert decoded.dtype == np.float32 and decoded.shape == WINDOW.shape
    assert np.max(np.abs(decoded - probability)) <= 0.5 / 255 + 1e-6
    # Row 0 is the southern edge on the wire as in the grid.
    raw = np.frombuffer(zlib.decompress(snapshot.cells), dtype=np.uint8).reshape(WINDOW.shape)
    assert raw[0, 0] == round(float(probability[0, 0]) * 255)


def test_a_fused_map_snapshot_round_trips() -> None:
    fusion = parked(10.0, 20.0, 1.0)
    for _ in range(3):
        fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT, box(15.0, 1.0)))
    snapshot = fusion.snapshot()
    window, decoded = decode_snapshot(snapshot)
    cost_map = fusion.cost_map()
    assert window == cost_map.window
    assert np.max(np.abs(decoded - cost_map.hazard_probability)) <= 0.5 / 255 + 1e-6
    assert len(snapshot.cells) < 64 * 1024  # well inside a bus message (256 KiB)


def test_downsampling_keeps_every_hazard() -> None:
    probability = np.full(WINDOW.shape, 0.5, dtype=np.float32)
    probability[149, 599] = 0.97  # the last cell: a partial block once the size is not a multiple
    probability[10, 10] = 0.1
    window, decoded = decode_snapshot(encode_snapshot(WINDOW, probability, downsample=4))
    assert (window.rows, window.cols, window.resolution_m) == (38, 150, pytest.approx(0.8))
    assert (window.origin_east_m, window.origin_north_m) == (WINDOW.origin_east_m, WINDOW.origin_north_m)
    assert decoded[37, 149] == pytest.approx(0.97, abs=0.002)
    assert decoded[2, 2] == pytest.approx(0.5, abs=0.002)  # a block's highest value wins


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({"rows": 0}, "size"),
        ({"cols": 5000, "rows": 5000}, "size"),
        ({"resolution_m": 0.0}, "resolution"),
        ({"cells": b"not zlib"}, "zlib"),
        ({"cells": zlib.compress(bytes(10))}, "inflate"),
        ({"cells": zlib.compress(bytes(150 * 600 + 1))}, "inflate"),
        ({"cells": zlib.compress(bytes(150 * 600))[:-6]}, "inflate"),  # truncated stream
    ],
)
def test_bad_snapshots_raise_a_clear_error(change: dict, reason: str) -> None:
    good = encode_snapshot(WINDOW, np.zeros(WINDOW.shape, dtype=np.float32))
    with pytest.raises(SnapshotError, match=reason):
        decode_snapshot(good._replace(**change))


def test_a_decompression_bomb_is_refused_without_inflating_it() -> None:
    bomb = MapSnapshot(0.0, 0.0, 0.2, 10, 10, zlib.compress(bytes(4_000_000)))
    with pytest.raises(SnapshotError, match="inflate"):
        decode_snapshot(bomb)


def test_encoding_checks_its_input() -> None:
    with pytest.raises(ValueError):
        encode_snapshot(WINDOW, np.zeros((3, 3), dtype=np.float32))
    with pytest.raises(ValueError):
        encode_snapshot(WINDOW, np.zeros(WINDOW.shape, dtype=np.float32), downsample=0)


def test_snapshot_is_a_valid_bus_message() -> None:
    fusion = parked(10.0, 20.0, 1.0)
    fusion.add_obstacles(0, obstacles(Sensor.LIDAR_H_LEFT, box(15.0, 1.0)))
    snapshot = fusion.snapshot()
    codec = Codec(None)
    opened = codec.open(codec.encode(b"MAP_SNAPSHOT", snapshot, 1, 1, 0, 0))
    assert decode_body(opened.type_id, opened.body) == snapshot
