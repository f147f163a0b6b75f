"""Measurement-to-actuator latency, from what a recording already holds: each PATH says how old
the obstacle picture it was planned from was (``Path.t_input_ns``), and the first
ACTUATOR_COMMAND published after that PATH is the first that used it (control follows the
newest path it holds at every cycle)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray


def measurement_to_actuator_ms(
    paths: Sequence[tuple[int, int]], commands_t_pub_ns: Sequence[int]
) -> NDArray[np.float64]:
    """Per path with a known input time: the first later command's publication minus the path's
    oldest input measurement, in ms. ``paths`` is (PATH t_pub_ns, t_input_ns) pairs."""
    if not paths or not commands_t_pub_ns:
        return np.zeros(0)
    commands = np.sort(np.asarray(commands_t_pub_ns, dtype=np.int64))
    published, inputs = (np.asarray(column, dtype=np.int64) for column in zip(*paths, strict=True))
    first = np.searchsorted(commands, published, side="right")
    used = (first < len(commands)) & (inputs > 0)
    return (commands[first[used]] - inputs[used]) / 1e6


def summarise(latency_ms: NDArray[np.float64]) -> dict[str, float | int]:
    """p50, p99, max (ms) and the sample count, for summary.json; empty with no samples."""
    if not len(latency_ms):
        return {}
    p50, p99 = np.percentile(latency_ms, [50, 99])
    return {
        "p50": round(float(p50), 1),
        "p99": round(float(p99), 1),
        "max": round(float(latency_ms.max()), 1),
        "samples": len(latency_ms),
    }
