"""The simulated world a scenario describes, in the course's local ENU frame (metres).

Plain frozen dataclasses shared by the simulator (collisions), the simulated lidars and cameras (what
they see) and the scenario loader (what a TOML file declares). Geometry helpers that several
consumers need live here too, so there is one definition of where an obstacle is.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field


class Shape(enum.Enum):
    BOX = "box"
    CYLINDER = "cylinder"


class Texture(enum.Enum):
    """Surface look, for the camera renderer; lidars ignore it."""

    ROCK = "rock"
    WOOD = "wood"
    METAL = "metal"
    VEGETATION = "vegetation"
    CONCRETE = "concrete"


@dataclass(frozen=True)
class WorldObstacle:
    """An upright obstacle. A cylinder uses ``radius_m``; a box ``length_m`` x ``width_m``
    rotated by ``yaw_rad`` (counter-clockwise from east)."""

    name: str
    shape: Shape
    east_m: float
    north_m: float
    height_m: float
    radius_m: float = 0.0
    length_m: float = 0.0
    width_m: float = 0.0
    yaw_rad: float = 0.0
    texture: Texture = Texture.ROCK

    def footprint_radius_m(self) -> float:
        """Radius of a circle around the centre that contains the whole footprint."""
        if self.shape is Shape.CYLINDER:
            return self.radius_m
        return math.hypot(self.length_m, self.width_m) / 2


class HazardKind(enum.Enum):
    DITCH = "ditch"  # ground drops by depth_m, then comes back up
    BERM = "berm"  # ground rises by height_m, then comes back down
    DROP_OFF = "drop_off"  # ground drops by depth_m and stays down


@dataclass(frozen=True)
class TerrainHazard:
    """A strip of changed ground height: centred at (east_m, north_m), ``length_m`` along
    ``yaw_rad`` (the direction a vehicle crosses it) and ``width_m`` across."""

    name: str
    kind: HazardKind
    east_m: float
    north_m: float
    yaw_rad: float
    length_m: float
    width_m: float
    magnitude_m: float  # depth for ditches and drop-offs, height for berms


@dataclass(frozen=True)
class LaneBorderLine:
    """A road edge or lane border as a polyline of ENU points."""

    name: str
    points_m: tuple[tuple[float, float], ...]


class FaultKind(enum.Enum):
    SILENCE = "silence"  # the sensor publishes nothing
    NOISE = "noise"  # noise multiplied by ``magnitude``
    STUCK = "stuck"  # the last measurement repeats
    OUTAGE = "outage"  # GPS: no fix
    JUMP = "jump"  # GPS: position offset by ``magnitude`` metres


@dataclass(frozen=True)
class SensorFault:
    """A fault of ``sensors`` (names such as "gps", "lidar_h_left", or "lidars" for all four)
    active from ``start_s`` to ``end_s`` seconds after the scenario starts, while the vehicle's
    course progress is between ``from_m`` and ``to_m``. The progress window places a fault on
    the course (RASCAL's lidars fell silent part-way along it) however long the stack took to
    start; both windows are judged on the truth sample, so every sensor process agrees."""

    sensors: tuple[str, ...]
    kind: FaultKind
    start_s: float
    end_s: float
    magnitude: float = 1.0
    from_m: float = 0.0
    to_m: float = math.inf

    def active(self, t_s: float, progress_m: float) -> bool:
        return self.start_s <= t_s < self.end_s and self.from_m <= progress_m < self.to_m


@dataclass(frozen=True)
class World:
    obstacles: tuple[WorldObstacle, ...] = ()
    hazards: tuple[TerrainHazard, ...] = ()
    lane_borders: tuple[LaneBorderLine, ...] = ()
    faults: tuple[SensorFault, ...] = field(default_factory=tuple)

    def faults_for(self, sensor: str, t_s: float, progress_m: float) -> list[SensorFault]:
        """Faults of ``sensor`` active at scenario time ``t_s`` and course progress
        ``progress_m`` (``lidars`` names all four lidars)."""
        aliases = {sensor, "lidars"} if sensor.startswith("lidar") else {sensor}
        return [f for f in self.faults if f.active(t_s, progress_m) and aliases.intersection(f.sensors)]
