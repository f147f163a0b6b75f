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
from rascal.runtime.toml_reader import TomlReader

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


def load_scenario(path: str | Path = DEFAULT_SCENARIO) -> Scenario:
    """Read and check a scenario file; every error names the file, table and key."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ScenarioError(f"{path}: scenario file not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{path}: not valid TOML: {exc}") from exc
    reader = _Reader(path)
    reader.keys(doc, "", {"scenario", "road", "obstacle", "random_obstacles", "hazard", "fault", "gps_jumps"})
    head = reader.table(doc, "scenario", required=True)
    reader.keys(head, "scenario", {"name", "rddf", "seed", "origin", "fair"})
    course = _course(reader, head)
    route = course.interpolate()
    seed = reader.integer(head, "scenario", "seed", default=0)
    obstacles = [_obstacle(reader, route, t, f"obstacle[{i}]") for i, t in enumerate(reader.array(doc, "obstacle"))]
    random_table = reader.table(doc, "random_obstacles")
    if random_table:
        obstacles += _random_obstacles(reader, route, random_table, seed, obstacles)
    for obstacle in obstacles:
        if not course.corridor.contains(obstacle.east_m, obstacle.north_m):
            raise ScenarioError(f"{path}: obstacle {obstacle.name!r} stands outside the corridor")
    world = World(
        obstacles=tuple(obstacles),
        hazards=tuple(_hazard(reader, route, t, f"hazard[{i}]") for i, t in enumerate(reader.array(doc, "hazard"))),
        lane_borders=_road(reader, route, reader.table(doc, "road")),
        faults=(
            *(_fault(reader, route, t, f"fault[{i}]") for i, t in enumerate(reader.array(doc, "fault"))),
            *_gps_jumps(reader, reader.table(doc, "gps_jumps"), seed),
        ),
    )
    if reader.boolean(head, "scenario", "fair", default=True):
        unfair = find_unfairness(Stations.along(course), blockers(world))
        if unfair:
            raise ScenarioError(f"{path}: unfair: {unfair}")
    name = reader.string(head, "scenario", "name", default=path.stem)
    return Scenario(name, path, seed, course, route, world)


def obstacle_from_table(route: CoursePath, table: dict[str, Any]) -> WorldObstacle:
    """An [[obstacle]] table placed as the loader places it, for tools that write scenarios."""
    return _obstacle(_Reader(Path("<generated>")), route, table, "obstacle")


def hazard_from_table(route: CoursePath, table: dict[str, Any]) -> TerrainHazard:
    """A [[hazard]] table placed as the loader places it, for tools that write scenarios."""
    return _hazard(_Reader(Path("<generated>")), route, table, "hazard")


class _Reader(TomlReader):
    """The shared readers (rascal/runtime/toml_reader.py) and a scenario's own: enum choices and
    [low, high] ranges."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, ScenarioError)

    def choice(self, table: dict[str, Any], where: str, key: str, enum: Any, default: str | None = None) -> Any:
        text = self.string(table, where, key, default)
        try:
            return enum(text)
        except ValueError:
            raise self.fail(f"{where}.{key}", f"{text!r} is not one of {[e.value for e in enum]}") from None

    def range_pair(self, table: dict[str, Any], where: str, key: str, default: list[float]) -> tuple[float, float]:
        value = table.get(key, default)
        if (
            not isinstance(value, list)
            or len(value) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
            or not 0 < value[0] <= value[1]
        ):
            raise self.fail(f"{where}.{key}", f"expected [low, high] with 0 < low <= high, got {value!r}")
        return float(value[0]), float(value[1])


def _course(reader: _Reader, head: dict[str, Any]) -> Course:
    rddf = reader.path.parent / reader.string(head, "scenario", "rddf")
    origin = None
    if "origin" in head:
        table = reader.table(head, "origin")
        reader.keys(table, "scenario.origin", {"lat_deg", "lon_deg", "alt_m"})
        origin = GeodeticOrigin(
            reader.number(table, "scenario.origin", "lat_deg", low=-90, high=90),
            reader.number(table, "scenario.origin", "lon_deg", low=-180, high=180),
            reader.number(table, "scenario.origin", "alt_m", default=0.0),
        )
    try:
        return Course.from_file(rddf, origin)
    except (RddfError, OSError) as exc:
        raise reader.fail("scenario.rddf", str(exc)) from exc
    except ValueError as exc:
        raise reader.fail("scenario.rddf", f"{rddf}: {exc}") from exc


def _heading(route: CoursePath, index: int) -> float:
    i = min(index, len(route.s_m) - 2)
    return math.atan2(route.north_m[i + 1] - route.north_m[i], route.east_m[i + 1] - route.east_m[i])


def _place(reader: _Reader, route: CoursePath, table: dict[str, Any], where: str) -> tuple[float, float, float]:
    """(east_m, north_m, course heading there) from at_m/offset_m, or east_m/north_m."""
    if "at_m" in table:
        if "east_m" in table or "north_m" in table:
            raise reader.fail(where, "give either at_m/offset_m or east_m/north_m, not both")
        at = reader.number(table, where, "at_m", low=0.0, high=route.length_m)
        offset = reader.number(table, where, "offset_m", default=0.0)
        index = int(np.searchsorted(route.s_m, at).clip(0, len(route.s_m) - 1))
        yaw = _heading(route, index)
        east = float(route.east_m[index]) - offset * math.sin(yaw)
        north = float(route.north_m[index]) + offset * math.cos(yaw)
        return east, north, yaw
    east = reader.number(table, where, "east_m")
    north = reader.number(table, where, "north_m")
    nearest = int(np.argmin(np.hypot(route.east_m - east, route.north_m - north)))
    return east, north, _heading(route, nearest)


def _obstacle(reader: _Reader, route: CoursePath, table: dict[str, Any], where: str) -> WorldObstacle:
    reader.keys(
        table,
        where,
        {
            "name",
            "shape",
            "at_m",
            "offset_m",
            "east_m",
            "north_m",
            "radius_m",
            "length_m",
            "width_m",
            "yaw_rad",
            "height_m",
            "texture",
        },
    )
    east, north, course_yaw = _place(reader, route, table, where)
    shape = reader.choice(table, where, "shape", Shape)
    common = {
        "name": reader.string(table, where, "name", default=where),
        "shape": shape,
        "east_m": east,
        "north_m": north,
        "height_m": reader.number(table, where, "height_m", low=0.05, high=50.0),
        "texture": reader.choice(table, where, "texture", Texture, default="rock"),
    }
    if shape is Shape.CYLINDER:
        return WorldObstacle(**common, radius_m=reader.number(table, where, "radius_m", low=0.02, high=20.0))
    return WorldObstacle(
        **common,
        length_m=reader.number(table, where, "length_m", low=0.05, high=50.0),
        width_m=reader.number(table, where, "width_m", low=0.05, high=50.0),
        # A box's yaw is relative to the course where it stands, as a person placing it would think.
        yaw_rad=course_yaw + reader.number(table, where, "yaw_rad", default=0.0),
    )


def _random_obstacles(
    reader: _Reader, route: CoursePath, table: dict[str, Any], seed: int, placed: list[WorldObstacle]
) -> list[WorldObstacle]:
    where = "random_obstacles"
    reader.keys(
        table, where, {"count", "from_m", "to_m", "min_gap_m", "size_m", "height_m", "free_width_m", "textures"}
    )
    count = reader.integer(table, where, "count")
    start = reader.number(table, where, "from_m", default=0.0, low=0.0, high=route.length_m)
    end = reader.number(table, where, "to_m", default=route.length_m, low=start, high=route.length_m)
    min_gap = reader.number(table, where, "min_gap_m", default=20.0, low=0.0)
    size = reader.range_pair(table, where, "size_m", [0.4, 1.5])
    height = reader.range_pair(table, where, "height_m", [0.4, 1.5])
    free = reader.number(table, where, "free_width_m", default=3.0, low=0.0)
    textures = [Texture(t) for t in table.get("textures", ["rock", "vegetation"]) if t in Texture._value2member_map_]
    if not textures:
        raise reader.fail(f"{where}.textures", f"expected some of {[t.value for t in Texture]}")
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
        raise reader.fail(f"{where}.count", f"only {len(obstacles)} of {count} fit between {start} and {end} m")
    return obstacles


def _hazard(reader: _Reader, route: CoursePath, table: dict[str, Any], where: str) -> TerrainHazard:
    reader.keys(
        table,
        where,
        {
            "name",
            "kind",
            "at_m",
            "offset_m",
            "east_m",
            "north_m",
            "length_m",
            "width_m",
            "depth_m",
            "height_m",
            "yaw_rad",
        },
    )
    kind = reader.choice(table, where, "kind", HazardKind)
    east, north, course_yaw = _place(reader, route, table, where)
    size_key = "height_m" if kind is HazardKind.BERM else "depth_m"
    return TerrainHazard(
        name=reader.string(table, where, "name", default=where),
        kind=kind,
        east_m=east,
        north_m=north,
        yaw_rad=course_yaw + reader.number(table, where, "yaw_rad", default=0.0),
        length_m=reader.number(table, where, "length_m", low=0.1, high=100.0),
        width_m=reader.number(table, where, "width_m", low=0.1, high=200.0),
        magnitude_m=reader.number(table, where, size_key, low=0.01, high=20.0),
    )


def _road(reader: _Reader, route: CoursePath, table: dict[str, Any]) -> tuple[LaneBorderLine, ...]:
    if not table:
        return ()
    reader.keys(table, "road", {"half_width_m", "from_m", "to_m"})
    half = reader.number(table, "road", "half_width_m", low=0.5, high=50.0)
    start = reader.number(table, "road", "from_m", default=0.0, low=0.0, high=route.length_m)
    end = reader.number(table, "road", "to_m", default=route.length_m, low=start, high=route.length_m)
    keep = (route.s_m >= start) & (route.s_m <= end)
    heading = np.arctan2(np.gradient(route.north_m), np.gradient(route.east_m))[keep]
    east, north = route.east_m[keep], route.north_m[keep]
    lines = []
    for name, side in (("road_left", 1.0), ("road_right", -1.0)):
        xs = east - side * half * np.sin(heading)
        ys = north + side * half * np.cos(heading)
        lines.append(LaneBorderLine(name, tuple(zip(xs.tolist(), ys.tolist(), strict=True))))
    return tuple(lines)


def _fault(reader: _Reader, route: CoursePath, table: dict[str, Any], where: str) -> SensorFault:
    """A fault active from ``start_s`` (required) to ``end_s`` seconds, and, optionally, only
    while the vehicle's course progress is in ``from_m``..``to_m`` (e.g. ``start_s = 0`` and
    ``from_m`` at 60 % of the course: silent from there on, however long the start took)."""
    reader.keys(table, where, {"sensors", "kind", "start_s", "end_s", "magnitude", "from_m", "to_m"})
    sensors = table.get("sensors")
    if not isinstance(sensors, list) or not sensors or not all(isinstance(s, str) for s in sensors):
        raise reader.fail(f"{where}.sensors", "expected a non-empty list of sensor names")
    unknown = sorted(set(sensors) - SENSOR_NAMES)
    if unknown:
        raise reader.fail(f"{where}.sensors", f"unknown sensor(s) {unknown}; known: {sorted(SENSOR_NAMES)}")
    start = reader.number(table, where, "start_s", low=0.0)
    from_m = reader.number(table, where, "from_m", default=0.0, low=0.0, high=route.length_m)
    return SensorFault(
        sensors=tuple(sensors),
        kind=reader.choice(table, where, "kind", FaultKind),
        start_s=start,
        end_s=reader.number(table, where, "end_s", default=FOREVER_S, low=start),
        magnitude=reader.number(table, where, "magnitude", default=1.0),
        from_m=from_m,
        to_m=reader.number(table, where, "to_m", low=from_m) if "to_m" in table else math.inf,
    )


def _gps_jumps(reader: _Reader, table: dict[str, Any], seed: int) -> list[SensorFault]:
    """Seeded GPS jumps at random times (a Poisson process): multipath and bad corrections make
    real DGPS fixes leap now and then, and the navigation filter must reject them."""
    if not table:
        return []
    where = "gps_jumps"
    reader.keys(table, where, {"per_hour", "magnitude_m", "duration_s", "horizon_s"})
    per_hour = reader.number(table, where, "per_hour", low=0.0, high=3600.0)
    magnitude = reader.range_pair(table, where, "magnitude_m", [5.0, 20.0])
    duration = reader.range_pair(table, where, "duration_s", [1.0, 5.0])
    horizon = reader.number(table, where, "horizon_s", default=3600.0, low=1.0, high=86400.0)
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
