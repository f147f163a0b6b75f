"""Obstacle evaluation on simulated scenes: ranges, scene generation, truth, matching and scoring
on hand-made cases, the command line, and the done-means on a seeded run."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from modules.esvs.evaluate import main
from modules.esvs.geometry import RASCAL_RIG
from modules.esvs.scenes_eval import (
    RANGE_BANDS_M,
    BandResult,
    Evaluation,
    SceneParams,
    Truth,
    build_scene,
    descriptor_camera_range,
    evaluate,
    format_report,
    frame_truth,
    match,
    nearest_camera_range,
    scene_frames,
    score_scene,
    tolerance_m,
    unoccluded_pixels,
)
from modules.esvs.vision.clusters import ClusterParams
from modules.esvs.vision.pipeline import VisionParams, process
from modules.sim.camera import solids
from modules.sim.camera.render import StereoRenderer
from modules.sim.world import Shape, World, WorldObstacle
from protocol.messages import Obstacle

RIG = RASCAL_RIG
MOUNT = RIG.mount_forward_m
# The one vision parameter tuned for this evaluation (passed in, the defaults untouched): finer
# disparity bins in the clustering grid keep two obstacles on one line of sight apart more often.
TUNED = VisionParams(clusters=ClusterParams(disparity_bin_px=0.25))


def box(x: float, y: float, side: float = 1.0, height: float = 1.0, yaw: float = 0.0, name: str = "b") -> WorldObstacle:
    return WorldObstacle(name, Shape.BOX, x, y, height, length_m=side, width_m=side, yaw_rad=yaw)


def cylinder(x: float, y: float, radius: float = 0.5, height: float = 1.0) -> WorldObstacle:
    return WorldObstacle("c", Shape.CYLINDER, x, y, height, radius_m=radius)


def descriptor(x: float, y: float, range_m: float | None = None, length: float = 0.5, width: float = 0.5) -> Obstacle:
    return Obstacle(x, y, length, width, 1.0, 0.0, 0.9, math.hypot(x, y) if range_m is None else range_m)


def truth(obstacle: WorldObstacle, visible: int = 500, alone: int = 500, nearest: float | None = None) -> Truth:
    near = math.hypot(obstacle.east_m - obstacle.footprint_radius_m(), obstacle.north_m) if nearest is None else nearest
    return Truth(obstacle, nearest_camera_range(RIG, obstacle), visible, near, obstacle.north_m, 0, alone)


def empty_result() -> Evaluation:
    return Evaluation(1, 0, 0, [BandResult(low, high) for low, high in RANGE_BANDS_M])


# --- ranges --------------------------------------------------------------------------------------


def test_range_is_from_the_ground_under_the_cameras_to_the_nearest_footprint_point() -> None:
    assert nearest_camera_range(RIG, cylinder(MOUNT + 20, 0, radius=0.5)) == pytest.approx(19.5)
    assert nearest_camera_range(RIG, box(MOUNT + 20, 0, side=2.0)) == pytest.approx(19.0)
    # A square turned 45 deg points a corner at the cameras.
    turned = box(MOUNT + 20, 0, side=1.0, yaw=math.pi / 4)
    assert nearest_camera_range(RIG, turned) == pytest.approx(20 - math.sqrt(0.5), abs=1e-3)
    off_axis = cylinder(MOUNT + 12, 5, radius=0.5)
    assert nearest_camera_range(RIG, off_axis) == pytest.approx(13.0 - 0.5)
    # A descriptor measures range_m from the vehicle origin; seen from the cameras it is shorter.
    assert descriptor_camera_range(RIG, descriptor(MOUNT + 20, 0.0)) == pytest.approx(20.0)
    assert descriptor_camera_range(RIG, descriptor(MOUNT + 12, 5.0)) == pytest.approx(13.0)


# --- scenes --------------------------------------------------------------------------------------


def test_scenes_hold_what_the_spec_says_and_repeat_with_the_seed() -> None:
    params = SceneParams()
    rng = np.random.default_rng(5)
    half_fov = math.radians(RIG.hfov_deg) / 2
    for _ in range(25):
        scene = build_scene(rng, RIG, params)
        assert params.min_obstacles <= len(scene.obstacles) <= params.max_obstacles
        assert scene.terrain == "flat" and scene.hazards == ()
        for index, o in enumerate(scene.obstacles):
            assert 10.0 - 0.01 <= nearest_camera_range(RIG, o) <= 35.0 + 0.01
            assert abs(math.atan2(o.north_m, o.east_m - MOUNT)) <= half_fov + 1e-9
            assert 0.5 <= o.height_m <= 2.0
            sizes = (2 * o.radius_m,) if o.shape is Shape.CYLINDER else (o.length_m, o.width_m)
            assert all(0.3 <= size <= 2.0 for size in sizes)
            # The world holds the same obstacle, seen from the scene's pose.
            seen = solids.to_vehicle_frame(scene.world.obstacles[index], *scene.pose)
            assert (seen.east_m, seen.north_m) == pytest.approx((o.east_m, o.north_m), abs=1e-6)
            for other in scene.obstacles[index + 1 :]:
                gap = math.hypot(o.east_m - other.east_m, o.north_m - other.north_m)
                assert gap >= o.footprint_radius_m() + other.footprint_radius_m() + params.min_gap_m - 1e-9
    kinds = set()
    for _ in range(30):
        scene = build_scene(rng, RIG, params, clear=True)
        assert scene.obstacles == () and scene.world.obstacles == ()
        kinds.add(scene.terrain)
        for hazard in scene.hazards:
            assert 12.0 <= hazard.east_m - MOUNT <= 33.0
    assert kinds == {"flat", "ditch", "berm"}
    again = [build_scene(np.random.default_rng(9), RIG, params) for _ in range(2)]
    assert again[0] == again[1]


def test_scene_and_clear_streams_do_not_shift_each_other() -> None:
    first = [scene for scene, _, _ in scene_frames(3, 2)]
    assert [scene for scene, _, _ in scene_frames(3, 1)] == first[:1]
    clear = [scene for scene, _, _ in scene_frames(3, 1, clear=True)]
    assert clear[0].obstacles == () and clear[0] != first[0]


# --- truth ---------------------------------------------------------------------------------------


def test_truth_counts_the_pixels_both_cameras_see_and_the_nearest_visible_point() -> None:
    front = box(MOUNT + 15, 0.0, side=1.0, height=1.0, name="front")
    behind = box(MOUNT + 19, 0.3, side=2.0, height=1.5, name="behind")
    frame = StereoRenderer(World(obstacles=(front, behind)), RIG).render((0.0, 0.0, 0.0), None)
    near, far = frame_truth(frame, (front, behind))
    assert near.visible_px == near.alone_px == unoccluded_pixels(RIG, front) > 1000
    assert near.visible_share == 1.0
    assert near.nearest_visible_m == pytest.approx(MOUNT + 14.5, abs=0.02)
    assert near.visible_centre_y_m == pytest.approx(0.0, abs=0.03)
    assert near.range_m == pytest.approx(14.5)
    # The far box shows around the near one: part of what it would show alone.
    assert 0 < far.visible_px < far.alone_px
    assert far.nearest_visible_m == pytest.approx(MOUNT + 18.0, abs=0.05)


def test_truth_marks_pixels_in_the_columns_the_matcher_cannot_reach() -> None:
    # Near the left edge of the image: the matcher gives no disparity in the first 32 columns.
    bearing = math.radians(RIG.hfov_deg / 2) - 0.02
    edge = cylinder(MOUNT + 20 * math.cos(bearing), 20 * math.sin(bearing), radius=0.4)
    frame = StereoRenderer(World(obstacles=(edge,)), RIG).render((0.0, 0.0, 0.0), None)
    (seen,) = frame_truth(frame, (edge,), blind_columns=32)
    assert seen.visible_px > 0 and 2 * seen.blind_px > seen.visible_px
    assert frame_truth(frame, (edge,), blind_columns=0)[0].blind_px == 0


# --- matching and scoring ------------------------------------------------------------------------


def test_a_descriptor_matches_within_max_half_metre_or_5_percent_plus_the_footprint_radius() -> None:
    target = truth(box(MOUNT + 20, 0.0, side=1.0))
    tolerance = tolerance_m(target)
    assert tolerance == pytest.approx(0.05 * 19.5 + math.sqrt(0.5))
    assert tolerance_m(truth(cylinder(MOUNT + 6, 0.0, radius=0.2))) == pytest.approx(0.5 + 0.2)
    x = MOUNT + 20
    assert match((descriptor(x + tolerance - 0.01, 0.0),), [target]) == {0: 0}
    assert match((descriptor(x, tolerance + 0.01),), [target]) == {}
    # Greedy and one to one: the closer descriptor takes the obstacle, the other is left over.
    assert match((descriptor(x + 0.9, 0.0), descriptor(x + 0.2, 0.0)), [target]) == {1: 0}
    # A descriptor between two obstacles goes to the nearer; nothing matches an obstacle not in view.
    left, right = truth(cylinder(MOUNT + 20, 1.2, 0.3)), truth(cylinder(MOUNT + 20, -1.2, 0.3))
    assert match((descriptor(x, 0.4),), [left, right]) == {0: 0}
    assert match((descriptor(x, 0.4),), [truth(left.obstacle, visible=0), right]) == {}


def test_scoring_counts_recall_precision_range_errors_and_misses() -> None:
    found = truth(cylinder(MOUNT + 12.5, 0.0, 0.5), nearest=MOUNT + 12.0)  # 12 m: band 10-15
    merged = truth(box(MOUNT + 28.0, 3.0, side=1.0))  # 27.6 m: band 25-30
    glimpsed = truth(cylinder(MOUNT + 22.0, -3.0, 0.3), visible=30)  # too little to count
    hidden = truth(cylinder(MOUNT + 33.0, -6.0, 0.4), visible=80, alone=400)  # 32.1 m: band 30-35
    detections = (
        descriptor(MOUNT + 12.2, 0.1, range_m=MOUNT + 12.3),  # found, range 0.3 m long over 12 m
        descriptor(MOUNT + 25.0, 3.0, length=6.0),  # reaches the box but is too far to match it
        descriptor(MOUNT + 22.0, -3.0),  # the glimpsed cylinder: neither true nor false
        descriptor(MOUNT + 33.0, 8.0),  # nothing there
    )
    result = empty_result()
    score_scene(0, [found, merged, glimpsed, hidden], detections, RIG, result)
    shown = [(b.shown, b.found) for b in result.bands]
    assert shown == [(1, 1), (0, 0), (0, 0), (1, 0), (1, 0)]
    assert result.recall == pytest.approx(1 / 3)
    assert result.bands[0].range_errors == pytest.approx([0.3 / 12.0])
    assert result.bands[0].lateral_errors == pytest.approx([0.1 / 12.0])
    assert result.unscored_matches == 1
    # The unmatched descriptors: one 25.2 m from the cameras, one 34.0 m.
    assert [(b.descriptors, b.true_descriptors) for b in result.bands] == [(1, 1), (0, 0), (0, 0), (1, 0), (1, 0)]
    assert result.precision == pytest.approx(1 / 3)
    assert [(m.cause, m.scene) for m in result.misses] == [("merged", 0), ("mostly hidden", 0)]
    assert result.within_share == 1.0
    report = format_report(result)
    assert "recall >= 95 % at 10-35 m: NOT met (33.3 %)" in report
    assert "merged: box 27.6 m at +6.1 deg" in report  # off the axis: farther than its x
    assert "< 1 false descriptor per 100 clear frames: not measured" in report


# --- command line --------------------------------------------------------------------------------


def test_the_command_line_runs_simulated_scenes_and_rejects_mixed_options(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--simulated", "--scenes", "1", "--clear-frames", "1", "--seed", "4"]) == 0
    out = capsys.readouterr().out
    assert "ESVS obstacles on 1 simulated scenes and 1 clear-terrain frames (seed 4)" in out
    assert "30-35 m" in out and "clear terrain" in out and "process() p50" in out
    for argv in (["--scenes", "3"], ["--simulated", "--pair", "somewhere"]):
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 2
    assert main(["--simulated", "--scenes", "0", "--clear-frames", "0"]) == 2
    assert "rascal esvs eval: need scenes" in capsys.readouterr().err


# --- the done-means -------------------------------------------------------------------------------
# 40 scenes (about 115 obstacles), not 12: with 35 obstacles one miss is 97 % and two are 94 %,
# too coarse to test a 95 % rate. Seed 2005 is the command line's default.


@pytest.mark.slow
def test_recall_and_range_error_on_seeded_scenes() -> None:
    result = evaluate(scenes=40, clear_frames=0, seed=2005, vision=TUNED)
    assert result.shown >= 100
    assert result.recall >= 0.95, format_report(result)
    assert result.within_share >= 0.95, format_report(result)


@pytest.mark.slow
def test_fewer_than_one_false_descriptor_per_100_clear_frames() -> None:
    result = evaluate(scenes=0, clear_frames=20, seed=2005, vision=TUNED)
    assert result.clear_false == 0, format_report(result)


@pytest.mark.slow
def test_false_descriptors_on_clear_terrain_are_ditch_far_walls() -> None:
    """Why the clusters' min_top_m exists: without it, flat ground, road edges and low berms still
    give no descriptor, but on a ditch a descriptor can sit on its far wall (SGBM gives the wall one
    disparity), reaching no higher than the ground around it, unlike any obstacle."""
    unfiltered = dataclasses.replace(TUNED, clusters=dataclasses.replace(TUNED.clusters, min_top_m=-math.inf))
    walls = 0
    for scene, frame, _ in scene_frames(2005, 20, clear=True):
        found, _, _ = process(frame.left, frame.right, RIG, unfiltered)
        if scene.terrain != "ditch":
            assert found.obstacles == (), scene.terrain
            continue
        (ditch,) = scene.hazards
        c, s = math.cos(ditch.yaw_rad), math.sin(ditch.yaw_rad)
        for o in found.obstacles:
            along = (o.x_m - ditch.east_m) * c + (o.y_m - ditch.north_m) * s
            assert abs(along - ditch.length_m / 2) < 1.0
            assert o.height_m < 0.15
            walls += 1
    assert walls > 0, "the seeded clear frames include ditches that fire without the filter"
