"""Vertical lidar: the profile follows the terrain, and detect_hazards finds each hazard."""

from __future__ import annotations

import math

import numpy as np
import pytest

from brain.pose import Pose
from modules.lidar.profile import VERTICAL_MOUNTS, Hazard, VerticalMount, detect_hazards
from modules.sim.lidar.profile import first_hits, profile_scan
from modules.sim.terrain import ground_height
from modules.sim.world import HazardKind, TerrainHazard
from protocol.messages import Sensor, SurfaceProfile

MOUNT = VERTICAL_MOUNTS["lidar_v_left"]
POSE = Pose(30.0, -20.0, 0.7)


def crossing(
    kind: HazardKind, start_m: float, length_m: float, magnitude_m: float, lateral_m: float = 0.0, width_m: float = 8.0
) -> TerrainHazard:
    """A hazard across the vehicle's path whose near edge is ``start_m`` ahead (vehicle x),
    centred ``lateral_m`` to the left."""
    centre = start_m + length_m / 2
    c, s = math.cos(POSE.yaw_rad), math.sin(POSE.yaw_rad)
    east, north = POSE.east_m + c * centre - s * lateral_m, POSE.north_m + s * centre + c * lateral_m
    return TerrainHazard("h", kind, east, north, POSE.yaw_rad, length_m, width_m, magnitude_m)


def scan(hazards: list[TerrainHazard], noise: bool = False, mount: VerticalMount = MOUNT) -> SurfaceProfile:
    rng = np.random.default_rng(11) if noise else None
    return profile_scan(hazards, POSE, mount, int(Sensor.LIDAR_V_LEFT), rng)


def terrain_under(profile: SurfaceProfile, hazards: list[TerrainHazard]) -> np.ndarray:
    """The model's ground height below each return (vehicle x -> ENU along the scan line)."""
    x = np.asarray(profile.ranges_m)
    c, s = math.cos(POSE.yaw_rad), math.sin(POSE.yaw_rad)
    east = POSE.east_m + c * x - s * profile.lateral_m
    north = POSE.north_m + s * x + c * profile.lateral_m
    return ground_height(hazards, east, north)


def test_flat_ground_is_level_from_near_to_far() -> None:
    profile = scan([], noise=True)
    assert profile.lateral_m == 0.5 and profile.sensor == Sensor.LIDAR_V_LEFT
    assert len(profile.ranges_m) == len(MOUNT.depressions_rad())
    assert np.all(np.diff(profile.ranges_m) > 0)
    assert profile.ranges_m[0] == pytest.approx(MOUNT.x_m + MOUNT.near_m, abs=0.05)
    assert profile.ranges_m[-1] == pytest.approx(MOUNT.x_m + MOUNT.far_m, abs=3.5)  # the last 0.5 deg step
    assert np.max(np.abs(profile.heights_m)) < 0.01
    assert detect_hazards(profile) == []


@pytest.mark.parametrize(
    ("kind", "length", "magnitude"),
    [(HazardKind.DITCH, 3.0, 0.6), (HazardKind.BERM, 2.0, 0.4), (HazardKind.DROP_OFF, 40.0, 1.0)],
)
def test_every_return_lies_on_the_terrain(kind: HazardKind, length: float, magnitude: float) -> None:
    hazards = [crossing(kind, 7.0, length, magnitude)]
    profile = scan(hazards)
    assert np.max(np.abs(np.asarray(profile.heights_m) - terrain_under(profile, hazards))) < 0.01


def test_a_ditch_reads_down_then_up_with_its_near_wall_in_shadow() -> None:
    hazards = [crossing(HazardKind.DITCH, 7.0, 3.0, 0.6)]
    profile = scan(hazards)
    x, z = np.asarray(profile.ranges_m), np.asarray(profile.heights_m)
    assert np.all(z[x < 7.0] > -0.01)  # level up to the edge
    bottom = (x > 7.6) & (x < 9.4)  # between the 45 deg walls
    assert bottom.any() and np.allclose(z[bottom], -0.6, atol=0.01)
    assert np.all(z[x > 10.0] > -0.01)  # and level again after
    assert not np.any((x > 7.0) & (x < 7.6))  # the wall facing away is never hit


def test_a_berm_rises_and_hides_what_is_behind_it() -> None:
    profile = scan([crossing(HazardKind.BERM, 7.0, 2.0, 0.4)])
    x, z = np.asarray(profile.ranges_m), np.asarray(profile.heights_m)
    assert np.allclose(z[(x > 7.4) & (x < 8.6)], 0.4, atol=0.01)  # its crest
    assert not np.any((x > 8.6) & (x < 9.0))  # its far wall, in shadow


def test_a_drop_off_stays_down() -> None:
    profile = scan([crossing(HazardKind.DROP_OFF, 7.0, 40.0, 1.0)])
    x, z = np.asarray(profile.ranges_m), np.asarray(profile.heights_m)
    assert np.allclose(z[x > 7.3], -1.0, atol=0.01)


@pytest.mark.parametrize("start", [5.0, 6.5, 8.0, 9.5])
@pytest.mark.parametrize(
    ("kind", "length", "magnitude"),
    [(HazardKind.DITCH, 3.0, 0.6), (HazardKind.BERM, 2.0, 0.4), (HazardKind.DROP_OFF, 40.0, 1.0)],
)
def test_detect_hazards_finds_each_kind_where_it_is(
    kind: HazardKind, length: float, magnitude: float, start: float
) -> None:
    # Edges within ~10 m: beyond, 0.5 deg beams land more than a metre apart (see profile.py).
    found = detect_hazards(scan([crossing(kind, start, length, magnitude)], noise=True))
    assert len(found) == 1
    hazard = found[0]
    assert hazard.kind is kind
    assert abs(hazard.start_range_m - start) <= 0.5
    if kind is HazardKind.DITCH:
        assert abs(hazard.end_range_m - (start + length)) <= 0.5
        assert 0.15 < hazard.magnitude_m <= magnitude + 0.03  # the bottom may be partly hidden
    elif kind is HazardKind.BERM:
        assert hazard.end_range_m >= start + length - 0.5  # its far side hides in its shadow
        assert hazard.magnitude_m == pytest.approx(magnitude, abs=0.03)
    else:
        assert hazard.end_range_m > start + 10.0
        assert hazard.magnitude_m == pytest.approx(magnitude, abs=0.03)


def test_detect_hazards_reads_a_profile_alone() -> None:
    # Pure function of the message: level, a step down behind a shadow, level again, a rise.
    profile = SurfaceProfile(
        int(Sensor.LIDAR_V_RIGHT),
        -0.5,
        (5.0, 5.2, 5.4, 6.5, 6.8, 7.0, 7.2, 7.4, 7.6, 9.0, 9.3),
        (0.0, 0.0, 0.0, -0.5, -0.4, -0.1, 0.0, 0.0, 0.3, 0.0, 0.0),
    )
    assert detect_hazards(profile) == [
        Hazard(HazardKind.DITCH, pytest.approx(5.5), 7.0, 0.5),
        Hazard(HazardKind.BERM, pytest.approx(7.5), 9.0, 0.3),
    ]


def test_the_two_vertical_lidars_look_down_either_side() -> None:
    assert VERTICAL_MOUNTS["lidar_v_left"].y_m == 0.5 and VERTICAL_MOUNTS["lidar_v_right"].y_m == -0.5
    # A ditch narrower than the track, under the left lidar only.
    left_only = [crossing(HazardKind.DITCH, 7.0, 3.0, 0.5, lateral_m=0.6, width_m=0.6)]
    assert len(detect_hazards(profile_scan(left_only, POSE, VERTICAL_MOUNTS["lidar_v_left"], 3))) == 1
    assert detect_hazards(profile_scan(left_only, POSE, VERTICAL_MOUNTS["lidar_v_right"], 4)) == []


def traced_everywhere(hazards: list[TerrainHazard], mount: VerticalMount = MOUNT) -> SurfaceProfile:
    """The profile with every beam traced through every ground sample out to the last: what
    profile_scan finds by tracing only the samples around the hazards."""
    depressions = mount.depressions_rad()
    reach = mount.max_range_m * math.cos(depressions[-1])
    along = np.arange(0.0, reach + 0.05, 0.05)
    c, s = math.cos(POSE.yaw_rad), math.sin(POSE.yaw_rad)
    east = POSE.east_m + c * mount.x_m - s * mount.y_m
    north = POSE.north_m + s * mount.x_m + c * mount.y_m
    ground = ground_height(hazards, east + c * along, north + s * along)
    distance, height = first_hits(along, ground, mount.z_m, np.tan(depressions))
    hit = np.isfinite(distance) & (np.hypot(distance, mount.z_m - height) <= mount.max_range_m)
    return SurfaceProfile(
        int(Sensor.LIDAR_V_LEFT), mount.y_m, tuple((mount.x_m + distance[hit]).tolist()), tuple(height[hit].tolist())
    )


@pytest.mark.parametrize("seed", range(12))
def test_tracing_only_around_the_hazards_finds_what_tracing_everywhere_does(seed: int) -> None:
    rng = np.random.default_rng(seed)
    kinds = (HazardKind.DITCH, HazardKind.BERM, HazardKind.DROP_OFF)
    hazards = [
        crossing(
            kinds[int(rng.integers(3))],
            float(rng.uniform(-5.0, 30.0)),
            float(rng.uniform(0.5, 12.0)),
            float(rng.uniform(0.1, 1.5)),
            lateral_m=float(rng.uniform(-3.0, 3.0)),
            width_m=float(rng.uniform(0.5, 10.0)),
        )
        for _ in range(int(rng.integers(0, 4)))
    ]
    assert scan(hazards) == traced_everywhere(hazards)
