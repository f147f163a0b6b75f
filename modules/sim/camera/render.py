"""The simulated ESVS cameras: a rectified stereo pair of the scenario world, with ground truth.

Each camera is ray-cast, not rasterised: every pixel's ray (precomputed per rig, see rays.py)
meets the flat ground at a known depth; the few pixels that look at a ditch or berm are
re-intersected exactly with the lidars' terrain model; the obstacles within range are
intersected over the pixel rectangles they project to, and a depth test keeps the nearest
surface. Surfaces are coloured from world-anchored procedural textures, so the right image,
rendered the same way from the right camera's centre, shows the same ground shifted by exactly
the disparity f*B/depth. Sensor noise and a small gain/offset mismatch between the cameras are
added last.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from brain.pose import Pose
from modules.esvs.geometry import RASCAL_RIG, StereoRig
from modules.sim.camera import solids, terrain
from modules.sim.camera.rays import RigRays, rig_rays
from modules.sim.camera.road import RoadDecal, draw_decal, lane_arrays
from modules.sim.camera.textures import FIXED_ONE, TextureSet, texture_set
from modules.sim.world import TerrainHazard, Texture, World, WorldObstacle

# Label image values; a positive label k is world.obstacles[k - 1].
LABEL_GROUND = 0
LABEL_SKY = -1
LABEL_LANE_BORDER = -2  # ground inside a road-edge band
LABEL_HAZARD = -3  # ground inside a ditch, berm or drop-off strip

_MATERIAL_SKY, _MATERIAL_GROUND, _MATERIAL_LANE = 0, 1, 2
_MATERIAL_OF_TEXTURE = {texture: 3 + i for i, texture in enumerate(Texture)}
_SKY_TINT = (1.18, 1.03, 0.86)
_LANE_TINT = (0.88, 0.98, 1.06)
_NEAR_M = 0.05  # solids are clipped this far in front of the camera plane before projection
_MOTTLE_STEP = 4  # the ground mottle is sampled every this many columns
_NOISE_BANK_SEED = 0x5E4503  # the sensor noise bank is fixed; each frame's windows come from its rng
_NOISE_BANK_IMAGES = 4  # bank per camera, in images

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class CameraConfig:
    """Scene look and sensor model. Brightness values are 8-bit digital numbers (DN)."""

    texture_seed: int = 2005
    far_m: float = 1000.0  # ground beyond this is lost in the haze and rendered as sky
    obstacle_range_m: float = 120.0  # obstacles farther from the camera are not drawn
    hazard_range_m: float = 150.0  # ditches and berms farther away are drawn as flat ground
    visibility_m: float = 2500.0  # haze: contrast falls as exp(-depth / visibility)
    sky_horizon_dn: float = 205.0
    sky_zenith_dn: float = 165.0
    sun_elevation_deg: float = 55.0
    sun_azimuth_rad: float = 2.4  # ENU, counter-clockwise from east (south-east-ish afternoon sun)
    ambient: float = 0.4
    diffuse: float = 0.7
    road_edge_width_m: float = 0.45
    road_edge_gain: float = 1.35  # windrows of loose soil are lighter than the road bed
    road_range_m: float = 150.0
    road_resolution_m: float = 0.08
    lod_bias: float = 1.0  # >1 picks blurrier texture levels
    noise_std_dn: float = 1.5
    left_gain: float = 1.0
    left_offset_dn: float = 0.0
    right_gain: float = 1.03  # the two cameras' gains and black levels never quite agree
    right_offset_dn: float = -2.0
    buried_m: float = 1.0  # solids reach this far below z = 0, so ditches don't undercut them

    def __post_init__(self) -> None:
        positive = ("far_m", "obstacle_range_m", "hazard_range_m", "visibility_m", "road_range_m")
        positive += ("road_resolution_m", "road_edge_width_m", "lod_bias", "left_gain", "right_gain")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"CameraConfig.{name} must be a positive number, got {value!r}")
        if not (math.isfinite(self.noise_std_dn) and self.noise_std_dn >= 0):
            raise ValueError(f"CameraConfig.noise_std_dn must be >= 0, got {self.noise_std_dn!r}")
        if not 0 < self.sun_elevation_deg <= 90:
            raise ValueError(f"CameraConfig.sun_elevation_deg must be in (0, 90], got {self.sun_elevation_deg!r}")


@dataclass(frozen=True)
class StereoFrame:
    """One rectified pair and its ground truth (all images rig.height_px x rig.width_px).

    ``disparity_px`` is the left image's true disparity f*B/depth, NaN where the pixel sees sky
    (no surface within the far limit); ``labels`` says what each left pixel shows (LABEL_* or
    an obstacle as its index in ``obstacles`` plus one)."""

    left: NDArray[np.uint8]
    right: NDArray[np.uint8]
    disparity_px: NDArray[np.float32]
    depth_m: NDArray[np.float32]  # left depth along the optical axis, inf for sky
    labels: NDArray[np.int16]
    right_disparity_px: NDArray[np.float32]  # the right image's own truth (for left-right checks)
    pose: Pose
    rig: StereoRig
    obstacles: tuple[WorldObstacle, ...]
    left_bgr: NDArray[np.uint8] | None = field(default=None, repr=False)
    right_bgr: NDArray[np.uint8] | None = field(default=None, repr=False)

    def obstacle(self, label: int) -> WorldObstacle | None:
        """The obstacle a label value names, None for ground, sky and the other classes."""
        return self.obstacles[label - 1] if 0 < label <= len(self.obstacles) else None

    def visible_obstacles(self) -> dict[str, int]:
        """Name -> number of left-image pixels, for every obstacle in view."""
        counts = np.bincount(self.labels[self.labels > 0].ravel(), minlength=len(self.obstacles) + 1)
        return {self.obstacles[k - 1].name: int(counts[k]) for k in np.flatnonzero(counts)}


@dataclass
class _Truth:
    """What each pixel shows: label (LABEL_* or obstacle index + 1) and material (for colour)."""

    labels: NDArray[np.int16]
    material: NDArray[np.uint8]


@dataclass
class _View:
    """One camera's render before the sensor: radiance in DN, depth, and the truth if asked for."""

    radiance: NDArray[np.float32]
    depth: NDArray[np.float32]
    truth: _Truth | None


@dataclass
class _Ground:
    """One camera's ground hits below the horizon (vehicle frame, float32), and the pixels a
    hazard changed: their rows and columns (relative to first_ground_row), shading relative to
    flat ground, and whether the hit lies inside a hazard's strip."""

    forward: NDArray[np.float32]
    left: NDArray[np.float32]
    texture_forward: NDArray[np.float32] | None = None  # where texture is looked up, if not (forward, left)
    texture_left: NDArray[np.float32] | None = None
    rows: NDArray[np.intp] | None = None
    cols: NDArray[np.intp] | None = None
    relief_shade: NDArray[np.float32] | None = None
    in_hazard: NDArray[np.bool_] | None = None


@dataclass(frozen=True)
class _FrameScene:
    """What one pose sees, in the vehicle frame: shared by both cameras of the pair."""

    pose: Pose
    obstacles: list[tuple[int, WorldObstacle]]  # (index in world.obstacles, vehicle-frame copy)
    hazards: list[TerrainHazard]
    decal: RoadDecal | None
    sun: FloatArray  # unit vector towards the sun, vehicle frame


@dataclass(frozen=True)
class _Flat:
    """One camera's view of flat ground, the same at every pose: a frame starts from it and
    changes only the pixels a hazard moved."""

    seen: NDArray[np.bool_]  # rows from first_ground_row down: flat ground within far_m
    radiance: NDArray[np.float32]  # whole image: the sky, and the haze's share of the ground where seen
    labels: NDArray[np.int16]  # whole image: LABEL_GROUND where seen, LABEL_SKY elsewhere
    material: NDArray[np.uint8]
    decal_forward: NDArray[np.float32]  # ground rows: where the flat-ground hit lies in road-decal pixels
    decal_left: NDArray[np.float32]
    mottle_forward: NDArray[np.float32]  # ground rows, every fourth column: the flat-ground hit
    mottle_left: NDArray[np.float32]


class StereoRenderer:
    """Renders stereo pairs of one world from one rig; build once, call ``render`` per pose."""

    def __init__(self, world: World, rig: StereoRig = RASCAL_RIG, config: CameraConfig | None = None) -> None:
        self.world = world
        self.rig = rig
        self.config = config or CameraConfig()
        self.rays: RigRays = rig_rays(rig, self.config.far_m)
        self.textures: TextureSet = texture_set(self.config.texture_seed)
        obstacles = world.obstacles
        self._centres = np.array([(o.east_m, o.north_m) for o in obstacles], dtype=float).reshape(-1, 2)
        self._radii = np.array([o.footprint_radius_m() for o in obstacles], dtype=float)
        self._lanes = lane_arrays(world.lane_borders)
        self._sky = self._sky_radiance()
        self._lod_bands = self._ground_bands()
        self._row_gain, self._row_offset = self._ground_rows()
        self._flat = (self._flat_view(right=False), self._flat_view(right=True))
        # Brightness factor of each road-edge coverage level (0-255).
        self._edge_gain = (1.0 + (self.config.road_edge_gain - 1.0) * np.arange(256) / 255).astype(np.float32)
        # Offsets into the material tiles, fixed per obstacle so twin rocks don't look identical.
        golden = (math.sqrt(5) - 1) / 2
        self._texture_offsets = [
            ((i * golden) % 1.0 * 7.3, (i * golden * golden) % 1.0 * 5.1) for i in range(len(obstacles))
        ]

    # -- public ---------------------------------------------------------------------------------

    def render(
        self,
        pose: Sequence[float],
        rng: np.random.Generator | None = None,
        color: bool = False,
        *,
        noise_gain: float = 1.0,
    ) -> StereoFrame:
        """The pair seen from a vehicle at ``pose`` = (east_m, north_m, yaw_rad), with its ground
        truth. Sensor noise is drawn from ``rng`` (none without one), ``noise_gain`` times the
        configured level; ``color`` adds BGR images."""
        pose = _pose(pose)
        left, right = self._views(pose, truth=True)
        left_image, right_image = self._sensor(left, right, rng, noise_gain)
        assert left.truth is not None and right.truth is not None
        left_bgr = right_bgr = None
        if color:
            table = _tint_table(self.textures)
            left_bgr = _tinted(left_image, left.truth.material, table)
            right_bgr = _tinted(right_image, right.truth.material, table)
        return StereoFrame(
            left=left_image,
            right=right_image,
            disparity_px=self._disparity(left.depth),
            depth_m=left.depth,
            labels=left.truth.labels,
            right_disparity_px=self._disparity(right.depth),
            pose=pose,
            rig=self.rig,
            obstacles=self.world.obstacles,
            left_bgr=left_bgr,
            right_bgr=right_bgr,
        )

    def images(
        self, pose: Sequence[float], rng: np.random.Generator | None = None, *, noise_gain: float = 1.0
    ) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        """The left and right images ``render`` gives, without the ground truth, which is a
        tenth of the cost: what a camera delivers."""
        return self._sensor(*self._views(_pose(pose), truth=False), rng, noise_gain)

    # -- per frame ------------------------------------------------------------------------------

    def _views(self, pose: Pose, truth: bool) -> tuple[_View, _View]:
        scene = self._frame_scene(pose)
        return self._view(scene, right=False, truth=truth), self._view(scene, right=True, truth=truth)

    def _sensor(
        self, left: _View, right: _View, rng: np.random.Generator | None, noise_gain: float
    ) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        if not (math.isfinite(noise_gain) and noise_gain >= 0):
            raise ValueError(f"noise_gain must be >= 0, got {noise_gain!r}")
        cfg = self.config
        std = cfg.noise_std_dn * noise_gain
        left_noise, right_noise = self._noise(rng) if rng is not None and std > 0 else (None, None)
        return (
            _exposed(left.radiance, cfg.left_gain, cfg.left_offset_dn, left_noise, std),
            _exposed(right.radiance, cfg.right_gain, cfg.right_offset_dn, right_noise, std),
        )

    def _frame_scene(self, pose: Pose) -> _FrameScene:
        cfg = self.config
        east, north, yaw = pose
        obstacles = []
        if len(self._centres):
            reach = np.hypot(self._centres[:, 0] - east, self._centres[:, 1] - north) - self._radii
            for index in np.flatnonzero(reach <= cfg.obstacle_range_m):
                obstacles.append((int(index), solids.to_vehicle_frame(self.world.obstacles[index], east, north, yaw)))
        hazards = []
        for hazard in self.world.hazards:
            reach = (
                math.hypot(hazard.east_m - east, hazard.north_m - north)
                - math.hypot(hazard.length_m, hazard.width_m) / 2
            )
            if reach <= cfg.hazard_range_m:
                hazards.append(terrain.to_vehicle_frame(hazard, east, north, yaw))
        decal = None
        if self._lanes:
            half_width = cfg.road_range_m * math.tan(math.radians(self.rig.hfov_deg) / 2) + 2.0
            decal = draw_decal(
                self._lanes,
                east,
                north,
                yaw,
                cfg.road_range_m,
                half_width,
                cfg.road_resolution_m,
                cfg.road_edge_width_m,
            )
        elevation = math.radians(cfg.sun_elevation_deg)
        azimuth = cfg.sun_azimuth_rad - yaw
        sun = np.array(
            [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
        )
        return _FrameScene(pose, obstacles, hazards, decal, sun)

    def _view(self, scene: _FrameScene, right: bool, truth: bool) -> _View:
        rays = self.rays
        centre = rays.camera_centre(right)
        flat = self._flat[int(right)]
        view = _View(np.array(flat.radiance), np.array(rays.flat_depth), None)
        if truth:
            view.truth = _Truth(flat.labels.copy(), flat.material.copy())
        if rays.first_ground_row < self.rig.height_px:
            ground = _Ground(rays.ground_forward, rays.ground_left(right))
            if scene.hazards:
                self._terrain(scene, centre, right, view.depth, ground)
            self._ground(scene, flat, ground, view)
        for index, obstacle in scene.obstacles:
            self._obstacle(scene, index, obstacle, centre, right, view)
        return view

    def _terrain(self, scene: _FrameScene, centre: FloatArray, right: bool, depth: FloatArray, ground: _Ground) -> None:
        """Re-intersect the ground pixels that may see a hazard; updates ``depth`` and ``ground``."""
        top = self.rays.first_ground_row
        near = np.zeros(ground.forward.shape, dtype=bool)
        for item in scene.hazards:
            box = self._pixel_box(terrain.corners(item), right)
            if box is not None and box[1] > top:
                r0, r1, c0, c1 = max(box[0], top), box[1], box[2], box[3]
                direction = self.rays.direction[r0:r1, c0:c1].reshape(-1, 3)
                flat = self.rays.flat_depth[r0:r1, c0:c1].reshape(-1)
                near[r0 - top : r1 - top, c0:c1] |= terrain.may_hit(item, centre, direction, flat).reshape(r1 - r0, -1)
        index = np.flatnonzero(near)
        if not index.size:
            return
        direction = self.rays.direction[top:].reshape(-1, 3)[index]
        flat = self.rays.flat_depth[top:].reshape(-1)[index]
        hits = terrain.terrain_hits(scene.hazards, centre, direction, self.config.far_m, flat)
        rows, cols = np.unravel_index(index, near.shape)
        depth[rows + top, cols] = hits.depth
        ok = np.isfinite(hits.depth)
        t = np.where(ok, hits.depth, 0.0)
        hit_x = np.where(ok, centre[0] + t * direction[:, 0], 0.0)
        hit_y = np.where(ok, centre[1] + t * direction[:, 1], 0.0)
        hit_z = np.where(ok, centre[2] + t * direction[:, 2], 0.0)
        ground.forward, ground.left = ground.forward.copy(), ground.left.copy()
        ground.forward[rows, cols], ground.left[rows, cols] = hit_x, hit_y
        # Texture lookups slide against the horizontal part of the normal with height, which
        # unrolls a steep wall roughly to its true length instead of smearing the few ground
        # texels under it down its face.
        ground.texture_forward, ground.texture_left = ground.forward.copy(), ground.left.copy()
        ground.texture_forward[rows, cols] -= hit_z * hits.normal[:, 0]
        ground.texture_left[rows, cols] -= hit_z * hits.normal[:, 1]
        ground.rows, ground.cols = rows, cols
        ground.relief_shade = self._shade(hits.normal @ scene.sun) / self._shade(scene.sun[2])
        ground.in_hazard = hits.in_hazard

    def _ground(self, scene: _FrameScene, flat: _Flat, ground: _Ground, view: _View) -> None:
        """Textured, shaded ground with road edges and haze over the rows below the horizon."""
        top = self.rays.first_ground_row
        east, north, yaw = scene.pose
        forward, left = ground.forward, ground.left
        tex_forward = forward if ground.texture_forward is None else ground.texture_forward
        tex_left = left if ground.texture_left is None else ground.texture_left
        # Brightness relative to the soil's mean on flat ground (soil and mottle are fixed point;
        # the rows' sun, on the mottle, takes their scale out), then the haze's share is added.
        bright = np.empty(forward.shape, dtype=np.float32)
        texture = self.textures.ground.texture
        for r0, r1, level in self._lod_bands:
            bright[r0:r1] = texture.sample_ground(tex_forward[r0:r1], tex_left[r0:r1], east, north, yaw, level)
        # The mottle varies over metres: every fourth column, interpolated across, is exact enough
        # (a row can span metres far away, so rows are all sampled).
        if ground.texture_forward is None:
            mottle_forward, mottle_left = flat.mottle_forward, flat.mottle_left
        else:
            mottle_forward = np.ascontiguousarray(tex_forward[:, ::_MOTTLE_STEP])
            mottle_left = np.ascontiguousarray(tex_left[:, ::_MOTTLE_STEP])
        coarse = self.textures.ground_mottle.sample_ground(mottle_forward, mottle_left, east, north, yaw, 0)
        # The rows' sun and haze (by flat-ground depth: hazards move depths too little to matter)
        # go on the coarse mottle, a quarter of the pixels; resizing only across keeps rows apart.
        coarse = coarse * self._row_gain
        bright *= cv2.resize(coarse, (forward.shape[1], forward.shape[0]), interpolation=cv2.INTER_LINEAR)
        seen = flat.seen
        if ground.rows is not None:
            bright[ground.rows, ground.cols] *= ground.relief_shade
            seen = seen.copy()
            seen[ground.rows, ground.cols] = np.isfinite(view.depth[ground.rows + top, ground.cols])
        coverage = None
        if scene.decal is not None:
            coverage = scene.decal.coverage_px(flat.decal_forward, flat.decal_left)
            if ground.rows is not None:
                rows, cols = ground.rows, ground.cols
                coverage[rows, cols] = scene.decal.coverage(forward[rows, cols], left[rows, cols])
            bright *= cv2.LUT(coverage, self._edge_gain)
        radiance = view.radiance[top:]
        np.add(radiance, bright, out=radiance, where=flat.seen)
        if ground.rows is not None:
            rows, cols = ground.rows, ground.cols
            moved = bright[rows, cols] + self._row_offset[rows, 0]
            radiance[rows, cols] = np.where(seen[rows, cols], moved, self._sky[rows + top, cols])
        if view.truth is not None:
            _label_ground(view.truth, top, seen, ground, coverage)

    def _obstacle(
        self, scene: _FrameScene, index: int, obstacle: WorldObstacle, centre: FloatArray, right: bool, view: _View
    ) -> None:
        box = self._pixel_box(solids.corners(obstacle, self.config.buried_m), right)
        if box is None:
            return
        r0, r1, c0, c1 = box
        direction = self.rays.direction[r0:r1, c0:c1].reshape(-1, 3)
        hits = solids.solid_hits(obstacle, centre, direction, self.config.buried_m)
        current = view.depth[r0:r1, c0:c1].reshape(-1)
        closer = np.flatnonzero(hits.depth < current)
        if not closer.size:
            return
        t = hits.depth[closer]
        look = self.textures.materials[obstacle.texture]
        middle = float(np.partition(t, t.size // 2)[t.size // 2])  # a median, without np.median's overhead
        level = look.texture.level_for(middle / self.rig.focal_px * self.config.lod_bias)
        dx, dy = self._texture_offsets[index]
        value = look.texture.sample(hits.surface_x[closer] + dx, hits.surface_y[closer] + dy, level)
        value *= np.float32(look.albedo_dn)
        value *= self._shade(hits.normal[closer] @ scene.sun)
        rows, cols = np.unravel_index(closer, (r1 - r0, c1 - c0))
        rows, cols = rows + r0, cols + c0
        view.depth[rows, cols] = t
        view.radiance[rows, cols] = self._hazed(value, t)
        if view.truth is not None:
            view.truth.labels[rows, cols] = index + 1
            view.truth.material[rows, cols] = _MATERIAL_OF_TEXTURE[obstacle.texture]

    # -- helpers --------------------------------------------------------------------------------

    def _pixel_box(self, corners_vehicle: FloatArray, right: bool) -> tuple[int, int, int, int] | None:
        """Rows r0:r1 and columns c0:c1 covering the projection of a convex solid with these
        corners; None when it is wholly behind the camera or outside the image. A solid that
        straddles the camera plane is clipped to the part in front of it first."""
        rig = self.rig
        camera = rig.vehicle_to_camera(corners_vehicle, right)
        z = camera[:, 2]
        front = z > _NEAR_M
        if not front.any():
            return None
        points = camera[front]
        if not front.all():
            # Where the segments between corners in front and behind cross the near plane: with
            # the corners in front they bound the clipped solid's projection.
            ahead, behind = camera[front], camera[~front]
            a, b = ahead[:, None, :], behind[None, :, :]
            fraction = (a[..., 2] - _NEAR_M) / (a[..., 2] - b[..., 2])
            points = np.concatenate([points, (a + fraction[..., None] * (b - a)).reshape(-1, 3)])
        f = rig.focal_px
        u = f * points[:, 0] / points[:, 2] + rig.cx_px
        v = f * points[:, 1] / points[:, 2] + rig.cy_px
        c0 = max(math.floor(u.min()) - 1, 0)
        c1 = min(math.ceil(u.max()) + 2, rig.width_px)
        r0 = max(math.floor(v.min()) - 1, 0)
        r1 = min(math.ceil(v.max()) + 2, rig.height_px)
        if c0 >= c1 or r0 >= r1:
            return None
        return r0, r1, c0, c1

    def _shade(self, sun_cosine: FloatArray | float) -> NDArray[np.float32]:
        cfg = self.config
        return np.float32(cfg.ambient) + np.float32(cfg.diffuse) * np.maximum(sun_cosine, 0.0).astype(np.float32)

    def _hazed(self, value: NDArray[np.float32], depth: FloatArray) -> NDArray[np.float32]:
        """Blend towards the horizon sky with distance (aerial perspective)."""
        haze = np.float32(self.config.sky_horizon_dn)
        clear = np.exp(-np.minimum(depth, self.config.far_m) / self.config.visibility_m).astype(np.float32)
        return haze + (value - haze) * clear

    def _sky_radiance(self) -> NDArray[np.float32]:
        """Sky brightness by elevation: brightest at the horizon. The same at every pose, and the
        same pixel in both cameras (zero disparity), as a sky at infinity must be."""
        cfg = self.config
        rise = np.clip(self.rays.elevation_rad / math.radians(30.0), 0.0, 1.0)
        sky = cfg.sky_horizon_dn + (cfg.sky_zenith_dn - cfg.sky_horizon_dn) * np.sqrt(rise)
        sky = sky.astype(np.float32)
        sky.flags.writeable = False
        return sky

    def _flat_view(self, right: bool) -> _Flat:
        """One camera's view of flat ground (see ``_Flat``)."""
        rays, rig = self.rays, self.rig
        top = rays.first_ground_row
        seen = np.isfinite(rays.flat_depth[top:])
        labels = np.full((rig.height_px, rig.width_px), LABEL_SKY, dtype=np.int16)
        labels[top:][seen] = LABEL_GROUND
        material = np.where(labels == LABEL_GROUND, _MATERIAL_GROUND, _MATERIAL_SKY).astype(np.uint8)
        scale = 1.0 / self.config.road_resolution_m
        decal_forward = (rays.ground_forward * scale).astype(np.float32)
        decal_left = (rays.ground_left(right) * scale).astype(np.float32)
        mottle = (
            np.ascontiguousarray(rays.ground_forward[:, ::_MOTTLE_STEP]),
            np.ascontiguousarray(rays.ground_left(right)[:, ::_MOTTLE_STEP]),
        )
        radiance = np.array(self._sky)
        np.copyto(radiance[top:], np.broadcast_to(self._row_offset, seen.shape), where=seen)
        arrays = (seen, radiance, labels, material, decal_forward, decal_left, *mottle)
        for array in arrays:
            array.flags.writeable = False
        return _Flat(*arrays)

    def _ground_rows(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """(gain, offset) per ground row, as (rows, 1) columns, taking a brightness factor to
        radiance: the soil's albedo in the sun on flat ground, hazed towards the horizon sky by
        the row's flat-ground depth."""
        cfg = self.config
        clear = np.exp(-np.minimum(self.rays.row_depth[self.rays.first_ground_row :], cfg.far_m) / cfg.visibility_m)
        sun = float(self._shade(math.sin(math.radians(cfg.sun_elevation_deg))))
        gain = self.textures.ground.albedo_dn * sun * clear / FIXED_ONE**2
        offset = cfg.sky_horizon_dn * (1.0 - clear)
        return gain.astype(np.float32)[:, None], offset.astype(np.float32)[:, None]

    def _ground_bands(self) -> list[tuple[int, int, int]]:
        """(first row, end row, mip level) runs, relative to first_ground_row: the level matches a
        pixel's footprint across the image row, which is depth / f on flat ground."""
        rays = self.rays
        texture = self.textures.ground.texture
        bands: list[tuple[int, int, int]] = []
        for row in range(rays.first_ground_row, self.rig.height_px):
            footprint = rays.row_depth[row] / self.rig.focal_px * self.config.lod_bias
            level = texture.level_for(footprint)
            start = row - rays.first_ground_row
            if bands and bands[-1][2] == level:
                bands[-1] = (bands[-1][0], start + 1, level)
            else:
                bands.append((start, start + 1, level))
        return bands

    def _noise(self, rng: np.random.Generator) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Standard normal noise images for the left and right camera: windows at offsets drawn
        from ``rng`` into the cameras' own halves of a fixed bank. Any pixel's noise is a fresh
        bank entry, and the two cameras never share one, so stereo cannot match noise."""
        shape = (self.rig.height_px, self.rig.width_px)
        pixels = shape[0] * shape[1]
        bank = _noise_bank(pixels)
        left, right = (int(start) for start in rng.integers(0, bank.shape[1] - pixels + 1, size=2))
        return bank[0, left : left + pixels].reshape(shape), bank[1, right : right + pixels].reshape(shape)

    def _disparity(self, depth: NDArray[np.float32]) -> NDArray[np.float32]:
        disparity = np.empty(depth.shape, dtype=np.float32)
        np.divide(np.float32(self.rig.focal_px * self.rig.baseline_m), depth, out=disparity)
        disparity[depth == np.inf] = np.nan
        return disparity


def _label_ground(
    truth: _Truth, top: int, seen: NDArray[np.bool_], ground: _Ground, coverage: NDArray[np.uint8] | None
) -> None:
    """Ground, road-edge and hazard labels below the horizon, over the flat view's."""
    band, mat = truth.labels[top:], truth.material[top:]
    if ground.rows is not None:
        moved = seen[ground.rows, ground.cols]
        band[ground.rows, ground.cols] = np.where(moved, LABEL_GROUND, LABEL_SKY)
        mat[ground.rows, ground.cols] = np.where(moved, _MATERIAL_GROUND, _MATERIAL_SKY)
    if coverage is not None:
        edge = (coverage > 127) & seen  # more than half covered
        band[edge] = LABEL_LANE_BORDER
        mat[edge] = _MATERIAL_LANE
    if ground.rows is not None:
        hazard = ground.in_hazard & seen[ground.rows, ground.cols]
        band[ground.rows[hazard], ground.cols[hazard]] = LABEL_HAZARD


@lru_cache(maxsize=2)
def _noise_bank(pixels: int) -> NDArray[np.float32]:
    """(2, NOISE_BANK_IMAGES * pixels) standard normal samples, one row per camera, always the
    same: drawing them per frame would cost more than the rest of the sensor model."""
    bank = np.random.default_rng(_NOISE_BANK_SEED).standard_normal((2, _NOISE_BANK_IMAGES * pixels), dtype=np.float32)
    bank.flags.writeable = False
    return bank


def _exposed(
    radiance: NDArray[np.float32], gain: float, offset: float, noise: NDArray[np.float32] | None, std: float
) -> NDArray[np.uint8]:
    """The sensor: gain, black level and ``std`` times ``noise``, rounded and saturated to 8
    bits (``radiance`` is used as scratch)."""
    if noise is None:
        radiance *= np.float32(gain)
        radiance += np.float32(offset)
        return _to_uint8(radiance)
    return cv2.addWeighted(radiance, gain, noise, std, offset, dtype=cv2.CV_8U)


def _pose(pose: Sequence[float]) -> Pose:
    try:
        east, north, yaw = (float(value) for value in pose)
    except (TypeError, ValueError):
        raise ValueError(f"pose must be (east_m, north_m, yaw_rad), got {pose!r}") from None
    if not all(math.isfinite(value) for value in (east, north, yaw)):
        raise ValueError(f"pose must be finite, got {pose!r}")
    return Pose(east, north, yaw)


def _to_uint8(image: NDArray[np.float32]) -> NDArray[np.uint8]:
    """Rounded and saturated to 8 bits (``image`` is used as scratch)."""
    image += np.float32(0.5)
    np.clip(image, 0.0, 255.0, out=image)
    return image.astype(np.uint8)


def _tint_table(textures: TextureSet) -> NDArray[np.uint8]:
    """(materials x 256, 3) BGR for every (material, grey level): colouring a frame is one lookup."""
    tints = np.ones((3 + len(Texture), 3), dtype=np.float32)
    tints[_MATERIAL_SKY] = _SKY_TINT
    tints[_MATERIAL_GROUND] = textures.ground.tint_bgr
    tints[_MATERIAL_LANE] = _LANE_TINT
    for texture, look in textures.materials.items():
        tints[_MATERIAL_OF_TEXTURE[texture]] = look.tint_bgr
    grey = np.arange(256, dtype=np.float32)
    return _to_uint8((tints[:, None, :] * grey[None, :, None]).reshape(-1, 3))


def _tinted(grey: NDArray[np.uint8], material: NDArray[np.uint8], table: NDArray[np.uint8]) -> NDArray[np.uint8]:
    index = material.astype(np.intp) << 8
    index |= grey
    return np.take(table, index, axis=0)


@lru_cache(maxsize=4)
def _renderer(world: World, rig: StereoRig, config: CameraConfig) -> StereoRenderer:
    return StereoRenderer(world, rig, config)


def render_pair(
    world: World,
    pose: Sequence[float],
    rig: StereoRig = RASCAL_RIG,
    rng: np.random.Generator | None = None,
    *,
    config: CameraConfig | None = None,
    color: bool = False,
) -> StereoFrame:
    """Render the stereo pair a vehicle at ``pose`` = (east_m, north_m, yaw_rad) sees in
    ``world``. The renderer for a (world, rig, config) is built once and reused; for a tight
    loop, holding a StereoRenderer saves hashing the world on each call."""
    return _renderer(world, rig, config or CameraConfig()).render(pose, rng, color)


__all__ = [
    "LABEL_GROUND",
    "LABEL_HAZARD",
    "LABEL_LANE_BORDER",
    "LABEL_SKY",
    "CameraConfig",
    "StereoFrame",
    "StereoRenderer",
    "render_pair",
]
