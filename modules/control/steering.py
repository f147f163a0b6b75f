"""Steering laws: Stanley/Hoffmann path tracking (Kratos 4.6) and RASCAL's PD heading controller.

Both return a front-wheel angle in radians, left positive, before the actuator limits (see
``limits.py``), which the caller applies.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rascal.runtime.config import setting


def heading_gain(speed_mps: float, wheelbase_m: float, bandwidth_radps: float) -> float:
    """Gain on the heading term that keeps the heading loop's bandwidth at most ``bandwidth_radps``.

    Steering by the heading error closes a loop of gain v / L (yaw rate per radian of wheel
    angle): 14 rad/s at 17.8 m/s on a 1.25 m wheelbase, which 60 ms of delay between measuring
    and steering already turns unstable. Above bandwidth * L the gain falls as 1 / v, holding
    that loop at ``bandwidth_radps``; the cross-track term makes up the small remainder in curves.
    """
    v = max(0.0, speed_mps)
    limit = bandwidth_radps * wheelbase_m
    return 1.0 if v <= limit else limit / v


@dataclass(frozen=True)
class StanleyGains:
    """Gains of the Hoffmann et al. (2007) law, evaluated at the front axle."""

    gain: float = setting(2.5, "k, 1/s: how hard a cross-track error turns the wheels (psi + atan(k e / (k_soft + v)))")
    softening_mps: float = setting(1.0, "k_soft: keeps the law finite and calm at walking speed")
    yaw_damping_s: float = setting(0.0, "k_d,yaw: steers against yaw rate the path does not ask for (0: off)")

    def __post_init__(self) -> None:
        if not (self.gain > 0.0 and self.softening_mps > 0.0 and self.yaw_damping_s >= 0.0):
            raise ValueError(f"Stanley gains must be positive (yaw damping may be 0): {self}")


def stanley_steering(
    heading_error_rad: float,
    cross_track_m: float,
    speed_mps: float,
    gains: StanleyGains,
    yaw_rate_radps: float = 0.0,
    path_curvature_1pm: float = 0.0,
    heading_gain: float = 1.0,
) -> float:
    """delta = g psi + atan(k e / (k_soft + v)) + k_yaw (r_path - r), with g = ``heading_gain``
    (1 in Hoffmann's law; see :func:`heading_gain` for why it falls at high speed).

    ``heading_error_rad`` is path heading minus vehicle yaw (positive: the path turns left of the
    vehicle). Hoffmann's e is positive to the RIGHT of the path, so with our left-positive
    ``cross_track_m`` the correction term is subtracted: a vehicle left of the path steers right.
    The yaw-rate term compares the measured yaw rate with the one the path's curvature asks for.
    """
    v = max(0.0, speed_mps)
    delta = heading_gain * heading_error_rad - math.atan(gains.gain * cross_track_m / (gains.softening_mps + v))
    if gains.yaw_damping_s:
        delta += gains.yaw_damping_s * (v * path_curvature_1pm - yaw_rate_radps)
    return delta


@dataclass(frozen=True)
class PdGains:
    """RASCAL's heading controller: PD on the error to the bearing of a look-ahead point."""

    kp: float = setting(1.0, "wheel angle per radian of heading error to the look-ahead point")
    kd_s: float = setting(0.1, "wheel angle per rad/s of heading-error rate")
    derivative_tau_s: float = setting(0.05, "low-pass on the differentiated error (measured yaw is noisy)")
    lookahead_min_m: float = setting(2.5, "shortest look-ahead distance")
    lookahead_time_s: float = setting(0.4, "look-ahead distance per m/s of speed")

    def __post_init__(self) -> None:
        if not (self.kp > 0.0 and self.kd_s >= 0.0 and self.derivative_tau_s >= 0.0):
            raise ValueError(f"PD gains: kp must be positive, kd_s and derivative_tau_s not negative: {self}")
        if not (self.lookahead_min_m > 0.0 and self.lookahead_time_s >= 0.0):
            raise ValueError(f"PD look-ahead must be positive: {self}")

    def lookahead_m(self, speed_mps: float) -> float:
        return max(self.lookahead_min_m, self.lookahead_time_s * max(0.0, speed_mps))


class PdHeadingController:
    """delta = kp e + kd de/dt, with de/dt a filtered difference of successive errors."""

    def __init__(self, gains: PdGains) -> None:
        self.gains = gains
        self._last_error: float | None = None
        self._rate = 0.0

    def reset(self) -> None:
        """Forget the error history (new path, or resuming after a stop): no derivative kick."""
        self._last_error = None
        self._rate = 0.0

    def steer(self, heading_error_rad: float, dt_s: float) -> float:
        if not dt_s > 0.0:
            raise ValueError(f"dt_s must be positive, got {dt_s!r}")
        g = self.gains
        if self._last_error is not None:
            # Difference through the wrap so a bearing crossing +-pi is not a 2 pi step.
            raw = math.remainder(heading_error_rad - self._last_error, 2.0 * math.pi) / dt_s
            alpha = dt_s / (g.derivative_tau_s + dt_s)
            self._rate += alpha * (raw - self._rate)
        self._last_error = heading_error_rad
        return g.kp * heading_error_rad + g.kd_s * self._rate
