"""The whole stack drives a short course: simulator, navigation sensors, four lidars, stereo
camera and ESVS, INS, brain and control, each its own process on the signed loopback bus under
`rascal run` (tests/integration/stack.py). Mid-drive the brain hangs (SIGSTOP): control brakes within
its path timeout and slows or stops the vehicle, the supervisor kills the silent brain and restarts
it, and the drive resumes and finishes with no collision. (A hang, not a kill: a killed brain can be
back within control's path timeout, and then there is no stale path to brake for.)"""

from __future__ import annotations

import itertools
import math
import os
import signal
import time
from pathlib import Path

import pytest

from tests.integration.stack import drive, rock, scenario, write_deployment
from tests.integration.test_supervisor import pids_of

pytestmark = pytest.mark.slow

# About 300 m: east, then a gentle bend to the north-east; 25 mph limit, 40 ft boundary.
RDDF = "1,34.8650000,-116.8900000,40,25\n2,34.8650000,-116.8880000,40,25\n3,34.8660000,-116.8870000,40,25\n"
SCENARIO = scenario(3, rock(120.0, 0.8))
BRAIN_HANGS_AT_M = 90.0
PATH_MAX_AGE_S = 0.5  # control's default
STOPPED_MPS = 0.3


def test_the_stack_drives_a_short_course_and_survives_losing_the_brain(
    bus_url: str, key_file: Path, tmp_path: Path
) -> None:
    deploy = write_deployment(tmp_path, bus_url, RDDF, SCENARIO)
    with drive(tmp_path, bus_url, key_file, deploy) as stack:
        stack.wait_for_progress(BRAIN_HANGS_AT_M, 150.0)
        (brain,) = pids_of("brain", bus_url)
        hung_at, hung_ns = time.monotonic(), stack.listener.clock.now_ns()
        speed = stack.truth[-1][1].speed_mps
        os.kill(brain, signal.SIGSTOP)

        def path_stale_brakes() -> list[float]:
            return [t for t, _env, c in stack.commands if t > hung_at and c.brake >= 0.99 and "PATH" in c.stop_reason]

        def replanned() -> int | None:
            return next((env.t_pub_ns for env, _path in stack.paths if env.t_pub_ns > hung_ns), None)

        assert stack.wait(lambda: bool(path_stale_brakes()), 5.0), stack.tail("control did not brake")
        reaction_s = path_stale_brakes()[0] - hung_at
        assert reaction_s <= PATH_MAX_AGE_S + 0.15  # the path's age limit, plus one 50 Hz control tick and slack
        assert stack.wait(lambda: replanned() is not None, 30.0), stack.tail("the brain did not come back")
    # Control held full brake from the stale path until the restarted brain planned again, and the
    # vehicle slowed all the while (to a stop, unless the brain came back first).
    back_ns = replanned()
    assert back_ns is not None
    first_brake = next(env.t_pub_ns for t, env, _c in stack.commands if t == path_stale_brakes()[0])
    held = [c for _t, env, c in stack.commands if first_brake <= env.t_pub_ns < back_ns]
    assert held and all(c.brake >= 0.99 and c.throttle == 0.0 for c in held), "control let go before the brain was back"
    braking = [t.speed_mps for env, t in stack.truth if first_brake <= env.t_meas_ns < back_ns]
    assert all(b <= a + 0.05 for a, b in itertools.pairwise(braking)), "the vehicle sped up without a path"
    stop_ns = next(
        (env.t_meas_ns for env, t in stack.truth if hung_ns < env.t_meas_ns and t.speed_mps < STOPPED_MPS), None
    )
    back_s = (back_ns - hung_ns) / 1e9
    stop_s = (stop_ns - hung_ns) / 1e9 if stop_ns is not None else math.inf
    # The supervisor kills the hung brain after its heartbeat timeout and restarts it at once:
    # while the brake was held the vehicle lost 1 m/s per second of it after
    # 0.2 s of actuator lag (full brake is 6 m/s^2), at most 1 m/s in all.
    held_s = (back_ns - first_brake) / 1e9
    speed_back = [t.speed_mps for env, t in stack.truth if env.t_meas_ns < back_ns][-1]
    slowed_by = braking[0] - braking[-1] if braking else 0.0
    assert stop_s <= back_s or slowed_by >= min(1.0, held_s - 0.2), stack.tail("not slowing")
    stopped = f"stopped after {stop_s:.1f} s" if stop_s <= back_s else f"at {speed_back:.1f} m/s"
    print(
        f"\nbrain hung at {BRAIN_HANGS_AT_M:.0f} m, {speed:.1f} m/s: control braking after {reaction_s * 1000:.0f} "
        f"ms, {stopped} when the brain planned again after {back_s:.1f} s"
    )
    drive_measures = stack.drive
    assert stack.summary["finished"] and drive_measures["finished"]
    assert drive_measures["collisions"] == 0 and drive_measures["corridor_exits"] == 0
    assert drive_measures["cross_track_rms_m"] <= 0.3
    assert drive_measures["min_clearance_m"] > 0.3
    assert stack.summary["modules"]["brain"]["restarts"] == 1
