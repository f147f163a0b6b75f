"""Collisions and clearances of the vehicle footprint against boxes and cylinders."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from modules.sim.collision import clearance_m, collides, footprint, obstacle_rect, rects_distance_m, rects_overlap
from modules.sim.vehicle import VehicleParams, VehicleState
from modules.sim.world import Shape, WorldObstacle

PARAMS = VehicleParams()
# At the origin facing east the footprint spans east -0.4..1.7 and north -0.6..0.6: the rear axle
# is 0.4 m from the rear end of a 2.1 m x 1.2 m outline.
FRONT_M, REAR_M, SIDE_M = 1.7, -0.4, 0.6
AT_ORIGIN = VehicleState()
DIAGONAL = (math.sqrt(0.5), math.sqrt(0.5))
MARGIN_M = 0.05


def box(
    east_m: float, north_m: float, length_m: float = 1.0, width_m: float = 1.0, yaw_rad: float = 0.0
) -> WorldObstacle:
    return WorldObstacle("box", Shape.BOX, east_m, north_m, 1.0, length_m=length_m, width_m=width_m, yaw_rad=yaw_rad)


def cylinder(east_m: float, north_m: float, radius_m: float) -> WorldObstacle:
    return WorldObstacle("cylinder", Shape.CYLINDER, east_m, north_m, 1.0, radius_m=radius_m)


def hits(state: VehicleState, obstacle: WorldObstacle) -> bool:
    return collides(state, [obstacle], PARAMS) is obstacle


def test_footprint_spans_the_outline_around_the_rear_axle() -> None:
    corners = [coordinate for corner in footprint(AT_ORIGIN, PARAMS).corners() for coordinate in corner]
    # Counter-clockwise from front left.
    assert corners == pytest.approx([FRONT_M, SIDE_M, REAR_M, SIDE_M, REAR_M, -SIDE_M, FRONT_M, -SIDE_M])


@pytest.mark.parametrize(("gap_m", "expected"), [(-MARGIN_M, True), (MARGIN_M, False)])
def test_box_ahead_collides_only_when_it_reaches_the_front(gap_m: float, expected: bool) -> None:
    obstacle = box(FRONT_M + 0.5 + gap_m, 0.3)
    assert hits(AT_ORIGIN, obstacle) is expected


@pytest.mark.parametrize(("gap_m", "expected"), [(-MARGIN_M, True), (MARGIN_M, False)])
def test_diamond_corner_against_the_front_face(gap_m: float, expected: bool) -> None:
    # A 1 m square turned 45 degrees points a corner sqrt(0.5) m from its centre at the vehicle.
    obstacle = box(FRONT_M + math.sqrt(0.5) + gap_m, -0.2, yaw_rad=math.pi / 4)
    assert hits(AT_ORIGIN, obstacle) is expected


@pytest.mark.parametrize(("gap_m", "expected"), [(-MARGIN_M, True), (MARGIN_M, False)])
def test_diamond_face_against_the_vehicle_corner(gap_m: float, expected: bool) -> None:
    # Only the diamond's own axes separate this case: the projections on the vehicle's axes overlap.
    corner_east, corner_north = FRONT_M, SIDE_M
    centre_m = 0.5 + gap_m
    obstacle = box(corner_east + centre_m * DIAGONAL[0], corner_north + centre_m * DIAGONAL[1], yaw_rad=math.pi / 4)
    assert hits(AT_ORIGIN, obstacle) is expected


@pytest.mark.parametrize(("gap_m", "expected"), [(-MARGIN_M, True), (MARGIN_M, False)])
def test_rotated_vehicle_corner_against_a_box_face(gap_m: float, expected: bool) -> None:
    # Turned 45 degrees, the front right corner (1.7, -0.6) is the easternmost point:
    # east (1.7 + 0.6) / sqrt(2) = 1.626, north (1.7 - 0.6) / sqrt(2) = 0.778.
    state = VehicleState(yaw_rad=math.pi / 4)
    corner_east, corner_north = 2.3 * math.sqrt(0.5), 1.1 * math.sqrt(0.5)
    obstacle = box(corner_east + 0.5 + gap_m, corner_north)
    assert hits(state, obstacle) is expected
    if not expected:
        assert clearance_m(state, obstacle, PARAMS) == pytest.approx(gap_m)


@pytest.mark.parametrize(("gap_m", "expected"), [(-MARGIN_M, True), (MARGIN_M, False)])
def test_cylinder_beside_the_vehicle(gap_m: float, expected: bool) -> None:
    assert hits(AT_ORIGIN, cylinder(0.65, SIDE_M + 0.3 + gap_m, 0.3)) is expected


@pytest.mark.parametrize(("gap_m", "expected"), [(-MARGIN_M, True), (MARGIN_M, False)])
def test_cylinder_off_the_corner_diagonally(gap_m: float, expected: bool) -> None:
    # Its bounding square overlaps the outline in both cases; only the true circle decides.
    centre_m = 0.3 + gap_m
    assert hits(AT_ORIGIN, cylinder(FRONT_M + centre_m * DIAGONAL[0], SIDE_M + centre_m * DIAGONAL[1], 0.3)) is expected


@pytest.mark.parametrize(("gap_m", "expected"), [(-MARGIN_M, True), (MARGIN_M, False)])
def test_cylinder_beside_a_turned_and_moved_vehicle(gap_m: float, expected: bool) -> None:
    state = VehicleState(east_m=5.0, north_m=-3.0, yaw_rad=2.0)
    # (0.65, 0.6 + 0.3 + gap) in the vehicle frame, rotated by the yaw and moved to the rear axle.
    x, y = 0.65, SIDE_M + 0.3 + gap_m
    c, s = math.cos(2.0), math.sin(2.0)
    obstacle = cylinder(5.0 + x * c - y * s, -3.0 + x * s + y * c, 0.3)
    assert hits(state, obstacle) is expected
    if not expected:
        assert clearance_m(state, obstacle, PARAMS) == pytest.approx(gap_m)


def test_long_wall_whose_centre_is_far_still_collides() -> None:
    # The prefilter must not drop a box by its centre: this 20 m wall starts 0.05 m inside the front.
    wall = box(FRONT_M - MARGIN_M + 10.0, 0.0, length_m=20.0, width_m=0.5)
    assert hits(AT_ORIGIN, wall)


def test_collides_returns_the_first_colliding_obstacle_in_order() -> None:
    far, first, second = cylinder(30.0, 0.0, 1.0), cylinder(0.0, 0.0, 0.2), box(1.0, 0.0)
    assert collides(AT_ORIGIN, [far, first, second], PARAMS) is first
    assert collides(AT_ORIGIN, [far], PARAMS) is None
    assert collides(AT_ORIGIN, [], PARAMS) is None


@pytest.mark.parametrize(
    ("obstacle", "expected_m"),
    [
        (box(3.0, 2.0), math.hypot(2.5 - FRONT_M, 1.5 - SIDE_M)),  # corner to corner: hypot(0.8, 0.9)
        (box(-2.0, 0.0, length_m=2.0), 1.0 - 0.4),  # behind: its front face at -1.0, our rear at -0.4
        (cylinder(0.65, 3.0, 0.5), 3.0 - 0.5 - SIDE_M),  # beside: centre to side minus radius
        (cylinder(FRONT_M + 3.0, SIDE_M + 4.0, 1.0), 5.0 - 1.0),  # off the corner: 3-4-5 triangle
        (box(FRONT_M + math.sqrt(0.5) + 0.3, 0.0, yaw_rad=math.pi / 4), 0.3),  # diamond corner to face
        (box(1.0, 0.0), 0.0),  # overlapping
        (cylinder(0.0, 0.0, 0.1), 0.0),  # inside
        (box(FRONT_M + 0.5, 0.0), 0.0),  # touching counts as zero
    ],
)
def test_clearance_matches_hand_computed_distances(obstacle: WorldObstacle, expected_m: float) -> None:
    assert clearance_m(AT_ORIGIN, obstacle, PARAMS) == pytest.approx(expected_m, abs=1e-12)


def test_rect_helpers_agree_with_the_obstacle_functions() -> None:
    obstacle = box(3.0, 2.0, yaw_rad=0.4)
    rect, outline = footprint(AT_ORIGIN, PARAMS), obstacle_rect(obstacle)
    assert rects_overlap(rect, outline) is False
    assert rects_distance_m(rect, outline) == clearance_m(AT_ORIGIN, obstacle, PARAMS)


# -- against an independent polygon oracle ------------------------------------------------------

Point = tuple[float, float]


def rectangle(east_m: float, north_m: float, yaw_rad: float, length_m: float, width_m: float) -> list[Point]:
    """Corners counter-clockwise, computed without the module under test."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    local = [(length_m / 2, width_m / 2), (-length_m / 2, width_m / 2), (-length_m / 2, -width_m / 2)]
    local.append((length_m / 2, -width_m / 2))
    return [(east_m + x * c - y * s, north_m + x * s + y * c) for x, y in local]


def cross(o: Point, a: Point, b: Point) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def inside(point: Point, polygon: list[Point]) -> bool:
    return all(cross(polygon[i], polygon[(i + 1) % 4], point) >= 0 for i in range(4))


def segment_distance(p: Point, a: Point, b: Point) -> float:
    ab = (b[0] - a[0], b[1] - a[1])
    t = max(0.0, min(1.0, ((p[0] - a[0]) * ab[0] + (p[1] - a[1]) * ab[1]) / (ab[0] ** 2 + ab[1] ** 2)))
    return math.hypot(p[0] - a[0] - t * ab[0], p[1] - a[1] - t * ab[1])


def point_polygon_distance(point: Point, polygon: list[Point]) -> float:
    if inside(point, polygon):
        return 0.0
    return min(segment_distance(point, polygon[i], polygon[(i + 1) % 4]) for i in range(4))


def segments_cross(a: Point, b: Point, c: Point, d: Point) -> bool:
    return cross(a, b, c) * cross(a, b, d) <= 0 and cross(c, d, a) * cross(c, d, b) <= 0


def polygon_distance(p: list[Point], q: list[Point]) -> float:
    edges_cross = any(segments_cross(p[i], p[(i + 1) % 4], q[j], q[(j + 1) % 4]) for i in range(4) for j in range(4))
    if edges_cross or inside(p[0], q) or inside(q[0], p):
        return 0.0
    return min(min(point_polygon_distance(v, q) for v in p), min(point_polygon_distance(v, p) for v in q))


def oracle_distance(state: VehicleState, obstacle: WorldObstacle) -> float:
    vehicle = rectangle(*_rear_to_centre(state), state.yaw_rad, PARAMS.length_m, PARAMS.width_m)
    if obstacle.shape is Shape.CYLINDER:
        return max(0.0, point_polygon_distance((obstacle.east_m, obstacle.north_m), vehicle) - obstacle.radius_m)
    outline = rectangle(obstacle.east_m, obstacle.north_m, obstacle.yaw_rad, obstacle.length_m, obstacle.width_m)
    return polygon_distance(vehicle, outline)


def _rear_to_centre(state: VehicleState) -> Point:
    ahead_m = PARAMS.length_m / 2 - PARAMS.rear_overhang_m
    return state.east_m + ahead_m * math.cos(state.yaw_rad), state.north_m + ahead_m * math.sin(state.yaw_rad)


def shrunk(obstacle: WorldObstacle, by_m: float) -> WorldObstacle:
    return WorldObstacle(
        obstacle.name,
        obstacle.shape,
        obstacle.east_m,
        obstacle.north_m,
        obstacle.height_m,
        radius_m=max(0.0, obstacle.radius_m - by_m),
        length_m=max(0.0, obstacle.length_m - 2 * by_m),
        width_m=max(0.0, obstacle.width_m - 2 * by_m),
        yaw_rad=obstacle.yaw_rad,
    )


coordinate = st.floats(-5.0, 5.0)
angle = st.floats(-math.pi, math.pi)
size = st.floats(0.05, 4.0)
obstacles = st.one_of(
    st.builds(box, coordinate, coordinate, size, size, angle),
    st.builds(cylinder, coordinate, coordinate, st.floats(0.02, 2.0)),
)


@given(st.builds(VehicleState, east_m=st.floats(-2.0, 2.0), north_m=st.floats(-2.0, 2.0), yaw_rad=angle), obstacles)
@settings(max_examples=400, deadline=None)
def test_collision_and_clearance_agree_with_a_polygon_oracle(state: VehicleState, obstacle: WorldObstacle) -> None:
    expected_m = oracle_distance(state, obstacle)
    if expected_m > 1e-9:
        assert not hits(state, obstacle)
        assert clearance_m(state, obstacle, PARAMS) == pytest.approx(expected_m, abs=1e-9)
    elif oracle_distance(state, shrunk(obstacle, 1e-6)) == 0.0:
        # Clearly overlapping (still so when shrunk), away from the rounding of exact touching.
        assert hits(state, obstacle)
        assert clearance_m(state, obstacle, PARAMS) == 0.0
