"""Measurement-to-actuator latency from a recording's PATH and ACTUATOR_COMMAND stamps."""

from __future__ import annotations

import numpy as np
import pytest

from rascal.latency import measurement_to_actuator_ms, summarise

MS = 1_000_000


def test_each_path_is_measured_to_the_first_command_after_it() -> None:
    # Paths published at 100 and 200 ms from inputs measured at 40 and 150 ms; commands every 20 ms.
    paths = [(100 * MS, 40 * MS), (200 * MS, 150 * MS)]
    commands = list(range(0, 300 * MS, 20 * MS))
    assert measurement_to_actuator_ms(paths, commands).tolist() == [80.0, 70.0]  # 120 - 40, 220 - 150


def test_unknown_inputs_and_paths_no_command_followed_are_left_out() -> None:
    paths = [(100 * MS, 0), (150 * MS, 90 * MS), (400 * MS, 350 * MS)]
    commands = [160 * MS, 120 * MS]  # in any order
    assert measurement_to_actuator_ms(paths, commands).tolist() == [70.0]
    assert len(measurement_to_actuator_ms([], commands)) == 0
    assert len(measurement_to_actuator_ms(paths, [])) == 0


def test_the_summary_gives_percentiles_and_nothing_for_no_samples() -> None:
    summary = summarise(np.arange(1.0, 101.0))
    assert summary["p50"] == pytest.approx(50.5) and summary["p99"] == pytest.approx(99.0, abs=0.1)
    assert summary["max"] == 100.0 and summary["samples"] == 100
    assert summarise(np.zeros(0)) == {}
