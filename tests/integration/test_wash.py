"""The whole stack meets the default scenario's wash on a short straight: a ditch 13.8 m wide
across a road whose corridor is 18 m wide, so the only way on is round one end, through a band
about half a metre wide between the gate's clearances. The sweeping lidar sees the wash 37 m
ahead; the stereo cameras lose it inside 10 m, and so does everything else once the vehicle
stops to look for that band. This is where the drive benchmark's seeds failed: the vehicle must
remember the wash while it stands in front of it, and find the band without a wheel in it."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.integration.stack import drive, rddf, scenario, write_deployment

pytestmark = pytest.mark.slow

# 330 m due east at 30 mph with a 30 ft boundary (the default course's, at its wash).
RDDF = rddf([(34.8650000, -116.8900000), (34.8650000, -116.8863900)], width_ft=30, speed_mph=30)
WASH = ("hazard", {"name": "wash", "kind": "ditch", "at_m": 170.0, "length_m": 2.5, "width_m": 13.8, "depth_m": 0.7})


def test_the_stack_finds_the_way_round_the_wash(bus_url: str, key_file: Path, tmp_path: Path) -> None:
    deploy = write_deployment(tmp_path, bus_url, RDDF, scenario(7, WASH))
    with drive(tmp_path, bus_url, key_file, deploy, duration_s=200.0, images=True) as stack:
        stack.wait_for_progress(200.0, 200.0)
    measures = stack.drive
    assert measures["finished"], stack.tail("the drive did not finish")
    assert measures["hazard_entries"] == 0, stack.tail("a wheel went into the wash")
    assert measures["collisions"] == 0 and measures["corridor_exits"] == 0
    # The end of every run: its report, drawn (the other drives skip the images) and summarised.
    assert stack.run_dir is not None
    drawn = sorted(path.name for path in (stack.run_dir / "report").iterdir())
    assert drawn == sorted(
        f"{name}.{kind}" for name in ("track", "map", "speed", "cross_track", "timing") for kind in ("png", "svg")
    )
    assert stack.summary["latency_ms"]["obstacle_to_actuator"]["samples"] > 0
