"""The module guide's example (docs/MODULE_GUIDE.md quotes this file): one obstacle straight ahead.

Run it as a process: ``python tests/guide/example_module.py --bus URL --set distance_m=8``.
"""

from __future__ import annotations

from dataclasses import dataclass

from protocol import channels
from protocol.messages import Frame, Obstacle, ObstacleList, Sensor
from rascal.runtime.config import setting
from rascal.runtime.launch import run_module
from rascal.runtime.module import Module
from rascal.runtime.ports import Port

# A real module declares its own channel in protocol/channels.py (the bus tools refuse undeclared
# channels); the example borrows the beacon's, so it needs no edit outside the tests.
CHANNEL = channels.OBSTACLES_BEACON


@dataclass(frozen=True)
class ExampleConfig:
    rate_hz: float = setting(5.0, "ObstacleList publication rate")
    distance_m: float = setting(10.0, "how far ahead of the vehicle the obstacle stands")


class Example(Module):
    """Publishes one obstacle ahead of the vehicle at a fixed rate."""

    name = "example"
    default_source_id = 60
    Config = ExampleConfig
    interface = (
        Port("out", "`OBSTACLES_BEACON`", "ObstacleList (SYNTHETIC, VEHICLE frame)", "`rate_hz` (5)"),
        Port("out", "`MODULE_STATUS`", "ModuleStatus", "1 Hz"),
    )

    def on_start(self) -> None:
        if self.config.rate_hz <= 0:
            raise ValueError("example: rate_hz must be positive")
        self.sent = 0
        self.every(1.0 / self.config.rate_hz, self.publish, priority=1)

    def publish(self) -> None:
        now = self.now_ns()
        d = self.config.distance_m
        obstacle = Obstacle(d, 0.0, 1.0, 1.0, 1.0, 0.0, 0.9, d)
        self.bus.publish(CHANNEL, ObstacleList(Sensor.SYNTHETIC, Frame.VEHICLE, (obstacle,)), t_meas_ns=now)
        self.sent += 1

    def status_detail(self) -> str:
        return f"sent {self.sent}"


if __name__ == "__main__":
    run_module(Example)
