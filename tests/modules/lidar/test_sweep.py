"""The sweeping lidar: its ground line across the road, and what it makes of ditches, berms and obstacles."""

from __future__ import annotations

import math

import numpy as np
import pytest

from brain.pose import Pose
from modules.lidar.profile import VERTICAL_MOUNTS
from modules.lidar.sweep import SWEEP_MOUNT, SweepMount, describe_sweep
from modules.sim.lidar.profile import first_hits
from modules.sim.lidar.raycast import Scene, descending_ray_ranges
from modules.sim.lidar.sweep import sweep_scan
from modules.sim.terrain import ground_height
from modules.sim.world import HazardKind, Shape, TerrainHazard, WorldObstacle
from protocol.messages import GroundStretch, GroundSweep, Sensor

EMPTY = Scene.from_obstacles(())
LINE_M = SWEEP_MOUNT.x_m + SWEEP_MOUNT.ground_m  # the scan line, ahead of the rear axle
# The default scenario's wash: 2.5 m along the road, 14 m across it, 0.7 m deep.
WASH = dict(length_m=2.5, width_m=14.0, magnitude_m=0.7)
TRAVEL_PER_SWEEP_M = 13.4 / 37.5  # 30 mph at the deployment's 37.5 sweeps a second


AT_ORIGIN = Pose(0.0, 0.0, 0.0)


def sweep(
    hazards: tuple[TerrainHazard, ...] | list[TerrainHazard] = (),
    scene: Scene = EMPTY,
    pose: Pose = AT_ORIGIN,
    mount: SweepMount = SWEEP_MOUNT,
    rng: np.random.Generator | None = None,
) -> GroundSweep:
    return describe_sweep(sweep_scan(list(hazards), scene, pose, mount, rng), mount, int(Sensor.LIDAR_SWEEP))


def low_stretches(stretches: tuple[GroundStretch, ...]) -> list[GroundStretch]:
    return [stretch for stretch in stretches if stretch.height_m < 0]


def test_flat_ground_is_one_level_stretch_along_the_line() -> None:
    (level,) = sweep(rng=np.random.default_rng(1)).stretches
    assert level.height_m == 0.0
    assert level.x_near_m == pytest.approx(LINE_M, abs=0.05) and level.x_far_m == pytest.approx(LINE_M, abs=0.05)
    half = SWEEP_MOUNT.ground_m * math.tan(SWEEP_MOUNT.half_fov_rad)
    assert level.y_right_m == pytest.approx(-half, abs=0.05) and level.y_left_m == pytest.approx(half, abs=0.05)


def test_the_wash_is_found_end_to_end_in_every_sweep_while_the_line_crosses_it() -> None:
    rng = np.random.default_rng(2)
    found = []
    for k in range(12):
        centre = LINE_M - 1.0 + k * TRAVEL_PER_SWEEP_M  # the wash's centre as the vehicle comes on
        stretches = sweep([TerrainHazard("wash", HazardKind.DITCH, centre, 0.0, 0.0, **WASH)], rng=rng).stretches
        low = low_stretches(stretches)
        if not low:
            continue
        found.append(k)
        assert min(s.y_right_m for s in low) == pytest.approx(-7.0, abs=0.2)
        assert max(s.y_left_m for s in low) == pytest.approx(7.0, abs=0.2)
        # Pieces, not one box: 2 m, half a beam spacing either side, and a slab's slant (0.2 m).
        assert all(s.y_left_m - s.y_right_m <= 2.0 + 0.4 + 0.2 for s in low)
        # The low ground lies within the wash, and level ground is claimed only beside it.
        assert all(centre - 1.25 <= s.x_near_m <= s.x_far_m <= centre + 1.25 for s in low)
        level = [s for s in stretches if s.height_m == 0.0]
        assert all(s.y_left_m <= -6.5 or s.y_right_m >= 6.5 for s in level)
    # 1.4 m of travel at least: 4 sweeps at 30 mph.
    assert len(found) >= 4 and found == list(range(found[0], found[-1] + 1))


def test_a_wash_seen_at_an_angle_keeps_its_ends() -> None:
    yaw = math.radians(15.0)
    pose = Pose(0.0, 0.0, yaw)
    for ahead in np.arange(LINE_M - 2.0, LINE_M + 2.0, 0.25):  # wash centre straight down the road
        wash = TerrainHazard("wash", HazardKind.DITCH, ahead, 0.0, 0.0, **WASH)
        low = low_stretches(sweep([wash], pose=pose).stretches)
        # The corners of every low box, back in the world, lie in the wash or within 0.8 m of it:
        # boxes are square to the vehicle, and a 2 m piece turned by 15 deg reaches 0.52 m further.
        for s in low:
            for x, y in ((s.x_near_m, s.y_right_m), (s.x_far_m, s.y_left_m)):
                east, north = x * math.cos(yaw) - y * math.sin(yaw), x * math.sin(yaw) + y * math.cos(yaw)
                assert abs(north) <= 7.0 + 0.8 and abs(east - ahead) <= 1.25 + 0.8


def test_obstacles_on_the_line_are_high_and_hide_the_ground_behind_them() -> None:
    rock = WorldObstacle("rock", Shape.BOX, LINE_M - 2.0, 4.0, 0.8, length_m=1.0, width_m=1.0)
    low_rock = WorldObstacle("pebble", Shape.BOX, 20.0, -4.0, 0.05, length_m=1.0, width_m=1.0)
    stretches = sweep(scene=Scene.from_obstacles((rock, low_rock))).stretches
    high = [s for s in stretches if s.height_m > 0]
    assert min(s.y_right_m for s in high) < 4.0 < max(s.y_left_m for s in high)
    assert min(s.x_near_m for s in high) == pytest.approx(LINE_M - 2.5, abs=0.1)
    assert not any(s.height_m == 0.0 and s.y_right_m < 4.0 < s.y_left_m for s in stretches)
    # The beam is far above a 5 cm pebble 20 m out: the ground behind it is seen level.
    behind = -4.0 * SWEEP_MOUNT.ground_m / (20.0 - SWEEP_MOUNT.x_m)
    assert any(s.height_m == 0.0 and s.y_right_m < behind < s.y_left_m for s in stretches)


def reach_past(stretches: list[GroundStretch], rock: WorldObstacle) -> float:
    """How far the stretches' corners reach outside ``rock``'s box (the vehicle at the origin)."""
    corners = np.array([(x, y) for s in stretches for x in (s.x_near_m, s.x_far_m) for y in (s.y_right_m, s.y_left_m)])
    c, s_ = math.cos(rock.yaw_rad), math.sin(rock.yaw_rad)
    local = np.abs((corners - (rock.east_m, rock.north_m)) @ np.array(((c, -s_), (s_, c))))
    return float(np.max(local - (rock.length_m / 2, rock.width_m / 2)))


def test_a_face_seen_at_a_slant_is_cut_into_pieces_that_hug_it() -> None:
    rock = WorldObstacle("rock", Shape.BOX, LINE_M - 2.0, 0.0, 0.9, length_m=1.4, width_m=1.4, yaw_rad=0.6)
    returns = sweep_scan((), Scene.from_obstacles((rock,)), Pose(0.0, 0.0, 0.0))
    pieces = [s for s in describe_sweep(returns, SWEEP_MOUNT, int(Sensor.LIDAR_SWEEP)).stretches if s.height_m > 0]
    whole = describe_sweep(returns, SWEEP_MOUNT, int(Sensor.LIDAR_SWEEP), max_depth_m=math.inf).stretches
    assert all(s.x_far_m - s.x_near_m <= 0.25 for s in pieces)
    # One box round the slanted faces reaches well past the rock; pieces no further than their
    # depth bound and half a beam spacing.
    assert reach_past([s for s in whole if s.height_m > 0], rock) > 0.5
    assert reach_past(pieces, rock) < 0.25 + 0.16


def test_a_berm_is_high() -> None:
    # The default scenario's berm: 6 m long across the road (north -8 to -2 m), 0.6 m high.
    berm = TerrainHazard("berm", HazardKind.BERM, LINE_M, -5.0, math.pi / 2, 6.0, 3.0, 0.6)
    high = [s for s in sweep([berm]).stretches if s.height_m > 0]
    assert min(s.y_right_m for s in high) == pytest.approx(-8.0, abs=0.3)
    assert max(s.y_left_m for s in high) == pytest.approx(-2.0, abs=0.3)


def test_ground_beyond_the_range_is_no_stretch_at_all() -> None:
    short = SweepMount(max_range_m=30.0)  # every beam meets the ground beyond 30 m
    assert sweep(mount=short).stretches == ()


def test_descending_rays_hit_only_obstacles_taller_than_the_ray_where_they_enter() -> None:
    post = WorldObstacle("post", Shape.CYLINDER, 20.0, 0.0, 1.0, radius_m=0.5)
    scene = Scene.from_obstacles((post,))
    origin, angles = np.zeros(2), np.array([-0.1, 0.0, 0.1])
    # From 2 m, falling 0.04 m per metre: 1.22 m high at the post (misses) or 0.5 m at 0.075 m per metre.
    assert np.all(np.isinf(descending_ray_ranges(origin, angles, 2.0, np.full(3, 0.04), scene, 80.0)))
    hit = descending_ray_ranges(origin, angles, 2.0, np.full(3, 0.075), scene, 80.0)
    assert hit[1] == pytest.approx(19.5) and np.isinf(hit[0]) and np.isinf(hit[2])


def test_first_hits_per_beam_samples_agree_with_shared_ones() -> None:
    ditch = TerrainHazard("ditch", HazardKind.DITCH, 12.0, 0.0, 0.0, 3.0, 8.0, 0.6)
    along = np.arange(0.0, 30.0, 0.05)
    ground = ground_height([ditch], along, np.zeros_like(along))
    slopes = np.tan(VERTICAL_MOUNTS["lidar_v_left"].depressions_rad())
    shared = first_hits(along, ground, 1.6, slopes)
    own = first_hits(np.tile(along, (len(slopes), 1)), np.tile(ground, (len(slopes), 1)), 1.6, slopes)
    np.testing.assert_array_equal(shared[0], own[0])
    np.testing.assert_array_equal(shared[1], own[1])


def test_a_hazard_beyond_any_beams_reach_changes_nothing() -> None:
    # The scenario's berm 500 m on, in line with one beam, once stretched the ground samples of
    # every beam across the wash to that beam's 500 m (and a sweep to 20 ms).
    wash = TerrainHazard("wash", HazardKind.DITCH, LINE_M, 0.0, 0.0, **WASH)
    far_berm = TerrainHazard("berm", HazardKind.BERM, LINE_M + 500.0, 0.0, math.pi / 2, 6.0, 3.0, 0.6)
    assert sweep([wash, far_berm]) == sweep([wash])
