"""A corridor truly blocked: a wall of rocks across the whole corridor 120 m along a short course.
The vehicle stops before it, inside the corridor and clear of the rocks, and the brain says the
corridor is blocked within 5 s of the stop (a HealthEvent, counted in the run's summary) instead
of waiting on it silently."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.integration.stack import NS, drive, rddf, rock, scenario, write_deployment

pytestmark = pytest.mark.slow

# 330 m due east at 25 mph; a 20 ft boundary: a corridor 12.2 m wide.
RDDF = rddf([(34.8650000, -116.8900000), (34.8650000, -116.8863900)], width_ft=20, speed_mph=25)
WALL_AT_M = 120.0
WALL = [rock(WALL_AT_M, -5.5 + 1.0 * i) for i in range(12)]  # 1.2 m rocks 1 m apart, edge to edge
STOPPED_MPS = 0.1
REPORT_WITHIN_S = 5.0


def test_a_blocked_corridor_stops_the_vehicle_short_and_is_reported(
    bus_url: str, key_file: Path, tmp_path: Path
) -> None:
    unfair = scenario(5, *WALL).replace("seed = 5\n", "seed = 5\nfair = false\n")  # blocked on purpose
    deploy = write_deployment(tmp_path, bus_url, RDDF, unfair)
    with drive(tmp_path, bus_url, key_file, deploy, duration_s=150.0) as stack:
        stack.wait_for_progress(60.0, 60.0)

        def stopped_since() -> int | None:
            moving = [env.t_meas_ns for env, t in stack.truth if t.speed_mps >= STOPPED_MPS]
            return moving[-1] if moving and stack.truth[-1][1].speed_mps < STOPPED_MPS else None

        def reported() -> list[int]:
            return [env.t_pub_ns for env, e in stack.events if e.module == "brain" and e.code == "corridor_blocked"]

        assert stack.wait(lambda: stopped_since() is not None and bool(reported()), 90.0), stack.tail(
            "no stop and blockage report"
        )
        stop_ns = stopped_since()
        assert stop_ns is not None
        assert (reported()[0] - stop_ns) / NS <= REPORT_WITHIN_S
        truth = stack.truth[-1][1]
        assert truth.progress_m < WALL_AT_M - 0.6, "the vehicle reached the wall"
        assert stack.run is not None
        stack.run.terminate()  # stopped as asked: the summary is still written
    measures = stack.drive
    assert not measures["finished"]
    assert measures["collisions"] == 0 and measures["corridor_exits"] == 0 and measures["hazard_entries"] == 0
    assert stack.summary["health_events"].get("brain:corridor_blocked", 0) >= 1
