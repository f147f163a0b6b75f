"""Declarative scenarios: a TOML file naming the course, what stands on it, and what will fail.

    [scenario]            name, rddf (path relative to this file), seed, optional origin, fair
    [road]                optional road edges (lane borders) at +-half_width_m of the centreline
    [[obstacle]]          hand-placed obstacles, by arc length and offset or by east/north
    [random_obstacles]    seeded random obstacles inside the corridor
    [[hazard]]            ditches, berms and drop-offs for the vertical lidars
    [[fault]]             the sensor fault schedule (seconds after the start, metres along the course)
    [gps_jumps]           occasional seeded GPS jumps, added to the fault schedule

Placement by ``at_m`` (arc length along the course centreline) and ``offset_m`` (left of it,
metres) keeps a scenario readable and valid when the course is edited. Every key is checked: a
bad file raises ScenarioError naming the file, the table and the key; nothing is half-loaded.

Every scenario must be fair (``modules/sim/fairness.py``): its obstacles and hazards leave a free
lane of the vehicle's width + 1.0 m from start to finish, or loading fails naming the place and
what blocks it. A test that blocks the course on purpose says ``fair = false`` in [scenario].
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from brain.corridor import Course, CoursePath, GeodeticOrigin
from brain.rddf import RddfError
from modules.sim.fairness import Stations, blockers, find_unfairness
from modules.sim.world import (
    FaultKind,
    HazardKind,
    LaneBorderLine,
    SensorFault,
    Shape,
    TerrainHazard,
    Texture,
    World,
    WorldObstacle,
)
from rascal.runtime.config import FINITE, ConfigError, build_config, check_range, given, required, setting

DEFAULT_SCENARIO = Path(__file__).resolve().parents[2] / "deploy" / "scenarios" / "mojave.toml"
FOREVER_S = 1e12
SENSOR_NAMES = frozenset(
    {
        "imu",
        "gps",
        "speedometer",
        "magnetometer_1",
        "magnetometer_2",
        "lidars",
        "lidar_h_left",
        "lidar_h_right",
        "lidar_v_left",
        "lidar_v_right",
        "lidar_sweep",
        "esvs",
    }
)


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message names the file, table and key."""


@dataclass(frozen=True)
class Scenario:
    name: str
    path: Path
    seed: int
    course: Course
    route: CoursePath
    world: World

    @property
    def origin(self) -> GeodeticOrigin:
        return self.course.origin

    @property
    def origin_lat_deg(self) -> float:
        return self.course.origin.lat_deg

    @property
    def origin_lon_deg(self) -> float:
        return self.course.origin.lon_deg

    @property
    def origin_alt_m(self) -> float:
        return self.course.origin.alt_m

    def start_pose(self) -> tuple[float, float, float]:
        """(east_m, north_m, yaw_rad): the first route point, facing along the route."""
        route = self.route
        return float(route.east_m[0]), float(route.north_m[0]), _heading(route, 0)


@dataclass(frozen=True)
class OriginTable:
    lat_deg: float = required("latitude of the ENU origin", within=(-90.0, 90.0))
    lon_deg: float = required("longitude of the ENU origin", within=(-180.0, 180.0))
    alt_m: float = setting(0.0, "altitude of the ENU origin", within=FINITE)


@dataclass(frozen=True, kw_only=True)
class ScenarioTable:
    name: str | None = setting(None, "the scenario's name (default: the file's)")
    rddf: str = required("the course, relative to this file")
    seed: int = setting(0, "seeds the random obstacles and the GPS jumps")
    origin: OriginTable | None = setting(None, "the ENU origin (default: the course's first waypoint)")
    fair: bool = setting(True, "refuse obstacles and hazards that block the free lane (fairness.py)")


@dataclass(frozen=True, kw_only=True)
class RoadTable:
    half_width_m: float = required("road edges this far either side of the centreline", within=(0.5, 50.0))
    from_m: float = setting(0.0, "where the edges begin along the course", within=(0.0, math.inf))
    to_m: float | None = setting(None, "where they end (default: the finish)")


@dataclass(frozen=True, kw_only=True)
class PlacedTable:
    """Where an obstacle or hazard stands: at_m/offset_m along the course, or east_m/north_m."""

    name: str | None = setting(None, "its name (default: the table's, e.g. obstacle[3])")
    at_m: float | None = setting(None, "arc length along the course centreline", within=(0.0, math.inf))
    offset_m: float = setting(0.0, "left of the centreline", within=FINITE)
    east_m: float | None = setting(None, "or: east of the origin", within=FINITE)
    north_m: float | None = setting(None, "and north of it", within=FINITE)
    yaw_rad: float = setting(0.0, "turned from the course's heading there", within=FINITE)


@dataclass(frozen=True, kw_only=True)
class ObstacleTable(PlacedTable):
    shape: Shape = required("box or cylinder")
    height_m: float = required("its height", within=(0.05, 50.0))
    radius_m: float | None = setting(None, "a cylinder's radius", within=(0.02, 20.0))
    length_m: float | None = setting(None, "a box's length, along its yaw", within=(0.05, 50.0))
    width_m: float | None = setting(None, "a box's width", within=(0.05, 50.0))
    texture: Texture = setting(Texture.ROCK, "its look, for the camera renderer")


@dataclass(frozen=True, kw_only=True)
class HazardTable(PlacedTable):
    kind: HazardKind = required("ditch, berm or drop_off")
    length_m: float = required("along its yaw", within=(0.1, 100.0))
    width_m: float = required("across it", within=(0.1, 200.0))
    depth_m: float | None = setting(None, "a ditch's or drop-off's depth", within=(0.01, 20.0))
    height_m: float | None = setting(None, "a berm's height", within=(0.01, 20.0))


@dataclass(frozen=True, kw_only=True)
class RandomObstaclesTable:
    count: int = required("how many")
    from_m: float = setting(0.0, "where they may begin along the course", within=(0.0, math.inf))
    to_m: float | None = setting(None, "where they end (default: the finish)")
    min_gap_m: float = setting(20.0, "along the course between any two obstacles", within=(0.0, math.inf))
    size_m: tuple[float, ...] = setting((0.4, 1.5), "[low, high] of their size")
    height_m: tuple[float, ...] = setting((0.4, 1.5), "[low, high] of their height")
    free_width_m: float = setting(3.0, "a lane this wide kept free on one side", within=(0.0, math.inf))
    textures: tuple[str, ...] = setting(("rock", "vegetation"), "drawn from these (other names are skipped)")


@dataclass(frozen=True, kw_only=True)
class FaultTable:
    sensors: tuple[str, ...] = required(f"some of {sorted(SENSOR_NAMES)}")
    kind: FaultKind = required("what goes wrong")
    start_s: float = required("seconds after the start", within=(0.0, math.inf))
    end_s: float | None = setting(None, "when it ends (default: never)")
    magnitude: float = setting(1.0, "its size (noise: a multiplier)", within=FINITE)
    from_m: float = setting(0.0, "active only from this far along the course", within=(0.0, math.inf))
    to_m: float | None = setting(None, "and up to this far (default: no end)")


@dataclass(frozen=True, kw_only=True)
class GpsJumpsTable:
    per_hour: float = required("mean jumps an hour", within=(0.0, 3600.0))
    magnitude_m: tuple[float, ...] = setting((5.0, 20.0), "[low, high] of a jump's size")
    duration_s: tuple[float, ...] = setting((1.0, 5.0), "[low, high] of how long one lasts")
    horizon_s: float = setting(3600.0, "no jumps after this", within=(1.0, 86400.0))


@dataclass(frozen=True, kw_only=True)
class ScenarioFile:
    """A scenario file's tables, checked by rascal.runtime.config as module settings are."""

    scenario: ScenarioTable = required("the course and the seed")
    road: RoadTable | None = setting(None, "road edges (lane borders)")
    obstacle: tuple[ObstacleTable, ...] = setting((), "hand-placed obstacles ([[obstacle]])")
    random_obstacles: RandomObstaclesTable | None = setting(None, "seeded random obstacles")
    hazard: tuple[HazardTable, ...] = setting((), "ditches, berms and drop-offs ([[hazard]])")
    fault: tuple[FaultTable, ...] = setting((), "the sensor fault schedule ([[fault]])")
    gps_jumps: GpsJumpsTable | None = setting(None, "seeded GPS jumps, added to the fault schedule")


def load_scenario(path: str | Path = DEFAULT_SCENARIO) -> Scenario:
    """Read and check a scenario file; every error names the file, table and key."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ScenarioError(f"{path}: scenario file not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{path}: not valid TOML: {exc}") from exc
    try:
        return _scenario(path, build_config(ScenarioFile, doc, ""))
    except ConfigError as exc:
        raise ScenarioError(f"{path}: {exc}") from None


def _scenario(path: Path, file: ScenarioFile) -> Scenario:
    head = file.scenario
    course = _course(path, head)
    route = course.interpolate()
    obstacles = [_obstacle(route, table, f"obstacle[{i}]") for i, table in enumerate(file.obstacle)]
    if file.random_obstacles is not None:
        obstacles += _random_obstacles(route, file.random_obstacles, head.seed, obstacles)
    for obstacle in obstacles:
        if not course.corridor.contains(obstacle.east_m, obstacle.north_m):
            raise ScenarioError(f"{path}: obstacle {obstacle.name!r} stands outside the corridor")
    world = World(
        obstacles=tuple(obstacles),
        hazards=tuple(_hazard(route, table, f"hazard[{i}]") for i, table in enumerate(file.hazard)),
        lane_borders=() if file.road is None else _road(route, file.road),
        faults=(
            *(_fault(route, table, f"fault[{i}]") for i, table in enumerate(file.fault)),
            *(() if file.gps_jumps is None else _gps_jumps(file.gps_jumps, head.seed)),
        ),
    )
    if head.fair:
        unfair = find_unfairness(Stations.along(course), blockers(world))
        if unfair:
            raise ScenarioError(f"{path}: unfair: {unfair}")
    return Scenario(path.stem if head.name is None else head.name, path, head.seed, course, route, world)


def obstacle_from_table(route: CoursePath, table: dict[str, Any]) -> WorldObstacle:
    """An [[obstacle]] table placed as the loader places it, for tools that write scenarios."""
    return _obstacle(route, build_config(ObstacleTable, table, "obstacle"), "obstacle")


def hazard_from_table(route: CoursePath, table: dict[str, Any]) -> TerrainHazard:
    """A [[hazard]] table placed as the loader places it, for tools that write scenarios."""
    return _hazard(route, build_config(HazardTable, table, "hazard"), "hazard")


def _pair(value: tuple[float, ...], where: str) -> tuple[float, float]:
    """A [low, high] range of positive numbers (sizes, durations)."""
    if len(value) != 2 or not 0 < value[0] <= value[1]:
        raise ConfigError(f"{where}: expected [low, high] with 0 < low <= high, got {list(value)!r}")
    return value[0], value[1]


def _course(path: Path, head: ScenarioTable) -> Course:
    rddf = path.parent / head.rddf
    origin = (
        None if head.origin is None else GeodeticOrigin(head.origin.lat_deg, head.origin.lon_deg, head.origin.alt_m)
    )
    try:
        return Course.from_file(rddf, origin)
    except (RddfError, OSError) as exc:
        raise ConfigError(f"scenario.rddf: {exc}") from exc
    except ValueError as exc:
        raise ConfigError(f"scenario.rddf: {rddf}: {exc}") from exc


def _heading(route: CoursePath, index: int) -> float:
    i = min(index, len(route.s_m) - 2)
    return math.atan2(route.north_m[i + 1] - route.north_m[i], route.east_m[i + 1] - route.east_m[i])


def _place(route: CoursePath, table: PlacedTable, where: str) -> tuple[float, float, float]:
    """(east_m, north_m, course heading there) from at_m/offset_m, or east_m/north_m."""
    if table.at_m is not None:
        if table.east_m is not None or table.north_m is not None:
            raise ConfigError(f"{where}: give either at_m/offset_m or east_m/north_m, not both")
        check_range(table.at_m, 0.0, route.length_m, f"{where}.at_m")
        index = int(np.searchsorted(route.s_m, table.at_m).clip(0, len(route.s_m) - 1))
        yaw = _heading(route, index)
        east = float(route.east_m[index]) - table.offset_m * math.sin(yaw)
        north = float(route.north_m[index]) + table.offset_m * math.cos(yaw)
        return east, north, yaw
    east = given(table.east_m, f"{where}.east_m")
    north = given(table.north_m, f"{where}.north_m")
    nearest = int(np.argmin(np.hypot(route.east_m - east, route.north_m - north)))
    return east, north, _heading(route, nearest)


def _obstacle(route: CoursePath, table: ObstacleTable, where: str) -> WorldObstacle:
    east, north, course_yaw = _place(route, table, where)
    name = where if table.name is None else table.name
    if table.shape is Shape.CYLINDER:
        radius = given(table.radius_m, f"{where}.radius_m")
        return WorldObstacle(name, table.shape, east, north, table.height_m, radius_m=radius, texture=table.texture)
    return WorldObstacle(
        name,
        table.shape,
        east,
        north,
        table.height_m,
        length_m=given(table.length_m, f"{where}.length_m"),
        width_m=given(table.width_m, f"{where}.width_m"),
        # A box's yaw is relative to the course where it stands, as a person placing it would think.
        yaw_rad=course_yaw + table.yaw_rad,
        texture=table.texture,
    )


def _random_obstacles(
    route: CoursePath, table: RandomObstaclesTable, seed: int, placed: list[WorldObstacle]
) -> list[WorldObstacle]:
    where = "random_obstacles"
    count = table.count
    check_range(table.from_m, 0.0, route.length_m, f"{where}.from_m")
    start = table.from_m
    end = route.length_m if table.to_m is None else table.to_m
    check_range(end, start, route.length_m, f"{where}.to_m")
    min_gap = table.min_gap_m
    size = _pair(table.size_m, f"{where}.size_m")
    height = _pair(table.height_m, f"{where}.height_m")
    free = table.free_width_m
    textures = [Texture(t) for t in table.textures if t in Texture._value2member_map_]
    if not textures:
        raise ConfigError(f"{where}.textures: expected some of {[t.value for t in Texture]}")
    rng = np.random.default_rng(seed)
    taken = [float(route.s_m[np.argmin(np.hypot(route.east_m - o.east_m, route.north_m - o.north_m))]) for o in placed]
    obstacles: list[WorldObstacle] = []
    for _attempt in range(count * 50):
        if len(obstacles) == count:
            break
        at = float(rng.uniform(start, end))
        if any(abs(at - other) < min_gap for other in taken):
            continue
        index = int(np.searchsorted(route.s_m, at).clip(0, len(route.s_m) - 1))
        half_width = float(route.half_width_m[index])
        extent = float(rng.uniform(*size))
        # Keep a free lane of free_width_m on one side so the course stays drivable.
        room = half_width - extent / 2 - free
        if room < 0.5:
            continue
        offset = float(rng.uniform(-room, room))
        yaw = _heading(route, index)
        east = float(route.east_m[index]) - offset * math.sin(yaw)
        north = float(route.north_m[index]) + offset * math.cos(yaw)
        name = f"random_{len(obstacles)}"
        texture = textures[int(rng.integers(len(textures)))]
        tall = float(rng.uniform(*height))
        if rng.random() < 0.5:
            obstacle = WorldObstacle(name, Shape.CYLINDER, east, north, tall, radius_m=extent / 2, texture=texture)
        else:
            obstacle = WorldObstacle(
                name,
                Shape.BOX,
                east,
                north,
                tall,
                length_m=extent,
                width_m=float(rng.uniform(size[0], extent)),
                yaw_rad=yaw + float(rng.uniform(-0.5, 0.5)),
                texture=texture,
            )
        obstacles.append(obstacle)
        taken.append(at)
    if len(obstacles) < count:
        raise ConfigError(f"{where}.count: only {len(obstacles)} of {count} fit between {start} and {end} m")
    return obstacles


def _hazard(route: CoursePath, table: HazardTable, where: str) -> TerrainHazard:
    east, north, course_yaw = _place(route, table, where)
    size_key = "height_m" if table.kind is HazardKind.BERM else "depth_m"
    return TerrainHazard(
        name=where if table.name is None else table.name,
        kind=table.kind,
        east_m=east,
        north_m=north,
        yaw_rad=course_yaw + table.yaw_rad,
        length_m=table.length_m,
        width_m=table.width_m,
        magnitude_m=given(getattr(table, size_key), f"{where}.{size_key}"),
    )


def _road(route: CoursePath, table: RoadTable) -> tuple[LaneBorderLine, ...]:
    half = table.half_width_m
    check_range(table.from_m, 0.0, route.length_m, "road.from_m")
    start = table.from_m
    end = route.length_m if table.to_m is None else table.to_m
    check_range(end, start, route.length_m, "road.to_m")
    keep = (route.s_m >= start) & (route.s_m <= end)
    heading = np.arctan2(np.gradient(route.north_m), np.gradient(route.east_m))[keep]
    east, north = route.east_m[keep], route.north_m[keep]
    lines = []
    for name, side in (("road_left", 1.0), ("road_right", -1.0)):
        xs = east - side * half * np.sin(heading)
        ys = north + side * half * np.cos(heading)
        lines.append(LaneBorderLine(name, tuple(zip(xs.tolist(), ys.tolist(), strict=True))))
    return tuple(lines)


def _fault(route: CoursePath, table: FaultTable, where: str) -> SensorFault:
    """A fault active from ``start_s`` (required) to ``end_s`` seconds, and, optionally, only
    while the vehicle's course progress is in ``from_m``..``to_m`` (e.g. ``start_s = 0`` and
    ``from_m`` at 60 % of the course: silent from there on, however long the start took)."""
    if not table.sensors:
        raise ConfigError(f"{where}.sensors: expected a non-empty list of sensor names")
    unknown = sorted(set(table.sensors) - SENSOR_NAMES)
    if unknown:
        raise ConfigError(f"{where}.sensors: unknown sensor(s) {unknown}; known: {sorted(SENSOR_NAMES)}")
    check_range(table.from_m, 0.0, route.length_m, f"{where}.from_m")
    end = FOREVER_S if table.end_s is None else table.end_s
    check_range(end, table.start_s, math.inf, f"{where}.end_s")
    to_m = math.inf
    if table.to_m is not None:
        check_range(table.to_m, table.from_m, math.inf, f"{where}.to_m")
        to_m = table.to_m
    return SensorFault(table.sensors, table.kind, table.start_s, end, table.magnitude, table.from_m, to_m)


def _gps_jumps(table: GpsJumpsTable, seed: int) -> list[SensorFault]:
    """Seeded GPS jumps at random times (a Poisson process): multipath and bad corrections make
    real DGPS fixes leap now and then, and the navigation filter must reject them."""
    per_hour, horizon = table.per_hour, table.horizon_s
    magnitude = _pair(table.magnitude_m, "gps_jumps.magnitude_m")
    duration = _pair(table.duration_s, "gps_jumps.duration_s")
    rng = np.random.default_rng([seed, 1])  # its own stream: obstacles stay put when jumps change
    jumps, t = [], 0.0
    while per_hour > 0:
        t += float(rng.exponential(3600.0 / per_hour))
        if t >= horizon:
            break
        length = float(rng.uniform(*duration))
        jumps.append(SensorFault(("gps",), FaultKind.JUMP, t, t + length, float(rng.uniform(*magnitude))))
        t += length
    return jumps
