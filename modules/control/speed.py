"""Speed control: a PI on speed error (RASCAL II.C, Kratos 4.7) and the throttle/brake split.

The controller's output is one signed effort in [-1, 1]: positive drives, negative brakes. The
integrator carries the throttle that holds a speed against drag and rolling resistance (the "DC
gain" RASCAL's integrator corrected). It only integrates while that can change the output
(conditional integration), and is clamped as well, so a long climb to a speed the vehicle cannot
reach, or a hard stop, does not leave it wound up.
"""

from __future__ import annotations

from dataclasses import dataclass

from modules.control.limits import clamp
from rascal.runtime.config import setting


@dataclass(frozen=True)
class SpeedGains:
    kp: float = setting(0.5, "effort per m/s of speed error (effort > 0 throttle, < 0 brake)")
    ki: float = setting(0.2, "effort per m/s of error per second")
    integral_min: float = setting(-0.5, "the integrator's share of the effort is held above this ...")
    integral_max: float = setting(1.0, "... and below this")
    deadband: float = setting(0.03, "efforts this small neither drive nor brake (no throttle/brake chatter)")

    def __post_init__(self) -> None:
        if not (self.kp >= 0.0 and self.ki >= 0.0 and self.kp + self.ki > 0.0):
            raise ValueError(f"speed gains must not be negative, and not both zero: {self}")
        if not -1.0 <= self.integral_min <= 0.0 <= self.integral_max <= 1.0:
            raise ValueError(f"speed integral bounds must satisfy -1 <= min <= 0 <= max <= 1: {self}")
        if not 0.0 <= self.deadband < 1.0:
            raise ValueError(f"speed deadband must be in [0, 1): {self}")


class PiSpeedController:
    """Signed effort from the speed error, with conditional integration and a clamped integrator."""

    def __init__(self, gains: SpeedGains) -> None:
        self.gains = gains
        self.integral = 0.0  # the integrator's share of the effort (already times ki)

    def reset(self) -> None:
        self.integral = 0.0

    def update(self, target_mps: float, speed_mps: float, dt_s: float) -> float:
        if not dt_s > 0.0:
            raise ValueError(f"dt_s must be positive, got {dt_s!r}")
        g = self.gains
        error = target_mps - speed_mps
        proportional = g.kp * error
        candidate = self.integral + g.ki * error * dt_s
        unsaturated = proportional + candidate
        # Integrate unless the output is saturated and the error would push it further in.
        if not ((unsaturated > 1.0 and error > 0.0) or (unsaturated < -1.0 and error < 0.0)):
            self.integral = clamp(candidate, g.integral_min, g.integral_max)
        return clamp(proportional + self.integral, -1.0, 1.0)


def split_effort(effort: float, deadband: float) -> tuple[float, float]:
    """(throttle, brake) from a signed effort: the deadband around zero coasts, and each pedal
    rises from 0 at the deadband's edge to 1 at full effort (continuous, no step at the edge)."""
    if not 0.0 <= deadband < 1.0:
        raise ValueError(f"deadband must be in [0, 1), got {deadband!r}")
    effort = clamp(effort, -1.0, 1.0)
    if effort > deadband:
        return (effort - deadband) / (1.0 - deadband), 0.0
    if effort < -deadband:
        return 0.0, (-effort - deadband) / (1.0 - deadband)
    return 0.0, 0.0
