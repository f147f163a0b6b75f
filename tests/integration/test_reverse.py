"""Backing out of a dead end: the vehicle starts with its nose 1.0 m from a 4 m wide boulder in the
middle of a 9.8 m corridor. To pass it the rear axle must be 2.75 m off the centre line (half
the rock, half the vehicle, the margin) before its nose reaches the rock's face; with a 2.29 m
turning radius that cannot be done in 1 m. It has no trail yet, so the brain backs it straight
up behind the start (clear on the map, inside the corridor; the corridor's round end 4.9 m
behind the start stops it at about 3.6 m), then plans afresh and drives round the rock to the
finish, its front corners' swing kept clear of the rock and the edge: reverse gear, reverse
path, rear-axle tracking and the recovery, all in the closed loop. (A 5 m rock left a full-lock
S-bend as the only way round from there, found on some runs only after three back-ups.)"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.integration.stack import NS, drive, rddf, scenario, write_deployment

pytestmark = pytest.mark.slow

# 119 m due east at 15 mph; a 16 ft boundary: a corridor 9.8 m wide.
RDDF = rddf([(34.8650000, -116.8900000), (34.8650000, -116.8887000)], width_ft=16, speed_mph=15)
# 1 m deep, 4 m across (2.9 m of corridor either side): its near side 1.0 m from the nose (the
# front is 1.7 m ahead of the rear axle).
BOULDER = (
    "obstacle",
    {"name": "boulder", "shape": "box", "at_m": 3.2, "offset_m": 0.0, "length_m": 1.0, "width_m": 4.0, "height_m": 1.0},
)


def test_the_vehicle_backs_out_of_a_dead_end_and_drives_round(bus_url: str, key_file: Path, tmp_path: Path) -> None:
    deploy = write_deployment(tmp_path, bus_url, RDDF, scenario(11, BOULDER))
    with drive(tmp_path, bus_url, key_file, deploy, duration_s=120.0) as stack:
        stack.wait_for_progress(20.0, 110.0)
    backing = [env.t_pub_ns for env, e in stack.events if e.module == "brain" and e.code == "backing_up"]
    assert backing, stack.tail("no back-up")
    reversing = [env.t_meas_ns for env, t in stack.truth if t.speed_mps < -0.1]
    assert reversing, stack.tail("it never reversed")
    assert min(t.speed_mps for _env, t in stack.truth) >= -1.2  # the back-up's 1 m/s
    forward_again = next(env.t_meas_ns for env, t in stack.truth if env.t_meas_ns > reversing[-1] and t.speed_mps > 0.1)
    print(
        f"back-up: asked {backing[0] / NS:.1f}, reversing {(reversing[0] - backing[0]) / NS:.1f} s later "
        f"for {(reversing[-1] - reversing[0]) / NS:.1f} s, forward again {(forward_again - backing[0]) / NS:.1f} s "
        f"after the ask; {len(backing)} back-up(s)"
    )
    measures = stack.drive
    assert measures["finished"], stack.tail("the drive did not finish")
    assert measures["collisions"] == 0 and measures["corridor_exits"] == 0, stack.tail("collision or exit")
    # The planner's 0.15 m margin, less what tracking takes of it (0.36-0.61 m left, measured).
    assert measures["min_clearance_m"] >= 0.1, stack.tail("shaved the rock")
    assert stack.summary["health_events"].get("brain:backing_up", 0) >= 1
    # Run with --no-images: summarised, not drawn.
    assert stack.summary["latency_ms"]["obstacle_to_actuator"]["samples"] > 0
    assert stack.run_dir is not None and not (stack.run_dir / "report").exists()
