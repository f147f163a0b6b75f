"""Sensor failures on a whole-stack drive under `rascal run` (tests/integration/stack.py), each
placed on the course by the scenario's fault schedule (a [[fault]] with a from_m progress window):

- RASCAL's 2005 race failure: all four lidars fall silent at 60 % of the course. The brain drives
  on stereo alone below the stereo cap, and avoids a rock standing after that point.
- A GPS outage of over 60 s through an S-curve: the INS dead-reckons and the vehicle stays in the
  corridor.

Outcomes are asserted (modes, caps, referee measures), with generous deadlines; the measured
numbers are printed for docs/RELIABILITY.md.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pymap3d
import pytest

from brain.health import HealthParams, stopping_speed_mps
from protocol.messages import NavQuality
from protocol.messages import Path as PathMessage
from tests.integration.stack import NS, drive, max_gap_s, rddf, rock, scenario, write_deployment

pytestmark = pytest.mark.slow

ORIGIN = (34.865, -116.89)
PARAMS = HealthParams()  # the brain's defaults, which it runs with
STEREO_CAP_MPS = stopping_speed_mps(PARAMS.stereo_range_m, PARAMS)  # 10 m/s


def waypoints(enu: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """(lat, lon) of points given in metres east and north of ORIGIN."""
    out = []
    for east, north in enu:
        lat, lon, _alt = pymap3d.enu2geodetic(east, north, 0.0, *ORIGIN, 0.0)
        out.append((float(lat), float(lon)))
    return out


def _to(mode_text: str) -> str:
    """The mode a drive_mode event text ('normal -> stereo_only: why') enters."""
    return mode_text.split(" -> ")[1].split(":")[0]


def fastest(path: PathMessage) -> float:
    return max((point.speed_mps for point in path.points), default=0.0)


# -- the race failure -------------------------------------------------------------------------

# 350 m due east at 30 mph (13.4 m/s, above the stereo cap); lidars silent from 60 % (210 m) on;
# a rock at 80 %, near the centreline, that only the stereo can see by then.
RACE_LENGTH_M = 350.0
LIDARS_SILENT_FROM_M = 0.6 * RACE_LENGTH_M
ROCK_AT_M = 0.8 * RACE_LENGTH_M
RACE_SCENARIO = scenario(
    11,
    rock(ROCK_AT_M, 0.5),
    ("fault", {"sensors": ["lidars"], "kind": "silence", "start_s": 0.0, "from_m": LIDARS_SILENT_FROM_M}),
)


def test_lidars_silent_from_60_percent_finish_on_stereo_alone_below_its_cap(
    bus_url: str, key_file: Path, tmp_path: Path
) -> None:
    course = rddf(waypoints([(0.0, 0.0), (RACE_LENGTH_M, 0.0)]), width_ft=40, speed_mph=30)
    deploy = write_deployment(tmp_path, bus_url, course, RACE_SCENARIO)
    with drive(tmp_path, bus_url, key_file, deploy) as stack:
        onset_env, onset = stack.wait_for_progress(LIDARS_SILENT_FROM_M, 150.0)
        passed_env, _ = stack.wait_for_progress(ROCK_AT_M + 5.0, 60.0)
    drive_measures = stack.drive
    assert stack.summary["finished"] and drive_measures["finished"], stack.tail("did not finish")
    assert drive_measures["collisions"] == 0 and drive_measures["corridor_exits"] == 0, drive_measures
    assert drive_measures["min_clearance_m"] > 0.3, drive_measures

    # The brain notices: the first mode after the onset without lidars (stereo_only, or blind
    # when a stereo report is late too on a loaded machine), and it drives on stereo_only.
    stereo_only = stack.entered("stereo_only", onset_env.t_meas_ns)
    assert stereo_only is not None, stack.tail("never stereo_only")
    blind = stack.entered("blind", onset_env.t_meas_ns)
    event = min((e for e in (stereo_only, blind) if e is not None), key=lambda e: e.t_meas_ns)
    reaction_s = (event.t_meas_ns - onset_env.t_meas_ns) / NS
    # Generous: the lidar max age (0.2 s) and a planning cycle, with room for a loaded machine.
    assert 0.0 < reaction_s <= 1.0, stack.tail(f"no lidar-less mode until {reaction_s:.2f} s")
    before = [_to(text) for env, text in stack.modes() if env.t_meas_ns < onset_env.t_meas_ns]
    assert before and before[-1] in ("normal", "lidar_only"), stack.tail("the lidars were not live before")
    # Stereo alone until the rock is passed: the lidars never count as live again. (On a loaded
    # machine a late stereo report may flap it to blind, or a late vehicle state to nav_lost:
    # both only brake, so both are allowed.)
    during = [text for env, text in stack.modes() if event.t_meas_ns < env.t_meas_ns <= passed_env.t_meas_ns]
    wrong = [text for text in during if _to(text) not in ("stereo_only", "blind", "nav_lost")]
    assert not wrong, stack.tail(f"the lidars counted as live again: {wrong}")

    paths_before = [fastest(p) for env, p in stack.paths if env.t_pub_ns < onset_env.t_meas_ns]
    paths_after = [fastest(p) for env, p in stack.paths if env.t_pub_ns > event.t_pub_ns]
    assert max(paths_before) > STEREO_CAP_MPS + 1.0, "the course allowed more than the cap before"
    assert paths_after and max(paths_after) <= STEREO_CAP_MPS + 1e-6
    settled_ns = event.t_meas_ns + int(3.0 * NS)  # the speed controller follows the cap down
    speeds_before = [t.speed_mps for env, t in stack.truth if env.t_meas_ns < onset_env.t_meas_ns]
    speeds_after = [t.speed_mps for env, t in stack.truth if env.t_meas_ns >= settled_ns]
    assert max(speeds_after) <= STEREO_CAP_MPS + 0.3  # the PI controller's small overshoot

    # The rock was in the stereo's view, reported while the lidars were silent.
    seen = [m for env, m in stack.stereo if onset_env.t_meas_ns < env.t_meas_ns < passed_env.t_meas_ns]
    assert any(m.obstacles for m in seen), "the ESVS never reported the rock"
    first = "stereo_only" if event is stereo_only else "blind"
    print(
        f"\nlidars silent at {onset.progress_m:.0f} m ({onset.speed_mps:.1f} m/s): {first} after "
        f"{reaction_s * 1e3:.0f} ms; speed {max(speeds_before):.1f} m/s before, at most {max(speeds_after):.1f} "
        f"m/s after (cap {STEREO_CAP_MPS:.1f}); rock passed at {drive_measures['min_clearance_m']:.2f} m clearance; "
        f"{len(during) // 2} flaps to blind and back before it"
    )


# -- GPS outage through a curve ---------------------------------------------------------------

# 40 m east, then an S-curve of two 150 m arcs (radius 100 m, left then right), then 30 m straight:
# 370 m at 11 mph (4.9 m/s). The GPS is out from 40 m to 350 m: at most 4.9 m/s, over 60 s.
ARC_RADIUS_M = 100.0
ARC_LENGTH_M = 150.0
GPS_OUT_FROM_M, GPS_OUT_TO_M = 40.0, 350.0
OUTAGE_S = 60.0
CURVE_SCENARIO = scenario(
    13,
    ("fault", {"sensors": ["gps"], "kind": "outage", "start_s": 0.0, "from_m": GPS_OUT_FROM_M, "to_m": GPS_OUT_TO_M}),
)


def s_curve() -> list[tuple[float, float]]:
    """ENU waypoints of the S-curve course, every 10 m along each arc."""
    points = [(0.0, 0.0), (40.0, 0.0)]
    east, north, heading = 40.0, 0.0, 0.0
    for turn in (1.0, -1.0):  # left, then right
        steps = round(ARC_LENGTH_M / 10.0)
        for _ in range(steps):
            heading += turn * (ARC_LENGTH_M / steps) / ARC_RADIUS_M
            east += 10.0 * math.cos(heading)
            north += 10.0 * math.sin(heading)
            points.append((east, north))
    points.append((east + 30.0 * math.cos(heading), north + 30.0 * math.sin(heading)))
    return points


def test_a_gps_outage_over_60_s_through_a_curve_stays_in_the_corridor(
    bus_url: str, key_file: Path, tmp_path: Path
) -> None:
    course = rddf(waypoints(s_curve()), width_ft=40, speed_mph=11)
    deploy = write_deployment(tmp_path, bus_url, course, CURVE_SCENARIO)
    with drive(tmp_path, bus_url, key_file, deploy) as stack:
        onset_env, _ = stack.wait_for_progress(GPS_OUT_FROM_M, 150.0)
        stack.wait_for_progress(GPS_OUT_TO_M + 10.0, 150.0)
    drive_measures = stack.drive
    assert stack.summary["finished"] and drive_measures["finished"], stack.tail("did not finish")
    assert drive_measures["corridor_exits"] == 0 and drive_measures["collisions"] == 0, drive_measures

    fixes = [env.t_meas_ns for env in stack.gps]
    outage_s = max_gap_s(fixes)
    assert outage_s >= OUTAGE_S, f"the GPS was out for {outage_s:.1f} s only"
    # The INS knew: dead reckoning for the outage (less its GPS max age), then DGPS again.
    spans = itertools.pairwise(stack.nav_quality)
    reckoned = [
        (b[0] - a[0]) / NS for a, b in spans if a[1] == NavQuality.DEAD_RECKONING and a[0] > onset_env.t_meas_ns
    ]
    assert reckoned and max(reckoned) >= OUTAGE_S - 1.0, stack.nav_quality
    assert stack.nav_quality[-1][1] == NavQuality.DGPS
    measures = ", ".join(
        f"{key} {drive_measures[key]}" for key in ("cross_track_rms_m", "cross_track_max_m", "mean_speed_mps")
    )
    print(
        f"\nGPS out {outage_s:.1f} s through the S-curve (INS dead reckoning {max(reckoned):.1f} s): "
        f"corridor exits {drive_measures['corridor_exits']}; {measures}"
    )
