"""Stalls: the vehicle standing (below 0.1 m/s) for over 30 s before the finish, once per stop."""

from __future__ import annotations

import pytest

from modules.referee.measures import STALL_TIME_S, Referee
from modules.sim.scenario import DEFAULT_SCENARIO, Scenario, load_scenario
from protocol.messages import SimTruth

STEP_S = 0.1


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    return load_scenario(DEFAULT_SCENARIO)


def _drive(referee: Referee, plan: list[tuple[float, float]], progress_m: float = 10.0, start_s: float = 0.0) -> float:
    """Feed truth at the start of the course: ``plan`` is (speed m/s, seconds) in turn."""
    t = start_s
    for speed, seconds in plan:
        for _ in range(round(seconds / STEP_S)):
            t += STEP_S
            referee.on_truth(SimTruth(0.0, 0.0, 0.0, speed, 0.0, 0.0, progress_m, 0, scenario_time_s=t))
    return t


def _stalls(scenario: Scenario, plan: list[tuple[float, float]]) -> int:
    referee = Referee(scenario)
    _drive(referee, plan)
    return referee.result().stalls


def test_a_stop_longer_than_the_limit_is_one_stall(scenario: Scenario) -> None:
    assert _stalls(scenario, [(3.0, 5.0), (0.0, STALL_TIME_S + 1.0), (3.0, 5.0)]) == 1


def test_a_shorter_stop_is_none(scenario: Scenario) -> None:
    assert _stalls(scenario, [(3.0, 5.0), (0.05, STALL_TIME_S - 1.0), (3.0, 5.0)]) == 0


def test_a_long_stop_counts_once_and_each_stop_counts(scenario: Scenario) -> None:
    assert _stalls(scenario, [(0.0, 5 * STALL_TIME_S)]) == 1
    assert _stalls(scenario, [(0.0, 40.0), (2.0, 1.0), (0.0, 40.0), (2.0, 1.0), (0.0, 10.0)]) == 2


def test_never_starting_is_a_stall(scenario: Scenario) -> None:
    assert _stalls(scenario, [(0.0, STALL_TIME_S + 0.5)]) == 1


def test_reversing_is_not_standing(scenario: Scenario) -> None:
    assert _stalls(scenario, [(-0.5, 2 * STALL_TIME_S)]) == 0


def test_standing_after_the_finish_is_not_a_stall(scenario: Scenario) -> None:
    referee = Referee(scenario)
    t = _drive(referee, [(3.0, 5.0)])
    _drive(referee, [(0.0, 3 * STALL_TIME_S)], progress_m=scenario.route.length_m, start_s=t)
    result = referee.result()
    assert result.finished and result.stalls == 0


def test_the_stop_is_timed_on_scenario_time_not_samples(scenario: Scenario) -> None:
    """Truth samples lost on the bus do not shorten a stop: two samples 31 s apart are a stall."""
    referee = Referee(scenario)
    for t in (1.0, 32.0):
        referee.on_truth(SimTruth(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 10.0, 0, scenario_time_s=t))
    assert referee.result().stalls == 1
    assert referee.result().as_dict()["stalls"] == 1
