"""A synthetic obstacle sensor: a known, moving pattern of descriptors at a fixed rate.

It stands in for a sensor wherever one is needed without a simulator: the demo, bus tests,
and load. Obstacles circle the vehicle so consumers can check what they receive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from protocol import channels
from protocol.messages import Frame, Obstacle, ObstacleList, Sensor
from rascal.runtime.config import setting
from rascal.runtime.module import Module
from rascal.runtime.ports import Port


@dataclass(frozen=True)
class BeaconConfig:
    rate_hz: float = setting(10.0, "ObstacleList publication rate")
    obstacles: int = setting(4, "descriptors per message")
    radius_m: float = setting(15.0, "distance of the circling obstacles from the vehicle")
    angular_speed_radps: float = setting(0.2, "how fast the pattern turns")
    channel: str = setting(channels.OBSTACLES_BEACON, "channel to publish on")


class Beacon(Module):
    """Synthetic obstacle source: publishes a turning ring of obstacles in the vehicle frame."""

    name = "beacon"
    default_source_id = 3
    Config = BeaconConfig
    interface = (
        Port("out", "`OBSTACLES_BEACON` (configurable)", "ObstacleList (SYNTHETIC, VEHICLE frame)", "`rate_hz` (10)"),
        Port("out", "`MODULE_STATUS`", "ModuleStatus", "1 Hz"),
    )

    def on_start(self) -> None:
        if self.config.rate_hz <= 0 or self.config.obstacles < 0:
            raise ValueError("beacon: rate_hz must be positive and obstacles non-negative")
        self.sent = 0
        self.every(1.0 / self.config.rate_hz, self.publish, priority=1)

    def publish(self) -> None:
        now = self.now_ns()
        self.bus.publish(self.config.channel, ring_of_obstacles(self.config, now * 1e-9), t_meas_ns=now)
        self.sent += 1

    def status_detail(self) -> str:
        return f"sent {self.sent}"


def ring_of_obstacles(config: BeaconConfig, t_s: float) -> ObstacleList:
    """The pattern at time ``t_s``: evenly spaced boxes on a circle, turning slowly."""
    count = config.obstacles
    obstacles = []
    for i in range(count):
        angle = math.remainder(config.angular_speed_radps * t_s + 2 * math.pi * i / max(count, 1), 2 * math.pi)
        x, y = config.radius_m * math.cos(angle), config.radius_m * math.sin(angle)
        obstacles.append(Obstacle(x, y, 1.0, 0.8, 1.2, angle, 0.9, math.hypot(x, y)))
    return ObstacleList(Sensor.SYNTHETIC, Frame.VEHICLE, tuple(obstacles))
