"""The vehicle's pose: where its rear axle centre is in ENU, and its heading.

One type for every part of the vehicle side that places things with a pose (fusion, control,
Hybrid A*'s start and goals, the simulated sensors' scans); ``PoseLike`` is what a function needs
when any object with the three fields will do (``protocol.messages.VehicleState`` fits).
"""

from __future__ import annotations

from typing import NamedTuple, Protocol


class Pose(NamedTuple):
    """The vehicle frame's origin (rear axle centre) and heading (counter-clockwise from east) in ENU."""

    east_m: float
    north_m: float
    yaw_rad: float


class PoseLike(Protocol):
    """Anything with a rear-axle pose in ENU: a Pose, a VehicleState, the simulator's state."""

    @property
    def east_m(self) -> float: ...

    @property
    def north_m(self) -> float: ...

    @property
    def yaw_rad(self) -> float: ...
