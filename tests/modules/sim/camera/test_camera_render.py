"""Simulated stereo cameras: ground truth matches the rig geometry, obstacles and terrain sit
where the world puts them, labels name what each pixel shows, and renders are reproducible."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from modules.esvs.geometry import RASCAL_RIG, StereoRig
from modules.sim.camera import (
    LABEL_GROUND,
    LABEL_HAZARD,
    LABEL_LANE_BORDER,
    LABEL_SKY,
    CameraConfig,
    StereoFrame,
    StereoRenderer,
    render_pair,
)
from modules.sim.terrain import ground_height
from modules.sim.world import (
    HazardKind,
    LaneBorderLine,
    Shape,
    TerrainHazard,
    Texture,
    World,
    WorldObstacle,
)

RIG = RASCAL_RIG
POSE = (120.0, -40.0, 0.7)  # away from the origin and turned, so the world -> vehicle transform matters


def world_point(pose: tuple[float, float, float], forward: float, left: float) -> tuple[float, float]:
    """ENU position of a vehicle-frame ground point."""
    east, north, yaw = pose
    return east + forward * math.cos(yaw) - left * math.sin(yaw), north + forward * math.sin(yaw) + left * math.cos(yaw)


def vehicle_points(frame: StereoFrame, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(n, 3) vehicle-frame points the ground-truth disparity puts at these pixels (Q matrix)."""
    camera = cv2.reprojectImageTo3D(frame.disparity_px, frame.rig.q_matrix)[rows, cols].astype(float)
    return frame.rig.camera_to_vehicle(camera)


def to_world(pose: tuple[float, float, float], points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    east, north, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return east + c * points[:, 0] - s * points[:, 1], north + s * points[:, 0] + c * points[:, 1]


def test_flat_ground_has_disparity_f_b_over_depth_and_sky_has_none() -> None:
    frame = render_pair(World(), POSE, RIG)
    horizon = RIG.horizon_row()
    assert frame.left.shape == frame.right.shape == (RIG.height_px, RIG.width_px)
    assert frame.left.dtype == np.uint8 and frame.disparity_px.dtype == np.float32
    # Each pixel below the horizon sees flat ground at the depth where its ray meets z = 0.
    rows, cols = np.mgrid[math.ceil(horizon) + 2 : RIG.height_px : 7, 0 : RIG.width_px : 11]
    ray = np.stack([(cols - RIG.cx_px) / RIG.focal_px, (rows - RIG.cy_px) / RIG.focal_px, np.ones(rows.shape)], -1)
    ray_vehicle = ray @ RIG.camera_to_vehicle_rotation.T
    depth = RIG.mount_height_m / -ray_vehicle[..., 2]
    np.testing.assert_allclose(frame.disparity_px[rows, cols], RIG.focal_px * RIG.baseline_m / depth, rtol=1e-5)
    assert np.all(frame.labels[rows, cols] == LABEL_GROUND)
    # ... and reprojecting the truth through the rig's Q matrix lands on the ground plane.
    points = vehicle_points(frame, rows.ravel(), cols.ravel())
    np.testing.assert_allclose(points[:, 2], 0.0, atol=1e-4 * depth.max())
    sky = frame.labels[: math.floor(horizon) - 1]
    assert np.all(sky == LABEL_SKY) and np.all(np.isnan(frame.disparity_px[: math.floor(horizon) - 1]))
    assert np.all(np.isinf(frame.depth_m[: math.floor(horizon) - 1]))


def test_a_box_appears_at_its_projected_pixels_with_its_disparity() -> None:
    forward, left = 18.0, 1.0
    east, north = world_point(POSE, forward, left)
    box = WorldObstacle("crate", Shape.BOX, east, north, 1.2, length_m=1.0, width_m=1.6, yaw_rad=POSE[2])
    frame = render_pair(World(obstacles=(box,)), POSE, RIG)
    # The face towards the camera is the plane x = forward - 0.5 in the vehicle frame.
    face = np.array([[forward - 0.5, left + y, z] for y in (-0.8, 0.8) for z in (0.0, 1.2)])
    u, v, _ = RIG.project(face)
    inner = (
        slice(math.ceil(v.min()) + 2, math.floor(v.max()) - 1),
        slice(math.ceil(u.min()) + 2, math.floor(u.max()) - 1),
    )
    assert np.all(frame.labels[inner] == 1)
    assert frame.obstacle(1) is box and frame.visible_obstacles() == {"crate": int(np.sum(frame.labels == 1))}
    rows, cols = np.mgrid[inner]
    points = vehicle_points(frame, rows.ravel(), cols.ravel())
    np.testing.assert_allclose(points[:, 0], forward - 0.5, atol=2e-3)
    # Just outside the face's outline (left and right of it, and above it) nothing is labelled the box.
    middle = round(float(v.mean()))
    assert frame.labels[middle, math.floor(u.min()) - 2] != 1 and frame.labels[middle, math.ceil(u.max()) + 2] != 1
    assert frame.labels[math.floor(v.min()) - 2, round(float(u.mean()))] != 1
    # The right camera sees the same face shifted left by the disparity.
    row, col = middle, round(float(u.mean()))
    shifted = round(col - float(frame.disparity_px[row, col]))
    assert frame.right_disparity_px[row, shifted] == pytest.approx(frame.disparity_px[row, col], abs=0.05)


def test_a_cylinder_occludes_the_box_behind_it() -> None:
    near_e, near_n = world_point(POSE, 12.0, 0.0)
    far_e, far_n = world_point(POSE, 20.0, 0.0)
    pole = WorldObstacle("pole", Shape.CYLINDER, near_e, near_n, 3.0, radius_m=0.3, texture=Texture.WOOD)
    wall = WorldObstacle(
        "wall", Shape.BOX, far_e, far_n, 2.0, length_m=0.5, width_m=6.0, yaw_rad=POSE[2], texture=Texture.CONCRETE
    )
    frame = render_pair(World(obstacles=(pole, wall)), POSE, RIG)
    u, v, _ = RIG.project(np.array([[11.7, 0.0, 1.0]]))
    row, col = round(float(v[0])), round(float(u[0]))
    assert frame.labels[row, col] == 1  # the pole, nearer, wins the depth test
    point = vehicle_points(frame, np.array([row]), np.array([col]))[0]
    assert math.hypot(point[0] - 12.0, point[1]) == pytest.approx(0.3, abs=5e-3)  # on the pole's surface
    assert frame.labels[row, col + 40] == 2  # beside the pole, the wall behind it
    assert set(frame.visible_obstacles()) == {"pole", "wall"}


def test_ditch_and_berm_change_the_ground_where_the_lidars_see_them() -> None:
    ditch_e, ditch_n = world_point(POSE, 16.0, 0.0)
    berm_e, berm_n = world_point(POSE, 28.0, -3.0)
    hazards = (
        TerrainHazard("wash", HazardKind.DITCH, ditch_e, ditch_n, POSE[2], 2.5, 10.0, 0.7),
        TerrainHazard("berm", HazardKind.BERM, berm_e, berm_n, POSE[2], 4.0, 3.0, 0.6),
    )
    frame = render_pair(World(hazards=hazards), POSE, RIG)
    rows, cols = np.nonzero(frame.labels == LABEL_HAZARD)
    assert rows.size > 500
    points = vehicle_points(frame, rows, cols)
    east, north = to_world(POSE, points)
    # Every hazard pixel's true 3-D point lies on the terrain (within the heights a 2 cm
    # neighbourhood spans, which covers the vertical sides of the strips).
    offsets = np.array([(dx, dy) for dx in (-0.02, 0.0, 0.02) for dy in (-0.02, 0.0, 0.02)])
    around = np.stack([ground_height(hazards, east + dx, north + dy) for dx, dy in offsets])
    assert np.all(points[:, 2] >= around.min(axis=0) - 2e-3)
    assert np.all(points[:, 2] <= around.max(axis=0) + 2e-3)
    # Seen from 16 m the far wall hides the floor, but the view reaches well into the ditch.
    assert points[:, 2].min() < -0.2 and points[:, 2].max() > 0.55  # into the ditch, onto the berm
    flat = render_pair(World(), POSE, RIG)
    deeper = frame.depth_m[rows, cols] > flat.depth_m[rows, cols] + 0.05
    nearer = frame.depth_m[rows, cols] < flat.depth_m[rows, cols] - 0.05
    assert deeper.any() and nearer.any()


def test_lane_borders_are_lighter_bands_on_the_ground() -> None:
    line = tuple(world_point(POSE, x, 2.0) for x in np.arange(0.0, 120.0, 1.0))
    frame = render_pair(World(lane_borders=(LaneBorderLine("road_left", line),)), POSE, RIG)
    on = np.array([[x, 2.0, 0.0] for x in (12.0, 18.0, 25.0, 32.0)])
    beside = on + np.array([0.0, 1.0, 0.0])
    u, v, _ = RIG.project(on)
    rows, cols = np.round(v).astype(int), np.round(u).astype(int)
    assert np.all(frame.labels[rows, cols] == LABEL_LANE_BORDER)
    ub, vb, _ = RIG.project(beside)
    assert np.all(frame.labels[np.round(vb).astype(int), np.round(ub).astype(int)] == LABEL_GROUND)
    band = frame.labels == LABEL_LANE_BORDER
    ground = frame.labels == LABEL_GROUND
    assert frame.left[band].mean() > frame.left[ground].mean() + 20


def test_same_seed_same_pair_other_seed_other_noise_same_truth() -> None:
    box = WorldObstacle("rock", Shape.CYLINDER, *world_point(POSE, 15.0, -1.0), 0.8, radius_m=0.5)
    renderer = StereoRenderer(World(obstacles=(box,)), RIG)
    first = renderer.render(POSE, np.random.default_rng(7))
    again = renderer.render(POSE, np.random.default_rng(7))
    other = renderer.render(POSE, np.random.default_rng(8))
    for name in ("left", "right", "disparity_px", "labels", "depth_m"):
        np.testing.assert_array_equal(getattr(first, name), getattr(again, name))
    assert not np.array_equal(first.left, other.left)
    np.testing.assert_array_equal(first.disparity_px, other.disparity_px)
    # The noise is about the configured 1.5 DN (the renders differ by two independent draws).
    difference = first.left.astype(float) - other.left.astype(float)
    assert difference.std() == pytest.approx(1.5 * math.sqrt(2), rel=0.2)


def test_images_are_the_renders_without_truth_and_noise_gain_scales_the_noise() -> None:
    renderer = StereoRenderer(World(), RIG)
    frame = renderer.render(POSE, np.random.default_rng(3))
    left, right = renderer.images(POSE, np.random.default_rng(3))
    np.testing.assert_array_equal(left, frame.left)
    np.testing.assert_array_equal(right, frame.right)
    clean, _ = renderer.images(POSE)
    loud, _ = renderer.images(POSE, np.random.default_rng(4), noise_gain=4.0)
    sky = frame.labels == LABEL_SKY  # mid-grey: no clipping
    assert (loud[sky].astype(float) - clean[sky]).std() == pytest.approx(4 * 1.5, rel=0.1)
    with pytest.raises(ValueError, match="noise_gain"):
        renderer.images(POSE, np.random.default_rng(4), noise_gain=-1.0)


def test_the_right_camera_is_a_little_brighter_and_offset() -> None:
    config = CameraConfig(right_gain=1.1, right_offset_dn=-5.0, noise_std_dn=0.0)
    frame = render_pair(World(), POSE, RIG, config=config)
    sky = frame.labels[:100] == LABEL_SKY  # sky is the same pixel in both cameras
    left, right = frame.left[:100][sky].astype(float), frame.right[:100][sky].astype(float)
    np.testing.assert_allclose(right, 1.1 * left - 5.0, atol=1.2)


def test_color_adds_bgr_images_of_the_same_scene() -> None:
    frame = render_pair(World(), POSE, RIG, np.random.default_rng(1), color=True)
    assert frame.left_bgr is not None and frame.right_bgr is not None
    assert frame.left_bgr.shape == (RIG.height_px, RIG.width_px, 3)
    sky = frame.labels == LABEL_SKY
    blue, red = frame.left_bgr[..., 0].astype(float), frame.left_bgr[..., 2].astype(float)
    assert blue[sky].mean() > red[sky].mean() and red[~sky].mean() > blue[~sky].mean()  # blue sky, tan soil
    assert render_pair(World(), POSE, RIG).left_bgr is None


def test_another_rig_renders_at_its_own_size() -> None:
    rig = StereoRig(width_px=320, height_px=240, pitch_down_deg=8.0)
    frame = render_pair(World(), (0.0, 0.0, 0.0), rig)
    assert frame.left.shape == (240, 320)
    row = 200
    ray = np.array([0.0, (row - rig.cy_px) / rig.focal_px, 1.0]) @ rig.camera_to_vehicle_rotation.T
    expected = rig.focal_px * rig.baseline_m / (rig.mount_height_m / -ray[2])
    assert float(frame.disparity_px[row, 160]) == pytest.approx(expected, rel=1e-4)


@pytest.mark.parametrize("pose", [(0.0, 0.0), (0.0, float("nan"), 0.0), "abc", (1.0, 2.0, float("inf"))])
def test_a_bad_pose_is_refused(pose: object) -> None:
    with pytest.raises(ValueError, match="pose"):
        render_pair(World(), pose, RIG)  # type: ignore[arg-type]


@pytest.mark.parametrize("field", ["far_m", "visibility_m", "road_resolution_m", "right_gain"])
def test_a_bad_config_is_refused(field: str) -> None:
    with pytest.raises(ValueError, match=field):
        CameraConfig(**{field: -1.0})
    with pytest.raises(ValueError, match="noise_std_dn"):
        CameraConfig(noise_std_dn=float("nan"))
