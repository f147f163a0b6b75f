"""Horizontal ray-casting against analytic geometry (no noise unless a test asks for it)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from brain.pose import Pose
from modules.lidar.scan import HORIZONTAL_MOUNTS, Mount, Scan, ScanSpec, sensor_pose
from modules.sim.lidar.raycast import Scene, cast
from modules.sim.world import Shape, WorldObstacle

AT_ORIGIN = Mount(0.0, 0.0, 0.7)
HERE = Pose(0.0, 0.0, 0.0)


def cylinder(east: float, north: float, radius: float, height: float = 2.0) -> WorldObstacle:
    return WorldObstacle("c", Shape.CYLINDER, east, north, height, radius_m=radius)


def box(east: float, north: float, length: float, width: float, yaw: float, height: float = 2.0) -> WorldObstacle:
    return WorldObstacle("b", Shape.BOX, east, north, height, length_m=length, width_m=width, yaw_rad=yaw)


def ray_angles(scan: Scan, pose: Pose) -> np.ndarray:
    return sensor_pose(pose, scan.mount)[1] + scan.bearings_rad


def segment_range(origin: np.ndarray, angle: float, a: np.ndarray, b: np.ndarray) -> float:
    """Distance along a ray to the segment a-b (Cramer's rule), inf when it misses."""
    direction = np.array((math.cos(angle), math.sin(angle)))
    edge = b - a
    det = direction[0] * -edge[1] + edge[0] * direction[1]
    if abs(det) < 1e-12:
        return math.inf
    rel = a - origin
    t = (rel[0] * -edge[1] + edge[0] * rel[1]) / det
    s = (direction[0] * rel[1] - direction[1] * rel[0]) / det
    return t if t > 0 and 0 <= s <= 1 else math.inf


poses = st.builds(
    Pose,
    st.floats(-500, 500),
    st.floats(-500, 500),
    st.floats(-math.pi, math.pi),
)


@settings(max_examples=150, deadline=None)
@given(
    pose=poses,
    sensor=st.sampled_from(sorted(HORIZONTAL_MOUNTS)),
    distance=st.floats(2.5, 75.0),
    bearing=st.floats(-1.4, 1.4),
    radius=st.floats(0.1, 2.0),
)
def test_cylinder_ranges_match_the_circle(
    pose: Pose, sensor: str, distance: float, bearing: float, radius: float
) -> None:
    mount = HORIZONTAL_MOUNTS[sensor]
    origin, yaw = sensor_pose(pose, mount)
    centre = origin + distance * np.array((math.cos(yaw + bearing), math.sin(yaw + bearing)))
    scan = cast(Scene.from_obstacles([cylinder(*centre, radius)]), pose, mount)
    offsets = ray_angles(scan, pose) - (yaw + bearing)  # each ray's angle from the centre's bearing
    half_chord_sq = radius**2 - (distance * np.sin(offsets)) ** 2
    expected = np.where(
        (half_chord_sq >= 0) & (np.cos(offsets) > 0),
        distance * np.cos(offsets) - np.sqrt(np.abs(half_chord_sq)),
        np.inf,
    )
    expected[expected > scan.spec.max_range_m] = np.inf
    # A ray that grazes the circle (tangent to within rounding) may hit or miss: judge the others.
    clear_cut = np.abs(half_chord_sq) > 1e-9 * radius**2
    assert np.array_equal(np.isinf(scan.ranges_m[clear_cut]), np.isinf(expected[clear_cut]))
    hit = np.isfinite(expected) & clear_cut  # a thin far cylinder may fall between rays: then none
    assert np.all(np.abs(scan.ranges_m[hit] - expected[hit]) < 0.01)


@settings(max_examples=150, deadline=None)
@given(
    pose=poses,
    sensor=st.sampled_from(sorted(HORIZONTAL_MOUNTS)),
    distance=st.floats(4.0, 75.0),
    bearing=st.floats(-1.3, 1.3),
    length=st.floats(0.2, 6.0),
    width=st.floats(0.2, 6.0),
    yaw=st.floats(-math.pi, math.pi),
)
def test_box_ranges_match_the_rectangle(
    pose: Pose, sensor: str, distance: float, bearing: float, length: float, width: float, yaw: float
) -> None:
    assume(math.hypot(length, width) / 2 < distance)  # the scanner stands outside the box
    mount = HORIZONTAL_MOUNTS[sensor]
    origin, sensor_yaw = sensor_pose(pose, mount)
    centre = origin + distance * np.array((math.cos(sensor_yaw + bearing), math.sin(sensor_yaw + bearing)))
    scan = cast(Scene.from_obstacles([box(*centre, length, width, yaw)]), pose, mount)
    c, s = math.cos(yaw), math.sin(yaw)
    half = ((length / 2, width / 2), (-length / 2, width / 2), (-length / 2, -width / 2), (length / 2, -width / 2))
    corners = [centre + np.array((c * x - s * y, s * x + c * y)) for x, y in half]
    for angle, measured in zip(ray_angles(scan, pose), scan.ranges_m, strict=True):
        expected = min(segment_range(origin, angle, corners[i], corners[(i + 1) % 4]) for i in range(4))
        if expected > scan.spec.max_range_m:
            expected = math.inf
        if math.isinf(expected):
            assert math.isinf(measured)
        else:
            assert abs(measured - expected) < 0.01


def test_a_wall_face_on_is_at_its_distance_on_every_ray_that_meets_it() -> None:
    scan = cast(Scene.from_obstacles([box(20.0, 0.0, 1.0, 10.0, 0.0)]), HERE, AT_ORIGIN)
    hit = np.isfinite(scan.ranges_m)
    expected = 19.5 / np.cos(scan.bearings_rad[hit])
    assert np.max(np.abs(scan.ranges_m[hit] - expected)) < 1e-9
    assert np.all(np.abs(19.5 * np.tan(scan.bearings_rad[hit])) <= 5.0 + 1e-9)


def test_obstacles_lower_than_the_scan_plane_are_invisible() -> None:
    low = [cylinder(10.0, 0.0, 1.0, height=0.69), box(15.0, 3.0, 2.0, 2.0, 0.3, height=0.5)]
    assert np.isinf(cast(Scene.from_obstacles(low), HERE, AT_ORIGIN).ranges_m).all()
    tall = [cylinder(10.0, 0.0, 1.0, height=0.71)]
    assert np.isfinite(cast(Scene.from_obstacles(tall), HERE, AT_ORIGIN).ranges_m).any()


def test_nothing_is_seen_behind_the_scanner_or_beyond_its_range() -> None:
    behind = cylinder(-10.0, 0.0, 1.0)
    far = cylinder(81.5, 0.0, 1.0)  # nearest surface 80.5 m away
    assert np.isinf(cast(Scene.from_obstacles([behind, far]), HERE, AT_ORIGIN).ranges_m).all()
    near_enough = cylinder(80.5, 0.0, 1.0)
    assert np.isfinite(cast(Scene.from_obstacles([near_enough]), HERE, AT_ORIGIN).ranges_m).any()


def test_the_nearest_obstacle_hides_the_ones_behind_it() -> None:
    scene = Scene.from_obstacles([cylinder(10.0, 0.0, 1.0), box(20.0, 0.0, 1.0, 6.0, 0.0)])
    scan = cast(scene, HERE, AT_ORIGIN)
    centre_ray = int(np.argmin(np.abs(scan.bearings_rad)))
    assert abs(scan.ranges_m[centre_ray] - 9.0) < 1e-9


def test_range_noise_has_the_configured_spread() -> None:
    scene = Scene.from_obstacles([box(10.0, 0.0, 1.0, 30.0, 0.0)])
    clean = cast(scene, HERE, AT_ORIGIN)
    noisy = cast(scene, HERE, AT_ORIGIN, ScanSpec(range_noise_std_m=0.01), np.random.default_rng(1))
    hit = np.isfinite(clean.ranges_m)
    assert hit.sum() > 100
    assert 0.008 < np.std(noisy.ranges_m[hit] - clean.ranges_m[hit]) < 0.012
    scaled = cast(scene, HERE, AT_ORIGIN, ScanSpec(range_noise_std_m=0.01), np.random.default_rng(1), noise_scale=10)
    assert 0.08 < np.std(scaled.ranges_m[hit] - clean.ranges_m[hit]) < 0.12


def test_a_scan_has_the_sick_geometry() -> None:
    spec = ScanSpec()
    bearings = spec.bearings_rad()
    assert len(bearings) == 361
    assert math.isclose(bearings[0], -math.pi / 2) and math.isclose(bearings[-1], math.pi / 2)
    assert np.allclose(np.diff(bearings), math.radians(0.5))
