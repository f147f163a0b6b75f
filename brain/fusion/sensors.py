"""Per-sensor models: how much one detection is worth, how far off it may be, and what the sensor
can see (so that silence inside its view counts as evidence of clear ground).

Sensors are grouped into classes that see different things: the horizontal lidars cut a plane
0.7 m above the ground (obstacles taller than that), the stereo system sees obstacles of any
height 10-35 m ahead, the vertical lidars see the ground surface along two lines. Each class keeps
its own evidence layer: a class's clear view erases only its own detections (a horizontal lidar
passing over a low rock must not erase what stereo saw), and agreement between classes is what
lets a hazard be confirmed quickly (RASCAL's stochastic categorisation).

The mounts repeat the simulated sensors' (modules/lidar/README.md, modules/esvs/geometry.py):
on a vehicle they are calibration constants, given here in the vehicle frame (x forward, y left,
from the rear axle centre).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from protocol.messages import Sensor


class SensorClass(enum.IntEnum):
    """Independent kinds of evidence; each has one layer in the map."""

    LIDAR_H = 0  # horizontal lidars: obstacles cutting their scan plane
    STEREO = 1  # ESVS: obstacles above the ground
    LIDAR_V = 2  # vertical lidars: ground surface (ditches, berms, drop-offs)
    LIDAR_SWEEP = 3  # the sweeping lidar: the ground line across the road ahead


@dataclass(frozen=True)
class SensorModel:
    """One sensor: its class, mount, view and the log-odds weight of what it reports.

    ``hit_log_odds`` is added (times the descriptor's confidence) to every cell a detection
    covers; ``miss_log_odds`` (negative) to every cell it saw clear. Reported positions are
    uncertain by ``noise_m + noise_per_m2 * range**2`` (stereo depth error grows with the square
    of the range); footprints are grown by that much and clear views stop that much short of
    what they saw. The view is the sector ``fov_rad`` wide around ``yaw_rad`` from
    ``min_range_m`` to ``max_range_m``; detections up to ``detect_range_m`` are used, those
    beyond ``max_range_m`` with weight falling as max_range/range."""

    sensor_class: SensorClass
    x_m: float
    y_m: float
    yaw_rad: float = 0.0
    fov_rad: float = math.pi
    min_range_m: float = 0.0
    max_range_m: float = 40.0
    detect_range_m: float = 80.0
    hit_log_odds: float = 0.9
    miss_log_odds: float = -0.4
    noise_m: float = 0.05
    noise_per_m2: float = 0.0
    line_half_width_m: float = 0.3  # vertical lidars: half width of the ground strip one line covers

    def __post_init__(self) -> None:
        if not 0 < self.fov_rad <= 2 * math.pi:
            raise ValueError(f"sensor field of view must be in (0, 2 pi], got {self.fov_rad}")
        if not 0 <= self.min_range_m < self.max_range_m <= self.detect_range_m:
            raise ValueError("sensor ranges must satisfy 0 <= min_range_m < max_range_m <= detect_range_m")
        if self.hit_log_odds <= 0 or self.miss_log_odds > 0:
            raise ValueError("a hit must add positive log-odds and a miss non-positive")
        if self.noise_m < 0 or self.noise_per_m2 < 0 or self.line_half_width_m <= 0:
            raise ValueError("sensor noise must be non-negative and a line's half width positive")

    def noise_at(self, range_m: Any) -> Any:
        """Position uncertainty at a range (a number or an array of them)."""
        return self.noise_m + self.noise_per_m2 * range_m * range_m


_H_LIDAR: dict[str, Any] = {
    "sensor_class": SensorClass.LIDAR_H,
    "fov_rad": math.pi,
    "max_range_m": 40.0,  # beyond, returns are sparse enough for small objects to slip between rays
    "detect_range_m": 80.0,
    "hit_log_odds": 0.9,
    "miss_log_odds": -0.4,
    "noise_m": 0.05,
    "noise_per_m2": 1e-4,  # 0.21 m at 40 m: a small box seen on one face (lidar README, Accuracy)
}
_V_LIDAR: dict[str, Any] = {
    "sensor_class": SensorClass.LIDAR_V,
    "fov_rad": math.radians(1.0),  # a line: the profile itself says what it covered
    "max_range_m": 24.0,  # the shallowest beam meets flat ground 24 m ahead of the rear axle
    "detect_range_m": 30.0,
    "hit_log_odds": 0.9,
    "miss_log_odds": -0.4,
    "noise_m": 0.2,  # edge placement, 0.2 m within 10 m and up to 0.8 m at 15-20 m
    "noise_per_m2": 1.5e-3,
}

_SWEEP_LIDAR: dict[str, Any] = {
    "sensor_class": SensorClass.LIDAR_SWEEP,
    "fov_rad": math.radians(60.0),  # the message says what the line covered
    "max_range_m": 45.0,  # the line lies 37 m ahead of the rear axle, up to 43 m at its ends
    "detect_range_m": 60.0,
    # One sweep makes a hazard (the threshold is 1.39): the line lies on a ditch for 1.5 m of
    # travel, as few as one sweep when the machine is busy, and a lidar's 4 cm dip is no noise.
    # It stays one for 170 m driven or 4 min standing (fusion's sweep fades): the vehicle has to
    # reach the ditch 37 m on, and may stop there to look for a way round.
    "hit_log_odds": 2.5,
    "miss_log_odds": -0.4,
    "noise_m": 0.05,  # range noise and pose; the lidar already grows hazards by half a beam spacing
    "line_half_width_m": 0.3,  # half the ground the line moves over between sweeps at 25 m/s
}

DEFAULT_SENSOR_MODELS: Mapping[int, SensorModel] = {
    Sensor.LIDAR_H_LEFT: SensorModel(x_m=1.8, y_m=0.4, yaw_rad=math.radians(15.0), **_H_LIDAR),
    Sensor.LIDAR_H_RIGHT: SensorModel(x_m=1.8, y_m=-0.4, yaw_rad=math.radians(-15.0), **_H_LIDAR),
    Sensor.LIDAR_V_LEFT: SensorModel(x_m=1.5, y_m=0.5, **_V_LIDAR),
    Sensor.LIDAR_V_RIGHT: SensorModel(x_m=1.5, y_m=-0.5, **_V_LIDAR),
    Sensor.LIDAR_SWEEP: SensorModel(x_m=1.8, y_m=0.0, **_SWEEP_LIDAR),
    Sensor.ESVS: SensorModel(
        sensor_class=SensorClass.STEREO,
        x_m=1.6,
        y_m=0.0,
        fov_rad=math.radians(41.26),
        min_range_m=10.0,  # the cameras are pitched to see the ground from 10 to 35 m
        max_range_m=35.0,
        detect_range_m=50.0,
        hit_log_odds=0.7,
        miss_log_odds=-0.3,
        noise_m=0.05,
        noise_per_m2=8e-4,  # depth error of a 0.3 m baseline: ~0.75 m at 30 m
    ),
}
