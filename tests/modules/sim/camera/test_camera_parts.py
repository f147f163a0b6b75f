"""The renderer's parts: seamless world-anchored textures, exact ray hits on solids and terrain,
and road-edge bands where the lane borders run."""

from __future__ import annotations

import math

import numpy as np
import pytest

from modules.sim.camera import solids, terrain
from modules.sim.camera.road import draw_decal, lane_arrays
from modules.sim.camera.textures import FIXED_ONE, MipTexture, periodic_noise, remap_wrapped, texture_set
from modules.sim.terrain import ground_height
from modules.sim.world import HazardKind, LaneBorderLine, Shape, TerrainHazard, WorldObstacle


def test_noise_tiles_are_normalised_and_wrap_without_a_seam() -> None:
    tile = periodic_noise(256, np.random.default_rng(0), slope=1.0)
    assert abs(float(tile.mean())) < 1e-5 and float(tile.std()) == pytest.approx(1.0, rel=1e-4)
    inside = np.abs(np.diff(tile, axis=1)).mean()
    across_seam = np.abs(tile[:, 0] - tile[:, -1]).mean()
    assert across_seam < 1.5 * inside


def test_mip_levels_halve_and_keep_the_mean() -> None:
    texture = MipTexture.from_tile(periodic_noise(64, np.random.default_rng(1)) + 1.0, texel_m=0.01)
    assert [level.shape[0] for level in texture.levels] == [64, 32, 16, 8, 4]
    assert all(float(level.mean()) == pytest.approx(1.0, abs=1e-5) for level in texture.levels)
    for level, fixed in zip(texture.levels, texture.fixed, strict=True):  # saturated outside [0, 4)
        expected = np.clip(level, 0.0, np.iinfo(np.uint16).max / FIXED_ONE)
        assert fixed.dtype == np.uint16 and np.abs(fixed / FIXED_ONE - expected).max() <= 0.5 / FIXED_ONE
    assert texture.level_for(0.005) == 0 and texture.level_for(0.045) == 2 and texture.level_for(10.0) == 4
    with pytest.raises(ValueError, match="power-of-two"):
        MipTexture.from_tile(np.zeros((48, 48), np.float32), texel_m=0.01)


@pytest.mark.parametrize("level", [0, 3])
def test_ground_lookup_is_anchored_to_the_world_whatever_the_pose(level: int) -> None:
    soil = texture_set(2005).ground.texture
    rng = np.random.default_rng(2)
    forward = rng.uniform(3.0, 60.0, (40, 50)).astype(np.float32)
    left = rng.uniform(-20.0, 20.0, (40, 50)).astype(np.float32)
    for east, north, yaw in ((0.0, 0.0, 0.0), (1234.56, -987.6, 2.5), (-40.1, 3001.7, -1.1)):
        c, s = math.cos(yaw), math.sin(yaw)
        f64, l64 = forward.astype(float), left.astype(float)
        expected = soil.sample(east + c * f64 - s * l64, north + s * f64 + c * l64, level)
        difference = np.abs(soil.sample_ground(forward, left, east, north, yaw, level) / FIXED_ONE - expected)
        # cv2.remap weights texels in 1/32 steps, so a rounding-level shift in a coordinate can
        # move a value by 1/32 of the step between neighbouring texels; no more. The fixed-point
        # levels add at most a unit either way.
        assert float(np.median(difference)) < 2 / FIXED_ONE and float(difference.max()) < 0.03


def test_long_flat_lookups_are_folded_for_opencv() -> None:
    image = np.arange(16, dtype=np.float32).reshape(4, 4)
    cols = np.tile(np.array([0.0, 1.5, 3.0, 4.0], np.float32), 20_000)
    rows = np.full(cols.shape, 2.0, np.float32)
    out = remap_wrapped(image, cols, rows)
    assert out.shape == cols.shape
    np.testing.assert_allclose(out[:4], [8.0, 9.5, 11.0, 8.0])  # column 4 wraps to column 0
    np.testing.assert_array_equal(out[-4:], out[:4])


def rays_towards(origin: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Ray directions with unit x component, like the renderer's (camera looking along x)."""
    direction = targets - origin
    return direction / direction[:, :1]


def test_box_hits_are_on_the_face_the_ray_enters() -> None:
    box = WorldObstacle("b", Shape.BOX, 10.0, 0.0, 1.0, length_m=2.0, width_m=1.0, yaw_rad=0.0)
    origin = np.array([0.0, 0.0, 1.5])
    targets = np.array([[9.0, 0.2, 0.5], [10.0, 0.0, 1.0], [9.0, 3.0, 0.5], [9.0, 0.0, 1.4]])
    hits = solids.solid_hits(box, origin, rays_towards(origin, targets), base_m=1.0)
    assert hits.depth[0] == pytest.approx(9.0) and hits.depth[1] == pytest.approx(10.0)
    np.testing.assert_allclose(hits.normal[0], [-1.0, 0.0, 0.0])  # front face
    np.testing.assert_allclose(hits.normal[1], [0.0, 0.0, 1.0])  # through the top
    assert math.isinf(hits.depth[2])  # passes beside it
    assert math.isinf(hits.depth[3])  # passes over the front edge, lands beyond (x = 9 at z = 1.4 > 1)
    turned = WorldObstacle("t", Shape.BOX, 10.0, 0.0, 1.0, length_m=2.0, width_m=1.0, yaw_rad=math.pi / 2)
    hit = solids.solid_hits(turned, origin, rays_towards(origin, np.array([[9.5, 0.0, 0.5]])), base_m=1.0)
    assert hit.depth[0] == pytest.approx(9.5)  # turned a quarter, its front face is half the width away


def test_cylinder_hits_on_the_side_and_the_top() -> None:
    pole = WorldObstacle("p", Shape.CYLINDER, 10.0, 0.0, 1.0, radius_m=0.5)
    origin = np.array([0.0, 0.0, 1.5])
    targets = np.array([[9.5, 0.0, 0.5], [10.0, 0.0, 1.0], [9.6, 0.3, 0.2], [9.5, 0.8, 0.5]])
    hits = solids.solid_hits(pole, origin, rays_towards(origin, targets), base_m=1.0)
    assert hits.depth[0] == pytest.approx(9.5)
    np.testing.assert_allclose(hits.normal[0], [-1.0, 0.0, 0.0], atol=1e-9)
    assert hits.depth[1] == pytest.approx(10.0) and hits.normal[1][2] == 1.0
    assert hits.depth[2] == pytest.approx(9.6)  # (9.6, 0.3) is on the circle
    assert math.isinf(hits.depth[3])


def marched_depth(hazards: list[TerrainHazard], origin: np.ndarray, direction: np.ndarray) -> float:
    """Brute force: the first of many small steps along the ray that is under the terrain."""
    t = np.arange(8.0, 50.0, 0.001)
    points = origin + t[:, None] * direction
    under = points[:, 2] <= ground_height(hazards, points[:, 0], points[:, 1])
    return float(t[np.argmax(under)]) if under.any() else math.inf


SEPARATE = [  # each ray meets at most one: solved piece by piece
    TerrainHazard("d", HazardKind.DITCH, 14.0, 0.5, 0.2, 2.5, 8.0, 0.7),
    TerrainHazard("b", HazardKind.BERM, 24.0, -1.0, 1.4, 4.0, 3.0, 0.6),
    TerrainHazard("c", HazardKind.DROP_OFF, 36.0, 3.0, 0.0, 14.0, 5.0, 1.0),
]
OVERLAPPING = [  # the berm stands on the drop-off's lower level: heights add
    TerrainHazard("d", HazardKind.DITCH, 14.0, 0.5, 0.2, 2.5, 8.0, 0.7),
    TerrainHazard("b", HazardKind.BERM, 22.0, -1.0, 1.4, 4.0, 3.0, 0.6),
    TerrainHazard("c", HazardKind.DROP_OFF, 30.0, 2.0, 0.0, 20.0, 6.0, 1.0),
]


@pytest.mark.parametrize("hazards", [SEPARATE, OVERLAPPING], ids=["separate", "overlapping"])
def test_terrain_hits_match_marching_along_the_ray(hazards: list[TerrainHazard]) -> None:
    origin = np.array([1.6, 0.15, 1.5])
    rng = np.random.default_rng(4)
    ends = np.column_stack([rng.uniform(10.0, 40.0, 200), rng.uniform(-4.0, 6.0, 200), np.zeros(200)])
    direction = rays_towards(origin, ends)
    flat = ends[:, 0] - origin[0]
    hits = terrain.terrain_hits(hazards, origin, direction, 1000.0, flat)
    marched = np.array([marched_depth(hazards, origin, d) for d in direction])
    np.testing.assert_allclose(hits.depth, marched, atol=0.002)
    changed = np.abs(marched - flat) > 0.01
    assert changed.sum() > 20  # the hazards really were in the way of many rays
    hit = ends[:, :2] + (hits.depth - flat)[:, None] * direction[:, :2]
    inside = np.zeros(len(hit), dtype=bool)
    for hazard in hazards:
        c, s = math.cos(hazard.yaw_rad), math.sin(hazard.yaw_rad)
        rx, ry = hit[:, 0] - hazard.east_m, hit[:, 1] - hazard.north_m
        inside |= (np.abs(rx * c + ry * s) <= hazard.length_m / 2 + 1e-3) & (
            np.abs(-rx * s + ry * c) <= hazard.width_m / 2 + 1e-3
        )
    assert np.all(inside[hits.in_hazard]) and np.all(hits.in_hazard[changed])
    np.testing.assert_allclose(np.linalg.norm(hits.normal, axis=1), 1.0)
    # may_hit is conservative: every ray whose hit moved off the flat ground is flagged by some hazard.
    flagged = np.zeros(len(direction), bool)
    for hazard in hazards:
        flagged |= terrain.may_hit(hazard, origin, direction, flat)
    assert np.all(flagged[changed])


def test_road_edges_cover_the_lane_border_and_nothing_beside_it() -> None:
    line = LaneBorderLine("edge", tuple((float(x), 3.0) for x in range(-10, 200)))
    decal = draw_decal(lane_arrays((line,)), 0.0, 0.0, 0.0, 150.0, 60.0, 0.08, 0.45)
    forward = np.array([5.0, 20.0, 60.0, 140.0, 20.0, 20.0, 160.0])
    left = np.array([3.0, 3.0, 3.05, 2.95, 3.6, 2.0, 3.0])
    coverage = decal.coverage(forward, left)
    assert coverage.dtype == np.uint8
    assert np.all(coverage[:4] > 0.8 * 255)
    assert np.all(coverage[4:] < 0.05 * 255)  # 0.6 m and 1 m beside it, and beyond the decal's range
    # Turned and moved, the same world line lands at the same world place.
    yaw = 0.9
    moved = draw_decal(
        lane_arrays((line,)), 20.0 - 10 * math.cos(yaw), 3.0 - 10 * math.sin(yaw), yaw, 150.0, 60.0, 0.08, 0.45
    )
    assert moved.coverage(np.array([10.0]), np.array([0.0]))[0] > 0.8 * 255
