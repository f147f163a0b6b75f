"""Driving a path backwards, and the gear change before it.

A reversing vehicle's rear axle leads: seen in the direction of travel (heading yaw + pi, speed
-v > 0) it moves like the rear axle of a forward vehicle whose wheels are turned the other way
(yaw rate = v tan(delta) / L = u tan(-delta) / L). So reversing is tracked at the rear axle, in
that frame, by curvature feedforward plus feedback on heading and cross-track error:

    kappa = kappa_path + k_heading * heading_error - k_cross * cross_track,   delta = -atan(L kappa)

With u constant the errors obey e'' + k_heading e' + k_cross e = 0 per metre travelled: a
response that settles over the same distance at any speed (the Stanley law's reference point,
the front axle, would trail here and is not stable). Target speeds are magnitudes; the reverse
gear is commanded, and the vehicle is braked to a standstill before any gear change.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from brain.vehicle import VehicleGeometry
from modules.control.controller import ControllerSettings, Mode, Motion, Output, VehicleController, require_finite
from modules.control.path_tracking import Projection, TrackedPath, wrap_angle


@dataclass(frozen=True)
class ReverseSettings:
    # Natural frequency 1 per metre with damping 0.9: a 10 cm offset is mostly gone in 3 m.
    heading_gain_1pm: float = 1.8
    cross_track_gain_1pm2: float = 1.0
    max_speed_mps: float = 1.5  # backing up is slow, whatever the path says
    # Target speed is read this far ahead: at these speeds the brakes stop the vehicle within
    # 0.3 m, so a longer preview would only stop it short of the path's end.
    speed_preview_m: float = 0.5
    gear_change_speed_mps: float = 0.05  # slower than this counts as a standstill (the vehicle's: 0.1)

    def __post_init__(self) -> None:
        names = (
            "heading_gain_1pm",
            "cross_track_gain_1pm2",
            "max_speed_mps",
            "speed_preview_m",
            "gear_change_speed_mps",
        )
        require_finite(self, names, positive=True)


class ReversingController(VehicleController):
    """The vehicle controller with a reverse gear: forward paths exactly as VehicleController
    drives them; reverse paths at the rear axle as above; a stop before every gear change."""

    def __init__(
        self,
        settings: ControllerSettings | None = None,
        reverse: ReverseSettings | None = None,
        vehicle: VehicleGeometry | None = None,
    ) -> None:
        super().__init__(settings, vehicle)
        self.reverse_settings = reverse or ReverseSettings()
        self.reverse = False  # the path asks to be driven backwards
        self.reverse_gear = False  # the gear commanded

    def set_path(self, path: TrackedPath, slow_mode: bool = False, reverse: bool = False) -> None:
        super().set_path(path, slow_mode)
        self.reverse = reverse

    def brake(self, reason: str, mode: Mode, dt_s: float) -> Output:
        """Braking keeps the gear: changing it is for a standstill and a path that asks."""
        return super().brake(reason, mode, dt_s)._replace(reverse=self.reverse_gear)

    def drive(self, motion: Motion, dt_s: float) -> Output:
        if self.reverse != self.reverse_gear:
            speed = abs(motion.speed_mps)
            if speed >= self.reverse_settings.gear_change_speed_mps:
                self._idle_s += dt_s
                self._last_speed_mps = speed
                return self._hold(speed, "stopping to change gear", Mode.HOLD)._replace(reverse=self.reverse_gear)
            self.reverse_gear = self.reverse
        if not self.reverse_gear:
            return super().drive(motion, dt_s)
        return self._drive_backwards(motion, dt_s)

    def _drive_backwards(self, motion: Motion, dt_s: float) -> Output:
        if not dt_s > 0.0:
            raise ValueError(f"dt_s must be positive, got {dt_s!r}")
        if self.tracker.path is None:
            raise RuntimeError("drive() before set_path()")
        s, r = self.settings, self.reverse_settings
        pose = motion.pose
        speed = max(0.0, -motion.speed_mps)  # backwards, as a magnitude
        self._last_speed_mps = speed
        travelled = speed * (dt_s + self._idle_s) + 1.0
        self._idle_s = 0.0
        heading = wrap_angle(pose.yaw_rad + math.pi)  # the direction of travel
        where = self.tracker.locate(pose.east_m, pose.north_m, heading, travelled)
        if abs(where.cross_track_m) > s.max_cross_track_m:
            out = self.brake(f"off path: {where.cross_track_m:+.1f} m from it", Mode.OFF_PATH, dt_s)
            return out._replace(cross_track_m=where.cross_track_m)

        heading_error = wrap_angle(where.heading_rad - heading)
        curvature = (
            where.curvature_1pm + r.heading_gain_1pm * heading_error - r.cross_track_gain_1pm2 * where.cross_track_m
        )
        target = -math.atan(self.vehicle.wheelbase_m * curvature)
        self._steering_wanted_rad = target
        self.steering_rad = self.limits.apply(self.steering_rad, target, dt_s)

        return self._speed_step(where, speed, self._backing_speed(where), heading_error, dt_s)._replace(reverse=True)

    def _backing_speed(self, where: Projection) -> float:
        r = self.reverse_settings
        if where.beyond_end_m > 0.0:
            return 0.0
        target = min(self.tracker.speed_ahead(where, r.speed_preview_m), r.max_speed_mps)
        return min(target, self.settings.slow_mode_speed_mps) if self.slow_mode else target
