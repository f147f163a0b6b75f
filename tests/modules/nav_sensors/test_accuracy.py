"""The navigation accuracy tool: a replay of the default scenario through both filters."""

from __future__ import annotations

import math

import pytest

from modules.sim.nav.accuracy import evaluate, main
from modules.sim.scenario import DEFAULT_SCENARIO, load_scenario


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_replay_of_the_default_course_meets_the_accuracy_targets(kind: str) -> None:
    scenario = load_scenario(DEFAULT_SCENARIO)
    result = evaluate(scenario, kind, seed=3, duration_s=95.0, speed_mps=10.0, outage=(30.0, 90.0))
    assert result.position_rms_m <= 0.3
    assert result.heading_rms_deg <= 1.0
    assert result.speed_rms_mps <= 0.1
    assert result.outage_error_m[60.0] <= 1.0
    assert math.isnan(result.outage_error_m[180.0])  # the outage is only 60 s long
    assert result.min_eigenvalue > 0.0


def test_the_tool_prints_a_row_per_filter_and_seed(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--duration", "25", "--outage", "none", "--seeds", "2", "--filters", "ekf"]) == 0
    out = capsys.readouterr().out
    assert "Navigation accuracy: mojave, 25 s" in out
    assert out.count(" ekf ") == 2


@pytest.mark.parametrize(
    "args", [["--filters", "kalman"], ["--outage", "90:30"], ["--outage", "soon"], ["--duration", "5"]]
)
def test_bad_arguments_are_named(args: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        main(args)
    assert exited.value.code == 2
    assert "error:" in capsys.readouterr().err
