"""The vehicle's outline and steering, declared once.

The simulator drives this vehicle, control steers it and the planner plans for it: each holds a
``vehicle`` section of this class, and a deployment's ``[vehicle]`` table sets all of them at
once (rascal.runtime.deployment). The defaults are RASCAL's ATV with its sensors and computers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import ClassVar

from rascal.runtime.config import setting


@dataclass(frozen=True)
class VehicleGeometry:
    """Footprint round the rear axle (the pose's reference point) and the steering's limits."""

    deployment_table: ClassVar[str] = "vehicle"  # the deployment table every such section is set from

    width_m: float = setting(1.2, "overall width of the footprint")
    length_m: float = setting(2.1, "overall length of the footprint")
    rear_overhang_m: float = setting(0.4, "rear axle (the pose's reference point) to the rear end")
    wheelbase_m: float = setting(1.25, "rear axle to front axle: with the steering, how tight it turns")
    max_steering_rad: float = setting(0.5, "front wheel angle limit, either side")
    max_steering_rate_radps: float = setting(0.8, "how fast the steering actuator turns the wheels")

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (isinstance(value, int | float) and math.isfinite(value)) or value < 0:
                raise ValueError(f"vehicle.{f.name}: must be finite and not negative, got {value!r}")
            if value == 0 and f.name != "rear_overhang_m":
                raise ValueError(f"vehicle.{f.name}: must be positive")
        if self.rear_overhang_m >= self.length_m:
            raise ValueError("vehicle.rear_overhang_m: must be shorter than length_m")
        if not self.max_steering_rad < math.pi / 2:
            raise ValueError("vehicle.max_steering_rad: must be below pi/2")

    @property
    def half_width_m(self) -> float:
        return self.width_m / 2.0

    @property
    def front_m(self) -> float:
        """Rear axle to the front end."""
        return self.length_m - self.rear_overhang_m

    @property
    def turning_radius_m(self) -> float:
        """The rear axle's tightest turn."""
        return self.wheelbase_m / math.tan(self.max_steering_rad)
