"""The whole pipeline on rendered scenes: obstacles where the boxes are, none on bare ground, the
painted parabolas as lane borders."""

from __future__ import annotations

import math

import numpy as np
import pytest

from modules.esvs.geometry import RASCAL_RIG
from modules.esvs.vision import STAGES, process
from modules.sim.camera.render import StereoRenderer
from modules.sim.world import Shape, World, WorldObstacle
from protocol.messages import Frame, Sensor
from tests.modules.esvs.vision.scenes import Box, Scene, Stripe, nearest_range, rendered

# Boxes 10-35 m ahead of the cameras (x 11.6-36.6 from the vehicle origin), apart in bearing.
OBSTACLE_SCENES = [
    Scene(boxes=(Box(12.5, -3.0, 1.0, 1.0, 0.6), Box(21.6, 0.5, 1.5, 1.0, 1.5), Box(31.0, 4.5, 1.2, 1.0, 1.0)), seed=1),
    Scene(boxes=(Box(16.6, 3.0, 0.8, 0.8, 2.0), Box(26.6, -3.5, 2.0, 1.0, 0.8), Box(36.0, 0.0, 1.0, 1.0, 1.2)), seed=2),
]
BARE = Scene(seed=3)
LANES = Scene(stripes=(Stripe(2.2, 0.02, 0.0015), Stripe(-2.0, -0.03, -0.001)), seed=4)


@pytest.mark.parametrize("scene", OBSTACLE_SCENES, ids=["scene1", "scene2"])
def test_each_box_is_one_obstacle_within_5_percent_of_its_range(scene: Scene) -> None:
    left, right, _ = rendered(scene)
    obstacles, _, _ = process(left, right, RASCAL_RIG)
    assert obstacles.sensor == Sensor.ESVS and obstacles.frame == Frame.VEHICLE
    assert len(obstacles.obstacles) == len(scene.boxes)
    for box in scene.boxes:
        truth = nearest_range(box)
        found = min(obstacles.obstacles, key=lambda o: abs(o.y_m - box.y_m) + abs(o.range_m - truth))
        assert abs(found.range_m - truth) <= 0.05 * truth, (box, found)
        assert abs(found.y_m - box.y_m) <= 0.25, (box, found)
        assert abs(found.width_m - box.width_m) <= 0.3, (box, found)
        assert abs(found.height_m - box.height_m) <= 0.2, (box, found)
        assert found.confidence > 0.5


def test_bare_textured_ground_has_no_obstacle() -> None:
    left, right, _ = rendered(BARE)
    obstacles, borders, stats = process(left, right, RASCAL_RIG)
    assert obstacles.obstacles == ()
    assert borders.borders == ()
    assert stats.obstacle_points == 0


def test_painted_parabolas_come_back_as_lane_borders() -> None:
    left, right, _ = rendered(LANES)
    obstacles, borders, _ = process(left, right, RASCAL_RIG)
    assert obstacles.obstacles == ()
    assert borders.sensor == Sensor.ESVS
    assert [b.side for b in borders.borders] == [1, -1]
    xs = np.linspace(12.0, 36.0, 13)
    for border, stripe in zip(borders.borders, LANES.stripes, strict=True):
        fitted = border.c0_m + border.c1 * xs + border.c2_per_m * xs**2
        truth = stripe.c0 + stripe.c1 * xs + stripe.c2 * xs**2
        assert np.abs(fitted - truth).max() < 0.15
        assert border.x_min_m < 12.5 and border.x_max_m > 36.0
        assert border.confidence > 0.8


def test_stats_time_every_stage_and_describe_the_band() -> None:
    left, right, _ = rendered(BARE)
    _, _, stats = process(left, right, RASCAL_RIG)
    assert tuple(stats.timings_s) == STAGES
    assert all(t >= 0 for t in stats.timings_s.values())
    assert stats.total_s == pytest.approx(sum(stats.timings_s.values()))
    # The band holds the ground 10 m and 35 m ahead of the cameras.
    for distance in (10.0, 35.0):
        row = RASCAL_RIG.ground_row(distance + RASCAL_RIG.mount_forward_m)
        assert stats.band.top <= row < stats.band.bottom


def test_the_same_pair_gives_the_same_descriptors() -> None:
    left, right, _ = rendered(OBSTACLE_SCENES[0])
    first, second = process(left, right), process(left, right)
    assert first[:2] == second[:2]


def test_descriptors_are_finite_message_values() -> None:
    left, right, _ = rendered(OBSTACLE_SCENES[1])
    obstacles, borders, _ = process(left, right)
    values = [v for o in obstacles.obstacles for v in o] + [v for b in borders.borders for v in b]
    assert all(math.isfinite(v) for v in values)


def test_images_of_the_wrong_kind_are_refused() -> None:
    left, right, _ = rendered(BARE)
    with pytest.raises(ValueError, match="left image"):
        process(left[:-1], right)
    with pytest.raises(ValueError, match="right image"):
        process(left, right.astype(np.float32))
    with pytest.raises(ValueError, match="grey uint8"):
        process(np.dstack([left] * 3), right)


def test_on_the_simulated_cameras_a_rock_and_both_road_edges_are_found() -> None:
    camera = pytest.importorskip("modules.sim.camera", reason="the simulated cameras are not in this tree")
    from modules.sim.world import LaneBorderLine, Shape, World, WorldObstacle

    rock = WorldObstacle("rock", Shape.BOX, 24.0, -1.0, 1.2, length_m=1.5, width_m=1.5)
    along = np.arange(-20.0, 200.0, 1.0)  # polylines with 1 m vertices, like the scenario's
    edges = tuple(
        LaneBorderLine(name, tuple((float(x), y) for x in along)) for name, y in (("left", 3.5), ("right", -3.5))
    )
    frame = camera.render_pair(World(obstacles=(rock,), lane_borders=edges), (0.0, 0.0, 0.0), RASCAL_RIG)
    obstacles, borders, _ = process(frame.left, frame.right, RASCAL_RIG)
    (found,) = obstacles.obstacles
    assert abs(found.range_m - float(np.hypot(23.25, 0.25))) < 0.05 * 23.25
    assert abs(found.y_m + 1.0) < 0.3
    assert [b.side for b in borders.borders] == [1, -1]
    for border, y in zip(borders.borders, (3.5, -3.5), strict=True):
        xs = np.linspace(max(border.x_min_m, 12.0), min(border.x_max_m, 36.0), 10)
        assert np.abs(border.c0_m + border.c1 * xs + border.c2_per_m * xs**2 - y).max() < 0.3


@pytest.mark.parametrize("turn_deg", [15.0, 30.0])
@pytest.mark.parametrize("side", [1.0, -1.0])
def test_a_box_seen_at_an_angle_is_described_turned_with_it(turn_deg: float, side: float) -> None:
    # A gate post 12 m ahead, turned against the vehicle as when the vehicle comes out of a bend.
    # A box square to the vehicle round it reached 0.3-0.5 m past its sides in its own frame.
    yaw = -side * math.radians(turn_deg)
    post = WorldObstacle("post", Shape.BOX, 14.0, side * 1.5, 1.1, length_m=1.26, width_m=0.93, yaw_rad=yaw)
    frame = StereoRenderer(World(obstacles=(post,)), RASCAL_RIG).render((0.0, 0.0, 0.0), np.random.default_rng(5))
    obstacles, _, _ = process(frame.left, frame.right, RASCAL_RIG)
    (found,) = obstacles.obstacles
    assert math.degrees(abs(found.yaw_rad - yaw)) <= 6.0
    c, s = math.cos(found.yaw_rad), math.sin(found.yaw_rad)
    corners = [
        (found.x_m + u * c - v * s, found.y_m + u * s + v * c)
        for u in (-found.length_m / 2, found.length_m / 2)
        for v in (-found.width_m / 2, found.width_m / 2)
    ]
    across_post = [-(x - post.east_m) * math.sin(yaw) + (y - post.north_m) * math.cos(yaw) for x, y in corners]
    assert max(abs(a) for a in across_post) <= post.width_m / 2 + 0.3
