"""Obstacle recall, precision and range error of the ESVS vision pipeline on simulated scenes.

``evaluate(scenes, clear_frames, seed)`` renders seeded random worlds with the simulated cameras,
runs ``modules.esvs.vision.process`` on every pair and scores its ObstacleList against the truth
the renderer knows; ``format_report`` prints the result as a plain-text table
(``rascal esvs eval --simulated``).

Definitions (every distance horizontal, in the VEHICLE frame of the rendered pose):

* **range** of a true obstacle: from the ground point under the middle of the camera pair
  (x = rig.mount_forward_m, y = 0) to the nearest point of the obstacle's footprint. The range
  bands (10-15 ... 30-35 m) and the 5 % tolerances use this range. A descriptor's range from the
  cameras is worked out from its ``range_m`` (measured from the vehicle origin) and its bearing.
* **scenes**: 2-4 boxes and cylinders 0.5-2 m tall and 0.3-2 m across (diameter, or each side),
  any yaw and ``Texture``, their nearest footprint points 10-35 m from the cameras, footprint
  centres anywhere across the horizontal field of view, footprints at least ``min_gap_m`` apart;
  road edges in some. **Clear frames**: the same ground, road edges, and in some a ditch
  (0.3-1 m deep) or a low berm (under 0.3 m, Algorithm 1's smallest step) crossing the path.
  Every world is seen from a random pose, so ground texture and sun direction vary.
* **shown** (counted for recall): an obstacle with at least ``min_visible_px`` left-image pixels
  that the right camera's image also contains (column minus true disparity inside the image);
  its truth range for the range error is the nearest of those visible surface points from the
  vehicle origin (the quantity ``Obstacle.range_m`` estimates), so partly hidden obstacles are
  judged on what can be seen.
* **match**: a descriptor matches a true obstacle when its centre (x_m, y_m) lies within
  ``max(0.5 m, 5 % of range) + footprint radius`` of the footprint centre; pairs are taken
  greedily, closest first, one to one. Every obstacle showing any pixel can be matched; one
  showing too little to be counted is neither a miss nor, when matched, a false descriptor.
* **range error**: |range_m - truth range| as a share of the range from the cameras; the
  lateral error likewise compares ``y_m`` with the middle of the visible part's lateral extent.
* **precision**: of the descriptors in scene frames whose own range from the cameras falls in a
  band, the share matched to an obstacle.
* **false descriptors on clear terrain**: every descriptor in a clear frame, whatever its range.

Each miss is given a cause (``Miss``): blind columns, mostly hidden behind another obstacle,
merged with another obstacle into one descriptor, or not found.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import TypeVar

import numpy as np

from brain.pose import Pose
from modules.esvs.geometry import RASCAL_RIG, StereoRig
from modules.esvs.vision.pipeline import VisionParams, process
from modules.sim.camera import solids
from modules.sim.camera.rays import rig_rays
from modules.sim.camera.render import StereoFrame, StereoRenderer
from modules.sim.world import HazardKind, LaneBorderLine, Shape, TerrainHazard, Texture, World, WorldObstacle
from protocol.messages import Obstacle

RANGE_BANDS_M: tuple[tuple[float, float], ...] = ((10.0, 15.0), (15.0, 20.0), (20.0, 25.0), (25.0, 30.0), (30.0, 35.0))
WITHIN = 0.05  # the done-means' share of range
HIDDEN = 0.5  # an obstacle showing less than this share of what it would alone is "mostly hidden"


@dataclass(frozen=True)
class SceneParams:
    """What the random worlds hold."""

    min_obstacles: int = 2
    max_obstacles: int = 4
    near_m: float = 10.0  # range from the cameras of the nearest footprint point
    far_m: float = 35.0
    min_height_m: float = 0.5
    max_height_m: float = 2.0
    min_size_m: float = 0.3  # box sides and cylinder diameters
    max_size_m: float = 2.0
    min_gap_m: float = 1.0  # between the footprint circles of two obstacles
    road_share: float = 0.5  # of worlds with road edges
    ditch_share: float = 1 / 3  # of clear frames with a ditch across the path
    berm_share: float = 1 / 3  # of clear frames with a low berm across the path
    min_visible_px: int = 50

    def __post_init__(self) -> None:
        if not 1 <= self.min_obstacles <= self.max_obstacles:
            raise ValueError(f"need 1 <= min_obstacles <= max_obstacles: {self.min_obstacles}, {self.max_obstacles}")
        if not 0 < self.near_m < self.far_m:
            raise ValueError(f"need 0 < near_m < far_m, got {self.near_m}, {self.far_m}")
        if not 0 < self.min_height_m <= self.max_height_m or not 0 < self.min_size_m <= self.max_size_m:
            raise ValueError("heights and sizes must be positive ranges")
        if self.min_gap_m < 0 or self.min_visible_px < 1:
            raise ValueError("min_gap_m must be >= 0 and min_visible_px >= 1")
        for name in ("road_share", "ditch_share", "berm_share"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in [0, 1]")
        if self.ditch_share + self.berm_share > 1:
            raise ValueError("ditch_share + berm_share must not exceed 1")


# --- worlds ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Scene:
    """One world and the pose it is seen from; ``obstacles`` and ``hazards`` are the world's, in
    the VEHICLE frame of that pose (same order, so label k is obstacles[k - 1])."""

    world: World
    pose: Pose
    obstacles: tuple[WorldObstacle, ...]
    hazards: tuple[TerrainHazard, ...]
    terrain: str  # "flat", "ditch" or "berm"
    road: bool


def camera_range(rig: StereoRig, x_m: float, y_m: float) -> float:
    """Horizontal distance of a VEHICLE point from the ground point under the cameras' middle."""
    return math.hypot(x_m - rig.mount_forward_m, y_m)


def nearest_camera_range(rig: StereoRig, obstacle: WorldObstacle) -> float:
    """Range (see the module docstring) of an obstacle given in the VEHICLE frame: the distance
    from the point under the cameras to the footprint (0 when that point is inside it)."""
    dx, dy = rig.mount_forward_m - obstacle.east_m, -obstacle.north_m
    if obstacle.shape is Shape.CYLINDER:
        return max(math.hypot(dx, dy) - obstacle.radius_m, 0.0)
    c, s = math.cos(obstacle.yaw_rad), math.sin(obstacle.yaw_rad)
    u, v = c * dx + s * dy, -s * dx + c * dy  # in the box's own axes
    return math.hypot(max(abs(u) - obstacle.length_m / 2, 0.0), max(abs(v) - obstacle.width_m / 2, 0.0))


def _random_obstacle(rng: np.random.Generator, name: str, params: SceneParams) -> WorldObstacle:
    height = float(rng.uniform(params.min_height_m, params.max_height_m))
    texture = list(Texture)[int(rng.integers(len(Texture)))]
    yaw = float(rng.uniform(-math.pi, math.pi))
    if rng.random() < 0.5:
        radius = float(rng.uniform(params.min_size_m, params.max_size_m)) / 2
        return WorldObstacle(name, Shape.CYLINDER, 0.0, 0.0, height, radius_m=radius, yaw_rad=yaw, texture=texture)
    length, width = (float(v) for v in rng.uniform(params.min_size_m, params.max_size_m, 2))
    return WorldObstacle(
        name, Shape.BOX, 0.0, 0.0, height, length_m=length, width_m=width, yaw_rad=yaw, texture=texture
    )


def _place(rng: np.random.Generator, rig: StereoRig, shape: WorldObstacle, params: SceneParams) -> WorldObstacle:
    """``shape`` moved so its footprint centre is at a random bearing inside the horizontal field
    of view and its nearest footprint point at a random range from the cameras."""
    target = float(rng.uniform(params.near_m, params.far_m))
    half_fov = math.radians(rig.hfov_deg) / 2
    bearing = float(rng.uniform(-half_fov, half_fov))
    distance = target + shape.footprint_radius_m()
    placed = shape
    for _ in range(4):  # the nearest point's range moves almost one for one with the centre's
        x = rig.mount_forward_m + distance * math.cos(bearing)
        y = distance * math.sin(bearing)
        placed = replace(shape, east_m=x, north_m=y)
        distance += target - nearest_camera_range(rig, placed)
    return placed


def random_obstacles(rng: np.random.Generator, rig: StereoRig, params: SceneParams) -> tuple[WorldObstacle, ...]:
    """VEHICLE-frame obstacles for one scene, footprints at least ``min_gap_m`` apart."""
    count = int(rng.integers(params.min_obstacles, params.max_obstacles + 1))
    obstacles: list[WorldObstacle] = []
    attempts = 0
    while len(obstacles) < count:
        attempts += 1
        if attempts > 1000:
            raise ValueError(f"cannot place {count} obstacles {params.min_gap_m} m apart in the field of view")
        candidate = _place(rng, rig, _random_obstacle(rng, f"o{len(obstacles)}", params), params)
        apart = all(
            math.hypot(candidate.east_m - o.east_m, candidate.north_m - o.north_m)
            >= candidate.footprint_radius_m() + o.footprint_radius_m() + params.min_gap_m
            for o in obstacles
        )
        if apart:
            obstacles.append(candidate)
    return tuple(obstacles)


def _road_edges(rng: np.random.Generator) -> tuple[tuple[tuple[float, float], ...], ...]:
    """Two VEHICLE-frame road edges, y = +-half width + offset + curvature * x^2, -10 to 120 m."""
    half_width = float(rng.uniform(2.5, 5.0))
    offset = float(rng.uniform(-1.0, 1.0))
    curvature = float(rng.uniform(-0.004, 0.004))
    xs = np.linspace(-10.0, 120.0, 66)
    return tuple(
        tuple((float(x), float(side * half_width + offset + curvature * x * x)) for x in xs) for side in (1.0, -1.0)
    )


def _crossing(rng: np.random.Generator, rig: StereoRig, kind: HazardKind) -> TerrainHazard:
    """A VEHICLE-frame ditch or low berm across the path, 12-33 m from the cameras."""
    if kind is HazardKind.DITCH:
        length, magnitude = float(rng.uniform(1.5, 4.0)), float(rng.uniform(0.3, 1.0))
    else:
        length, magnitude = float(rng.uniform(1.0, 3.0)), float(rng.uniform(0.1, 0.25))
    return TerrainHazard(
        name=kind.value,
        kind=kind,
        east_m=rig.mount_forward_m + float(rng.uniform(12.0, 33.0)),
        north_m=float(rng.uniform(-3.0, 3.0)),
        yaw_rad=float(rng.uniform(-0.3, 0.3)),
        length_m=length,
        width_m=float(rng.uniform(8.0, 25.0)),
        magnitude_m=magnitude,
    )


_Placed = TypeVar("_Placed", WorldObstacle, TerrainHazard)


def _to_world(pose: Pose, x: float, y: float) -> tuple[float, float]:
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    return pose.east_m + c * x - s * y, pose.north_m + s * x + c * y


def _placed_in_world(pose: Pose, item: _Placed) -> _Placed:
    """A VEHICLE-frame obstacle or hazard moved into the world a vehicle at ``pose`` sees."""
    east, north = _to_world(pose, item.east_m, item.north_m)
    return replace(item, east_m=east, north_m=north, yaw_rad=item.yaw_rad + pose.yaw_rad)


def _random_pose(rng: np.random.Generator) -> Pose:
    east, north = (float(v) for v in rng.uniform(-5000.0, 5000.0, 2))
    return Pose(east, north, float(rng.uniform(-math.pi, math.pi)))


def build_scene(
    rng: np.random.Generator, rig: StereoRig = RASCAL_RIG, params: SceneParams | None = None, clear: bool = False
) -> Scene:
    """One random world (with obstacles, or clear terrain) and the pose that sees it."""
    params = params or SceneParams()
    pose = _random_pose(rng)
    obstacles = () if clear else random_obstacles(rng, rig, params)
    road = bool(rng.random() < params.road_share)
    edges = _road_edges(rng) if road else ()
    terrain = "flat"
    hazards: tuple[TerrainHazard, ...] = ()
    if clear:
        draw = rng.random()
        if draw < params.ditch_share:
            terrain, hazards = "ditch", (_crossing(rng, rig, HazardKind.DITCH),)
        elif draw < params.ditch_share + params.berm_share:
            terrain, hazards = "berm", (_crossing(rng, rig, HazardKind.BERM),)
    world_obstacles = [_placed_in_world(pose, o) for o in obstacles]
    world_hazards = [_placed_in_world(pose, h) for h in hazards]
    lines = tuple(
        LaneBorderLine(f"edge{i}", tuple(_to_world(pose, x, y) for x, y in edge)) for i, edge in enumerate(edges)
    )
    world = World(obstacles=tuple(world_obstacles), hazards=tuple(world_hazards), lane_borders=lines)
    return Scene(world, pose, obstacles, hazards, terrain, road)


# --- truth and matching ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Truth:
    """What one frame shows of one obstacle (VEHICLE frame)."""

    obstacle: WorldObstacle
    range_m: float  # nearest footprint point from the cameras (the banding range)
    visible_px: int  # left pixels the right image also contains
    nearest_visible_m: float  # nearest visible surface point from the vehicle origin; inf if none
    visible_centre_y_m: float = math.nan  # middle of the visible surface's lateral extent
    blind_px: int = 0  # of visible_px, those in the left columns the matcher leaves without disparity
    alone_px: int = 0  # what visible_px would be with no other obstacle in front

    @property
    def visible_share(self) -> float:
        return self.visible_px / self.alone_px if self.alone_px else 0.0


def unoccluded_pixels(rig: StereoRig, obstacle: WorldObstacle) -> int:
    """Left pixels of a VEHICLE-frame obstacle on flat ground with nothing in front of it, counted
    like ``Truth.visible_px`` (the right image must hold them too)."""
    u, v, depth = rig.project(solids.corners(obstacle, 0.0))
    if not (depth > 0.05).all():
        raise ValueError(f"obstacle {obstacle.name} reaches behind the cameras")
    c0, c1 = max(math.floor(u.min()) - 1, 0), min(math.ceil(u.max()) + 2, rig.width_px)
    r0, r1 = max(math.floor(v.min()) - 1, 0), min(math.ceil(v.max()) + 2, rig.height_px)
    if c0 >= c1 or r0 >= r1:
        return 0
    direction = rig_rays(rig, 1000.0).direction[r0:r1, c0:c1].reshape(-1, 3)
    hits = solids.solid_hits(obstacle, rig.left_camera_position, direction, 0.0)
    cols = np.tile(np.arange(c0, c1), r1 - r0)
    with np.errstate(divide="ignore"):
        seen = np.isfinite(hits.depth) & (cols - rig.focal_px * rig.baseline_m / hits.depth >= 0)
    return int(seen.sum())


def frame_truth(frame: StereoFrame, obstacles: tuple[WorldObstacle, ...], blind_columns: int = 0) -> list[Truth]:
    """Per obstacle (VEHICLE frame, in label order): its range and what the cameras see of it;
    ``blind_columns`` is how many left columns the matcher cannot give a disparity."""
    rig = frame.rig
    rows, cols = np.nonzero(frame.labels > 0)
    labels = frame.labels[rows, cols].astype(np.intp)
    in_right = cols - frame.disparity_px[rows, cols] >= 0  # the right camera's image holds the point too
    rows, cols, labels = rows[in_right], cols[in_right], labels[in_right]
    depth = frame.depth_m[rows, cols].astype(float)
    camera = np.column_stack(
        ((cols - rig.cx_px) / rig.focal_px * depth, (rows - rig.cy_px) / rig.focal_px * depth, depth)
    )
    vehicle = rig.camera_to_vehicle(camera)
    ranges = np.hypot(vehicle[:, 0], vehicle[:, 1])
    count = len(obstacles) + 1
    visible = np.bincount(labels, minlength=count)
    blind = np.bincount(labels[cols < blind_columns], minlength=count)
    nearest, left, right = np.full(count, np.inf), np.full(count, -np.inf), np.full(count, np.inf)
    np.minimum.at(nearest, labels, ranges)
    np.maximum.at(left, labels, vehicle[:, 1])
    np.minimum.at(right, labels, vehicle[:, 1])
    seen = visible > 0
    centre = np.full(count, np.nan)
    centre[seen] = (left[seen] + right[seen]) / 2
    return [
        Truth(
            o,
            nearest_camera_range(rig, o),
            int(visible[k + 1]),
            float(nearest[k + 1]),
            float(centre[k + 1]),
            int(blind[k + 1]),
            unoccluded_pixels(rig, o),
        )
        for k, o in enumerate(obstacles)
    ]


def tolerance_m(truth: Truth) -> float:
    """How far a descriptor's centre may be from the footprint centre to match."""
    return max(0.5, WITHIN * truth.range_m) + truth.obstacle.footprint_radius_m()


def match(detections: tuple[Obstacle, ...], truths: list[Truth]) -> dict[int, int]:
    """Descriptor index -> truth index: greedy one-to-one, closest pair first, each pair within
    the truth's tolerance (obstacles showing no pixel cannot be matched)."""
    pairs = []
    for i, detection in enumerate(detections):
        for j, truth in enumerate(truths):
            if truth.visible_px == 0:
                continue
            gap = math.hypot(detection.x_m - truth.obstacle.east_m, detection.y_m - truth.obstacle.north_m)
            if gap <= tolerance_m(truth):
                pairs.append((gap, i, j))
    matched: dict[int, int] = {}
    taken: set[int] = set()
    for _, i, j in sorted(pairs):
        if i not in matched and j not in taken:
            matched[i] = j
            taken.add(j)
    return matched


def descriptor_camera_range(rig: StereoRig, detection: Obstacle) -> float:
    """A descriptor's range from the cameras: its ``range_m`` point (from the vehicle origin) put
    on its bearing, then measured from the cameras."""
    bearing = math.atan2(detection.y_m, detection.x_m)
    r, m = detection.range_m, rig.mount_forward_m
    return math.sqrt(max(r * r - 2 * m * r * math.cos(bearing) + m * m, 0.0))


def band_of(range_m: float) -> int | None:
    return next((i for i, (low, high) in enumerate(RANGE_BANDS_M) if low <= range_m < high), None)


# --- results -------------------------------------------------------------------------------------


@dataclass
class BandResult:
    near_m: float
    far_m: float
    shown: int = 0  # obstacles counted for recall
    found: int = 0  # of them matched
    descriptors: int = 0  # descriptors (scene frames) whose range from the cameras is in the band
    true_descriptors: int = 0  # of them matched to an obstacle
    range_errors: list[float] = field(default_factory=list)  # shares of range, per found obstacle
    lateral_errors: list[float] = field(default_factory=list)  # the same for the lateral centre

    @property
    def recall(self) -> float:
        return self.found / self.shown if self.shown else math.nan

    @property
    def precision(self) -> float:
        return self.true_descriptors / self.descriptors if self.descriptors else math.nan


@dataclass(frozen=True)
class Miss:
    """A shown obstacle no descriptor matched, and the first cause that fits: "blind columns",
    most of its visible pixels lie in the left columns the matcher cannot reach; "mostly hidden",
    it shows less than half of what it would with nothing in front of it; "merged", a
    descriptor's extent (x_m +- length/2, y_m +- width/2) reaches its footprint within
    max(0.5 m, 5 %) but went to another obstacle or to neither (two obstacles joined into one);
    "not found" otherwise."""

    scene: int
    shape: str
    range_m: float
    bearing_deg: float  # from the cameras, + left
    height_m: float
    radius_m: float  # footprint radius
    visible_px: int
    visible_share: float
    cause: str


@dataclass
class ClearTerrain:
    frames: int = 0
    frames_with_descriptors: int = 0
    descriptors: int = 0


@dataclass
class Evaluation:
    scenes: int
    clear_frames: int
    seed: int
    bands: list[BandResult]
    min_visible_px: int = 50
    other_descriptors: int = 0  # scene descriptors outside 10-35 m from the cameras
    other_true: int = 0  # of them matched
    unscored_matches: int = 0  # descriptors matched to obstacles showing too little to count
    shown_in_view: int = 0  # shown obstacles showing at least HIDDEN of what they would alone
    found_in_view: int = 0
    clear: dict[str, ClearTerrain] = field(default_factory=dict)  # by terrain: flat, ditch, berm
    misses: list[Miss] = field(default_factory=list)
    render_s: list[float] = field(default_factory=list)
    process_s: list[float] = field(default_factory=list)
    wall_s: float = 0.0

    @property
    def shown(self) -> int:
        return sum(b.shown for b in self.bands)

    @property
    def found(self) -> int:
        return sum(b.found for b in self.bands)

    @property
    def recall(self) -> float:
        return self.found / self.shown if self.shown else math.nan

    @property
    def descriptors(self) -> int:
        return sum(b.descriptors for b in self.bands) + self.other_descriptors

    @property
    def true_descriptors(self) -> int:
        return sum(b.true_descriptors for b in self.bands) + self.other_true

    @property
    def precision(self) -> float:
        return self.true_descriptors / self.descriptors if self.descriptors else math.nan

    @property
    def range_errors(self) -> list[float]:
        return [e for b in self.bands for e in b.range_errors]

    @property
    def lateral_errors(self) -> list[float]:
        return [e for b in self.bands for e in b.lateral_errors]

    @property
    def within_share(self) -> float:
        """Share of found obstacles whose range error is at most 5 % of their range."""
        errors = self.range_errors
        return sum(e <= WITHIN for e in errors) / len(errors) if errors else math.nan

    @property
    def clear_false(self) -> int:
        return sum(c.descriptors for c in self.clear.values())

    @property
    def false_per_100_clear(self) -> float:
        return 100.0 * self.clear_false / self.clear_frames if self.clear_frames else math.nan


# --- running -------------------------------------------------------------------------------------


def _miss_cause(truth: Truth, detections: tuple[Obstacle, ...]) -> str:
    if 2 * truth.blind_px > truth.visible_px:
        return "blind columns"
    if truth.visible_share < HIDDEN:
        return "mostly hidden"
    o = truth.obstacle
    slack = max(0.5, WITHIN * truth.range_m) + o.footprint_radius_m()
    for d in detections:
        dx = max(abs(o.east_m - d.x_m) - d.length_m / 2, 0.0)
        dy = max(abs(o.north_m - d.y_m) - d.width_m / 2, 0.0)
        if math.hypot(dx, dy) <= slack:
            return "merged"
    return "not found"


def score_scene(
    index: int,
    truths: list[Truth],
    detections: tuple[Obstacle, ...],
    rig: StereoRig,
    result: Evaluation,
) -> None:
    """Add one scene frame's recall, precision and range errors to ``result``."""
    matched = match(detections, truths)
    by_truth = {j: i for i, j in matched.items()}
    counted = [t.visible_px >= result.min_visible_px for t in truths]
    for i, detection in enumerate(detections):
        j = matched.get(i)
        if j is not None and not counted[j]:
            result.unscored_matches += 1
            continue
        band = band_of(descriptor_camera_range(rig, detection))
        if band is None:
            result.other_descriptors += 1
            result.other_true += j is not None
        else:
            result.bands[band].descriptors += 1
            result.bands[band].true_descriptors += j is not None
    for j, truth in enumerate(truths):
        band = band_of(truth.range_m)
        if band is None or not counted[j]:
            continue
        scores = result.bands[band]
        scores.shown += 1
        in_view = truth.visible_share >= HIDDEN
        result.shown_in_view += in_view
        if j in by_truth:
            scores.found += 1
            result.found_in_view += in_view
            detection = detections[by_truth[j]]
            scores.range_errors.append(abs(detection.range_m - truth.nearest_visible_m) / truth.range_m)
            scores.lateral_errors.append(abs(detection.y_m - truth.visible_centre_y_m) / truth.range_m)
            continue
        o = truth.obstacle
        result.misses.append(
            Miss(
                scene=index,
                shape=o.shape.value,
                range_m=truth.range_m,
                bearing_deg=math.degrees(math.atan2(o.north_m, o.east_m - rig.mount_forward_m)),
                height_m=o.height_m,
                radius_m=o.footprint_radius_m(),
                visible_px=truth.visible_px,
                visible_share=truth.visible_share,
                cause=_miss_cause(truth, detections),
            )
        )


def scene_frames(
    seed: int,
    count: int,
    clear: bool = False,
    rig: StereoRig = RASCAL_RIG,
    params: SceneParams | None = None,
) -> Iterator[tuple[Scene, StereoFrame, float]]:
    """``count`` seeded scenes (or clear-terrain frames) rendered: (scene, frame, render seconds).
    Scenes and clear frames draw from separate streams of ``seed``, so asking for more of one
    leaves the other unchanged."""
    params = params or SceneParams()
    rng = np.random.default_rng([seed, int(clear)])
    for _ in range(count):
        scene = build_scene(rng, rig, params, clear)
        start = time.perf_counter()
        frame = StereoRenderer(scene.world, rig).render(scene.pose, rng)
        yield scene, frame, time.perf_counter() - start


def evaluate(
    scenes: int = 100,
    clear_frames: int = 200,
    seed: int = 2005,
    rig: StereoRig = RASCAL_RIG,
    params: SceneParams | None = None,
    vision: VisionParams | None = None,
) -> Evaluation:
    """Render and score ``scenes`` obstacle scenes and ``clear_frames`` clear-terrain frames."""
    if scenes < 0 or clear_frames < 0 or scenes + clear_frames == 0:
        raise ValueError(f"need scenes >= 0 and clear_frames >= 0, not both 0; got {scenes}, {clear_frames}")
    params = params or SceneParams()
    vision = vision or VisionParams()
    blind_columns = vision.matcher.min_disparity + vision.matcher.num_disparities
    bands = [BandResult(low, high) for low, high in RANGE_BANDS_M]
    result = Evaluation(scenes, clear_frames, seed, bands, params.min_visible_px)
    start = time.perf_counter()

    def detect(frame: StereoFrame, render_s: float) -> tuple[Obstacle, ...]:
        began = time.perf_counter()
        found, _, _ = process(frame.left, frame.right, rig, vision)
        result.render_s.append(render_s)
        result.process_s.append(time.perf_counter() - began)
        return found.obstacles

    for index, (scene, frame, render_s) in enumerate(scene_frames(seed, scenes, False, rig, params)):
        detections = detect(frame, render_s)
        score_scene(index, frame_truth(frame, scene.obstacles, blind_columns), detections, rig, result)
    for scene, frame, render_s in scene_frames(seed, clear_frames, True, rig, params):
        detections = detect(frame, render_s)
        terrain = result.clear.setdefault(scene.terrain, ClearTerrain())
        terrain.frames += 1
        terrain.frames_with_descriptors += bool(detections)
        terrain.descriptors += len(detections)
    result.wall_s = time.perf_counter() - start
    return result


# --- report --------------------------------------------------------------------------------------


def _percent(value: float, digits: int = 1) -> str:
    return "-" if math.isnan(value) else f"{value * 100:.{digits}f} %"


def _error_cells(errors: list[float], lateral: list[float]) -> list[str]:
    if not errors:
        return ["-", "-", "-", "-"]
    p50, p95 = np.percentile(errors, [50, 95])
    within = sum(e <= WITHIN for e in errors) / len(errors)
    lateral_p95 = float(np.percentile(lateral, 95))
    return [_percent(float(p50), 2), _percent(float(p95), 2), _percent(within), _percent(lateral_p95, 2)]


def _table(rows: list[list[str]]) -> str:
    """Plain-text columns: the first left-aligned, the rest right-aligned, a rule under the header."""
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    lines = [
        "  ".join([row[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(row[1:], widths[1:], strict=True)])
        for row in rows
    ]
    lines.insert(1, "-" * len(lines[0]))
    return "\n".join(lines)


def format_table(result: Evaluation) -> str:
    """Recall, precision and range error by range band, then descriptors on clear terrain."""
    header = ["range", "shown", "found", "recall", "descr.", "true", "precision"]
    rows = [[*header, "err p50", "err p95", "err <= 5 %", "lat p95"]]
    for b in result.bands:
        counts = [str(b.shown), str(b.found), _percent(b.recall), str(b.descriptors), str(b.true_descriptors)]
        errors = _error_cells(b.range_errors, b.lateral_errors)
        rows.append([f"{b.near_m:.0f}-{b.far_m:.0f} m", *counts, _percent(b.precision), *errors])
    if result.other_descriptors:
        rows.append(["other", "", "", "", str(result.other_descriptors), str(result.other_true), "", "", "", "", ""])
    counts = [str(result.shown), str(result.found), _percent(result.recall), str(result.descriptors)]
    counts += [str(result.true_descriptors), _percent(result.precision)]
    rows.append(["10-35 m", *counts, *_error_cells(result.range_errors, result.lateral_errors)])
    clear = [["clear terrain", "frames", "with descr.", "descriptors", "per 100 frames"]]
    for name, terrain in sorted(result.clear.items()):
        per_100 = 100 * terrain.descriptors / terrain.frames
        clear.append([name, str(terrain.frames), str(terrain.frames_with_descriptors), str(terrain.descriptors)])
        clear[-1].append(f"{per_100:.1f}")
    with_any = sum(c.frames_with_descriptors for c in result.clear.values())
    per_100 = "-" if not result.clear_frames else f"{result.false_per_100_clear:.1f}"
    clear.append(["all", str(result.clear_frames), str(with_any), str(result.clear_false), per_100])
    return _table(rows) + ("\n\n" + _table(clear) if result.clear_frames else "")


def format_report(result: Evaluation) -> str:
    """The tables, the verdict on each done-means target, the misses and the cost."""
    recall, false, within = result.recall, result.false_per_100_clear, result.within_share
    lines = [
        f"ESVS obstacles on {result.scenes} simulated scenes and {result.clear_frames} clear-terrain frames "
        f"(seed {result.seed})",
        format_table(result),
        "",
        f"recall >= 95 % at 10-35 m: {_verdict(recall, recall >= 0.95)} ({_percent(recall)}); "
        f"< 1 false descriptor per 100 clear frames: {_verdict(false, false < 1.0)} "
        f"({'-' if math.isnan(false) else f'{false:.1f}'}); "
        f"range error <= 5 % of range: {_verdict(within, within >= 0.95)} ({_percent(within)} of found obstacles)",
    ]
    in_view = result.found_in_view / result.shown_in_view if result.shown_in_view else math.nan
    lines.append(
        f"recall of the {result.shown_in_view} shown obstacles at least {HIDDEN:.0%} in view (not hidden behind "
        f"another): {_percent(in_view)}"
    )
    ditch = result.clear.get("ditch", ClearTerrain())
    if ditch.descriptors and result.clear_frames > ditch.frames:
        rest = 100.0 * (result.clear_false - ditch.descriptors) / (result.clear_frames - ditch.frames)
        lines.append(f"false descriptors per 100 clear frames without a ditch: {rest:.1f}")
    if result.unscored_matches:
        lines.append(f"{result.unscored_matches} descriptors matched obstacles showing too little to count")
    if result.misses:
        causes: dict[str, int] = {}
        for m in result.misses:
            causes[m.cause] = causes.get(m.cause, 0) + 1
        lines += ["", "missed: " + ", ".join(f"{n} {cause}" for cause, n in sorted(causes.items()))]
        for m in result.misses:
            lines.append(
                f"  scene {m.scene}: {m.cause}: {m.shape} {m.range_m:.1f} m at {m.bearing_deg:+.1f} deg, "
                f"{m.height_m:.2f} m tall, radius {m.radius_m:.2f} m, {m.visible_px} px ({m.visible_share:.0%} of "
                "what it shows alone)"
            )
    if result.process_s:
        render, vision = np.percentile(result.render_s, [50, 99]), np.percentile(result.process_s, [50, 99])
        lines += [
            "",
            f"render p50 {render[0] * 1e3:.1f} ms (p99 {render[1] * 1e3:.1f}), process() p50 "
            f"{vision[0] * 1e3:.1f} ms (p99 {vision[1] * 1e3:.1f}); {len(result.process_s)} frames in "
            f"{result.wall_s:.1f} s",
        ]
    lines += [
        "",
        "range: from the ground under the cameras to the nearest footprint point. shown: obstacles with >= "
        f"{result.min_visible_px} left pixels that the right image also holds. A descriptor matches when its "
        "centre is within max(0.5 m, 5 % of range) + footprint radius of the footprint centre (greedy, closest "
        "first). err: |range_m - range of the nearest visible point| / range; lat: |y_m - middle of the visible "
        "part's lateral extent| / range. Clear terrain: every descriptor is false.",
    ]
    return "\n".join(lines)


def _verdict(value: float, ok: bool) -> str:
    if math.isnan(value):
        return "not measured"
    return "met" if ok else "NOT met"
