"""The vehicle controller without any I/O: the vehicle's motion and a path in, an actuator command out.

It joins RASCAL's three parts (II.C): the path interface (``path_tracking``), heading control
(``steering``: Stanley/Hoffmann or RASCAL's PD) and speed control (``speed``: PI), and applies
the steering limits. Deciding *whether* to drive (stale inputs, pause, e-stop) is the process's
job; it calls :meth:`VehicleController.brake` instead of :meth:`drive` then. Given a corridor
guard (``corridor_guard``), driving forwards slows, then stops, rather than cut out of the corridor.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import NamedTuple, Protocol

from brain.pose import Pose, PoseLike
from brain.vehicle import VehicleGeometry
from modules.control.corridor_guard import CorridorGuard, EdgeVerdict
from modules.control.limits import SteeringLimits
from modules.control.path_tracking import PathTracker, Projection, TrackedPath, wrap_angle
from modules.control.speed import PiSpeedController, SpeedGains, split_effort
from modules.control.steering import PdGains, PdHeadingController, StanleyGains, heading_gain, stanley_steering
from rascal.runtime.config import section, setting

LAWS = ("stanley", "pd")
NO_GUARD = EdgeVerdict(math.inf, math.inf, math.inf)


class Mode(enum.Enum):
    DRIVE = "drive"
    HOLD = "hold"  # the path asks for zero speed here and the vehicle has stopped
    END = "end"  # past the end of the path
    OFF_PATH = "off_path"
    FAILSAFE = "failsafe"
    PAUSE = "pause"
    ESTOP = "estop"
    CORRIDOR = "corridor"  # on this steering the footprint would cross the corridor's edge


class NavState(PoseLike, Protocol):
    """What control reads of a navigation solution (``protocol.messages.VehicleState`` fits)."""

    @property
    def speed_mps(self) -> float: ...

    @property
    def yaw_rate_radps(self) -> float: ...


class Motion(NamedTuple):
    """What the controller needs of the navigation solution: the rear axle's pose and how it moves."""

    pose: Pose
    speed_mps: float  # signed: along the body's x axis, negative backwards
    yaw_rate_radps: float = 0.0

    @classmethod
    def of(cls, state: NavState, age_s: float = 0.0) -> Motion:
        """``state`` dead-reckoned ``age_s`` on at its speed and yaw rate, along their arc. A
        navigation solution is tens of milliseconds old when control acts on it; at 2 m/s, 60 ms
        is 0.12 m, as much as the corridor margin."""
        east, north, yaw = state.east_m, state.north_m, state.yaw_rad
        speed, yaw_rate = state.speed_mps, state.yaw_rate_radps
        if age_s > 0.0:
            half_turn = 0.5 * yaw_rate * age_s
            chord = speed * age_s * (math.sin(half_turn) / half_turn if half_turn else 1.0)
            heading = yaw + half_turn
            east += chord * math.cos(heading)
            north += chord * math.sin(heading)
            yaw = wrap_angle(yaw + 2.0 * half_turn)
        return cls(Pose(east, north, yaw), speed, yaw_rate)


class Output(NamedTuple):
    throttle: float
    brake: float
    steering_rad: float
    stop_reason: str  # empty while driving
    mode: Mode
    cross_track_m: float  # of the reference point, left positive (nan when not on a path)
    heading_error_rad: float
    target_speed_mps: float
    speed_error_mps: float  # target minus actual
    reverse: bool = False  # the reverse gear (see reverse.py)


def require_finite(settings: object, names: Iterable[str], *, positive: bool) -> None:
    """ValueError naming the first of ``names`` that is not finite and positive (or, with
    ``positive=False``, not finite and at least 0)."""
    for name in names:
        value = getattr(settings, name)
        if not (math.isfinite(value) and (value > 0.0 if positive else value >= 0.0)):
            raise ValueError(f"{name} must be finite and {'positive' if positive else 'not negative'}, got {value!r}")


@dataclass(frozen=True)
class ControllerSettings:
    """The steering law, its gains and the speed loop's (the vehicle it steers is apart:
    brain/vehicle.py)."""

    law: str = setting("stanley", "steering law: stanley (Hoffmann, Kratos 4.6) or pd (RASCAL heading PD)")
    stanley: StanleyGains = section(StanleyGains, "the Stanley law's gains")
    pd: PdGains = section(PdGains, "the PD heading law's gains")
    speed: SpeedGains = section(SpeedGains, "the PI speed loop's gains")
    heading_bandwidth_radps: float = setting(
        6.0, "cap on the heading loop's bandwidth: above bandwidth * wheelbase the heading gain falls as 1/v"
    )
    speed_preview_time_s: float = setting(0.5, "target speed is read this many seconds of travel ahead")
    speed_preview_min_m: float = setting(2.0, "... and at least this far (a path starting at 0 m/s still starts)")
    stop_speed_mps: float = setting(0.3, "below it, with a zero target, the brake is simply held")
    slow_mode_speed_mps: float = setting(1.0, "speed cap while the path is in slow mode (RASCAL: 1 m/s)")
    max_cross_track_m: float = setting(5.0, "further from the path than this: brake (off path)")
    # The steering asks for more than the wheels' limit: the path turns tighter than the vehicle
    # can at this speed (or the vehicle is rejoining it). Slow to the speed at which the tightest
    # turn takes this lateral acceleration, until the steering has room again.
    saturated_share: float = setting(0.9, "steering asked beyond this share of the wheel stop is saturated")
    saturated_lateral_accel_mps2: float = setting(
        2.0, "saturated, slow to the speed at which the tightest turn takes this lateral acceleration"
    )
    window_back_m: float = setting(2.0, "the path is searched for the vehicle this far back ...")
    window_ahead_m: float = setting(6.0, "... and this far ahead of where it was")
    curvature_window_m: float = setting(2.0, "path curvature is averaged over this length")

    def __post_init__(self) -> None:
        if self.law not in LAWS:
            raise ValueError(f"controller law must be one of {LAWS}, not {self.law!r}")
        positive = (
            "heading_bandwidth_radps",
            "speed_preview_min_m",
            "stop_speed_mps",
            "max_cross_track_m",
            "window_ahead_m",
            "saturated_share",
            "saturated_lateral_accel_mps2",
        )
        require_finite(self, positive, positive=True)
        not_negative = (
            "speed_preview_time_s",
            "slow_mode_speed_mps",
            "window_back_m",
            "curvature_window_m",
        )
        require_finite(self, not_negative, positive=False)


class VehicleController:
    """Path tracking, heading and speed control with the steering limits, one step at a time."""

    def __init__(self, settings: ControllerSettings | None = None, vehicle: VehicleGeometry | None = None) -> None:
        self.settings = settings or ControllerSettings()
        self.vehicle = vehicle or VehicleGeometry()
        self.limits = SteeringLimits(self.vehicle.max_steering_rad, self.vehicle.max_steering_rate_radps)
        s = self.settings
        self.tracker = PathTracker(s.window_back_m, s.window_ahead_m, max(s.curvature_window_m, 1e-3))
        self.pd = PdHeadingController(s.pd)
        self.speed = PiSpeedController(s.speed)
        self.steering_rad = 0.0  # the last commanded (already limited) wheel angle
        self._steering_wanted_rad = 0.0  # what the steering law asked for, before the limits
        self.slow_mode = False
        self._idle_s = 0.0  # time since the last drive step, for the tracker's search window
        self._last_speed_mps = 0.0
        self.guard: CorridorGuard | None = None  # the process sets one when it knows the course
        self.edge: EdgeVerdict | None = None  # the guard's last verdict

    def set_path(self, path: TrackedPath, slow_mode: bool = False) -> None:
        """Follow a new path (raises PathError through TrackedPath if it is unusable)."""
        self.tracker.set_path(path)
        self.slow_mode = slow_mode
        self.pd.reset()

    def brake(self, reason: str, mode: Mode, dt_s: float) -> Output:
        """Full brake, no throttle, steering held where it is; the controllers start afresh later."""
        self.speed.reset()
        self.pd.reset()
        self._idle_s += dt_s
        return Output(0.0, 1.0, self.steering_rad, reason, mode, math.nan, math.nan, 0.0, -self._last_speed_mps)

    def drive(self, motion: Motion, dt_s: float) -> Output:
        if not dt_s > 0.0:
            raise ValueError(f"dt_s must be positive, got {dt_s!r}")
        if self.tracker.path is None:
            raise RuntimeError("drive() before set_path()")
        s = self.settings
        pose = motion.pose
        speed = max(0.0, motion.speed_mps)
        self._last_speed_mps = speed
        travelled = speed * (dt_s + self._idle_s) + 1.0
        self._idle_s = 0.0

        # The reference point: Stanley works at the front axle (its heading term then holds a
        # curve with no cross-track error), the PD at the rear axle it steers around.
        offset = self.vehicle.wheelbase_m if s.law == "stanley" else 0.0
        ref_east = pose.east_m + offset * math.cos(pose.yaw_rad)
        ref_north = pose.north_m + offset * math.sin(pose.yaw_rad)
        where = self.tracker.locate(ref_east, ref_north, pose.yaw_rad, travelled)

        if abs(where.cross_track_m) > s.max_cross_track_m:
            # Too far to rejoin by steering: this is not a path we are on.
            out = self.brake(f"off path: {where.cross_track_m:+.1f} m from it", Mode.OFF_PATH, dt_s)
            return out._replace(cross_track_m=where.cross_track_m)

        gain = heading_gain(speed, self.vehicle.wheelbase_m, s.heading_bandwidth_radps)
        if s.law == "stanley":
            heading_error = wrap_angle(where.heading_rad - pose.yaw_rad)
            target = stanley_steering(
                heading_error, where.cross_track_m, speed, s.stanley, motion.yaw_rate_radps, where.curvature_1pm, gain
            )
        else:
            look_east, look_north = self.tracker.lookahead_point(where, s.pd.lookahead_m(speed))
            bearing = math.atan2(look_north - pose.north_m, look_east - pose.east_m)
            heading_error = wrap_angle(bearing - pose.yaw_rad)
            target = gain * self.pd.steer(heading_error, dt_s)
        self._steering_wanted_rad = target
        self.steering_rad = self.limits.apply(self.steering_rad, target, dt_s)

        target_speed = self._target_speed(where, speed)
        edge = self._check_edge(pose, speed, target_speed)
        if edge.brake:
            stop = f"corridor edge {edge.crossing_m:.1f} m ahead"
            return self._speed_step(where, speed, target_speed, heading_error, dt_s, stop)
        return self._speed_step(where, speed, target_speed, heading_error, dt_s, cap_mps=edge.cap_mps)

    def _speed_step(
        self,
        where: Projection,
        speed: float,
        target_speed: float,
        heading_error: float,
        dt_s: float,
        edge_stop: str | None = None,
        cap_mps: float = math.inf,
    ) -> Output:
        """The speed half of a step, either way along the path: hold at its end, where it asks
        to stop or at the corridor's edge (``edge_stop``), else the PI towards ``target_speed``
        under the corridor guard's ``cap_mps``."""
        s = self.settings
        if where.beyond_end_m > 0.0:
            out = self._hold(speed, "end of path", Mode.END)
        elif target_speed < s.stop_speed_mps and speed < s.stop_speed_mps:
            out = self._hold(speed, "path asks to stop", Mode.HOLD)
        elif edge_stop is not None:
            out = self._hold(speed, edge_stop, Mode.CORRIDOR)
        else:
            target_speed = min(target_speed, cap_mps)
            effort = self.speed.update(target_speed, speed, dt_s)
            throttle, brake = split_effort(effort, s.speed.deadband)
            out = Output(throttle, brake, self.steering_rad, "", Mode.DRIVE, 0.0, 0.0, 0.0, 0.0)
        return out._replace(
            cross_track_m=where.cross_track_m,
            heading_error_rad=heading_error,
            target_speed_mps=target_speed,
            speed_error_mps=target_speed - speed,
        )

    def _target_speed(self, where: Projection, speed_mps: float) -> float:
        s = self.settings
        preview = max(s.speed_preview_min_m, s.speed_preview_time_s * speed_mps)
        target = self.tracker.speed_ahead(where, preview)
        if where.beyond_end_m > 0.0:
            target = 0.0
        if self.slow_mode:
            target = min(target, s.slow_mode_speed_mps)
        limit = self.limits.max_steering_rad
        if abs(self._steering_wanted_rad) >= s.saturated_share * limit:
            tightest_curvature = math.tan(limit) / self.vehicle.wheelbase_m
            target = min(target, math.sqrt(s.saturated_lateral_accel_mps2 / tightest_curvature))
        return target

    def _check_edge(self, pose: Pose, speed_mps: float, target_speed_mps: float) -> EdgeVerdict:
        """The guard's verdict on the steering just commanded (no cap, no brake without a guard)."""
        if self.guard is None:
            return NO_GUARD
        self.edge = self.guard.assess(
            pose.east_m, pose.north_m, pose.yaw_rad, speed_mps, self.steering_rad, target_speed_mps
        )
        return self.edge

    def _hold(self, speed_mps: float, reason: str, mode: Mode) -> Output:
        """Stopped (or stopping) on purpose: brake fully, keep steering along the path."""
        self.speed.reset()
        return Output(0.0, 1.0, self.steering_rad, reason, mode, 0.0, 0.0, 0.0, -speed_mps)
