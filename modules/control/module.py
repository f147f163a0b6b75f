"""The control process: VehicleState and Path in, ActuatorCommand out at 50 Hz.

Every tick it drives only if both inputs are fresh and usable and the operator has not paused
or e-stopped the vehicle; otherwise it brakes fully with the steering held, and says why in
``stop_reason``. Entering and leaving that fail-safe are reported once each as HealthEvents.
Stop commands act inside the subscription handler: the braking command leaves at once, not at
the next tick. Given the course, a corridor guard slows, then stops, the vehicle rather than let
its steering take it out of the corridor; each such stop is one ``corridor_edge`` HealthEvent.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path as FilePath

from brain.course_config import load_course
from brain.vehicle import VehicleGeometry
from modules.control.controller import ControllerSettings, Mode, Motion, Output
from modules.control.corridor_guard import CorridorGuard, GuardSettings
from modules.control.path_tracking import DEFAULT_HEADING_SMOOTHING_M, PathError, TrackedPath
from modules.control.reverse import ReversingController
from modules.control.stop_latch import StopLatch, StopOrder
from protocol import channels
from protocol.codec import Envelope
from protocol.messages import ActuatorCommand, NavQuality, Path, Severity, StopCommand, StopMode, VehicleState
from rascal.runtime.config import ConfigError, section, setting
from rascal.runtime.module import Module, run_artefact
from rascal.runtime.ports import Port
from rascal.runtime.rtdb import Validity


@dataclass(frozen=True)
class ControlConfig:
    rate_hz: float = setting(50.0, "actuator command rate")
    state_max_age_s: float = setting(0.2, "VEHICLE_STATE older than this is stale: fail-safe brake")
    path_max_age_s: float = setting(0.5, "PATH older than this is stale: fail-safe brake")
    heading_smoothing_m: float = setting(
        DEFAULT_HEADING_SMOOTHING_M, "path heading is averaged over +- this (sharp corners start turning early)"
    )
    stop_file: str = setting(
        "", "where the operator's stop/pause outlives a restart (default: control.stop.json in the run/state dir)"
    )
    course: str = setting("", "RDDF file whose corridor the guard keeps the vehicle in (empty: no corridor guard)")
    origin: str = setting("", "ENU origin 'lat,lon[,alt]' overriding the course's first waypoint")
    controller: ControllerSettings = section(ControllerSettings, "the steering law, its gains and the speed loop")
    guard: GuardSettings = section(GuardSettings, "the corridor guard: how far ahead, how near the edge")
    vehicle: VehicleGeometry = section(VehicleGeometry, "the vehicle steered: wheelbase, steering limits, footprint")

    def __post_init__(self) -> None:
        for name in ("rate_hz", "state_max_age_s", "path_max_age_s"):
            if not getattr(self, name) > 0.0:
                raise ConfigError(f"{name} must be positive, got {getattr(self, name)!r}")
        if not self.heading_smoothing_m >= 0.0:
            raise ConfigError(f"heading_smoothing_m must not be negative, got {self.heading_smoothing_m!r}")


class Control(Module):
    """Vehicle control: path interface, Stanley or PD steering, PI speed; fail-safe braking."""

    name = "control"
    default_source_id = 40
    Config = ControlConfig
    interface = (
        Port(
            "in",
            "`VEHICLE_STATE`",
            "VehicleState (rear-axle pose, speed, yaw rate, nav quality)",
            "INS rate (≥ 20 Hz)",
            "`state_max_age_s` (0.2 s)",
        ),
        Port(
            "in",
            "`PATH`",
            "Path (ENU points with target speeds, `slow_mode`, `reverse`)",
            "planner rate (≥ 2 Hz)",
            "`path_max_age_s` (0.5 s)",
        ),
        Port("in", "`STOP`", "StopCommand (RUN, PAUSE, ESTOP)", "on event", "none: acted on in the handler"),
        Port(
            "out",
            "`ACTUATOR_COMMAND`",
            "ActuatorCommand (throttle, brake 0..1, steering left +, `stop_reason`, `reverse` gear)",
            "`rate_hz` (50), plus one at once per stop command",
        ),
        Port(
            "out",
            "`HEALTH`",
            "HealthEvent `control_failsafe` / `control_resumed` (once per transition), `estop`, `pause`, `run`, "
            "`stop_unknown`, `corridor_edge` (once per stop at the edge)",
            "on event",
        ),
        Port(
            "out",
            "`MODULE_STATUS`",
            "ModuleStatus; detail: controller, mode, cross-track error, speed error, steering, "
            "predicted corridor clearance and cap",
            "1 Hz",
        ),
    )

    def on_start(self) -> None:
        config: ControlConfig = self.config
        self.dt_s = 1.0 / config.rate_hz
        self.controller = ReversingController(config.controller, vehicle=config.vehicle)
        self.state_in = self.input(channels.VEHICLE_STATE, config.state_max_age_s)
        self.path_in = self.input(channels.PATH, config.path_max_age_s)
        if config.course:
            corridor = load_course(config.course, config.origin).corridor
            self.controller.guard = CorridorGuard(corridor, config.vehicle, config.guard)
        self.at_edge = False  # stopped for the corridor's edge, until the guard sees its margin kept again
        self.latch = StopLatch(_stop_file(config.stop_file))
        order, problem = self.latch.load()
        self.stop_mode, self.stop_text = order.mode, order.reason
        if problem is not None:
            self.report(Severity.ERROR, "stop_file", problem)
        elif order.mode is not StopMode.RUN:
            held = f"restarted under an operator stop: {order.reason}; holding until RUN"
            self.report(Severity.CRITICAL, "pause", held)
        self.failsafe_reason: str | None = None  # None: not in the fail-safe
        self.last: Output | None = None
        self.commands = 0
        self._path_msg: Path | None = None  # the Path message the controller follows (or rejected)
        self._path_error: str | None = None
        self.bus.subscribe(channels.STOP, self.on_stop_command)
        self.every(self.dt_s, self.tick, priority=5)

    # -- operator stop ------------------------------------------------------------------------

    def on_stop_command(self, command: StopCommand, _envelope: Envelope) -> None:
        if self.stop_mode is StopMode.ESTOP:
            return  # latched until the process restarts
        try:
            mode = StopMode(command.mode)
        except ValueError:
            # An order we cannot read is still someone asking to stop: hold braked until RUN.
            mode = StopMode.PAUSE
            self.report(Severity.WARNING, "stop_unknown", f"unknown stop mode {command.mode}: holding as PAUSE")
        if mode is self.stop_mode:
            return
        try:
            self.latch.store(StopOrder(mode, command.reason))
        except OSError as exc:
            # Honour the order regardless: failing to remember a stop must not stop it working.
            self.report(Severity.ERROR, "stop_file", f"{self.latch.path}: {exc}; a restart would forget this order")
        self.stop_mode, self.stop_text = mode, command.reason
        severity = Severity.CRITICAL if mode is StopMode.ESTOP else Severity.INFO
        self.report(severity, mode.name.lower(), command.reason or mode.name)
        if mode is not StopMode.RUN:
            self._publish(self._operator_stop())

    def _operator_stop(self) -> Output:
        mode = Mode.ESTOP if self.stop_mode is StopMode.ESTOP else Mode.PAUSE
        reason = f"{mode.value}: {self.stop_text}" if self.stop_text else mode.value
        return self.controller.brake(reason, mode, self.dt_s)

    # -- the periodic step --------------------------------------------------------------------

    def tick(self) -> None:
        if self.stop_mode is not StopMode.RUN:
            self._publish(self._operator_stop())
            return
        now = self.now_ns()
        state_reading = self.state_in.read(now)
        path_reading = self.path_in.read(now)
        problems = [
            problem
            for problem in (
                _input_problem(channels.VEHICLE_STATE, state_reading.validity, state_reading.age_ns),
                _input_problem(channels.PATH, path_reading.validity, path_reading.age_ns),
            )
            if problem is not None
        ]
        state: VehicleState | None = state_reading.value
        if state is not None and state.quality == NavQuality.INVALID:
            problems.append("VEHICLE_STATE invalid (no navigation solution)")
        if path_reading.value is not None:
            path_problem = self._take_path(path_reading.value)
            if path_problem is not None:
                problems.append(path_problem)
        if problems or state is None:
            reason = "; ".join(problems)
            self._failsafe(reason)
            self._publish(self.controller.brake(reason, Mode.FAILSAFE, self.dt_s))
            return
        motion = Motion.of(state, (state_reading.age_ns or 0) / 1e9)  # where the vehicle is now, not when measured
        out = self.controller.drive(motion, self.dt_s)
        # Being far off the path is a fail-safe too: the path no longer describes where we are.
        self._failsafe(out.stop_reason if out.mode is Mode.OFF_PATH else None)
        self._watch_edge(out)
        self._publish(out)

    def _take_path(self, path: Path) -> str | None:
        """Follow ``path`` if it is new and usable; the reason it is not, if it is not."""
        previous = self._path_msg
        if path is not previous and (
            previous is None or path.path_id != previous.path_id or path.points != previous.points
        ):
            self._path_msg = path
            try:
                tracked = TrackedPath.from_points(path.points, self.config.heading_smoothing_m)
                self.controller.set_path(tracked, bool(path.slow_mode), bool(path.reverse))
                self._path_error = None
            except PathError as exc:
                self._path_error = f"PATH {path.path_id} unusable: {exc}"
        elif path is not previous:
            self._path_msg = path
            self.controller.slow_mode = bool(path.slow_mode)
        return self._path_error

    def _failsafe(self, reason: str | None) -> None:
        """Report entering and leaving the fail-safe, once each."""
        if reason is not None and self.failsafe_reason is None:
            self.report(Severity.ERROR, "control_failsafe", f"braking: {reason}")
        elif reason is None and self.failsafe_reason is not None:
            self.report(Severity.INFO, "control_resumed", f"driving again after: {self.failsafe_reason}")
        self.failsafe_reason = reason

    def _watch_edge(self, out: Output) -> None:
        """One corridor_edge event per stop at the edge: the next only once the guard has seen the
        footprint keep its margin again (creeping along the edge, or backing off, is the same stop)."""
        edge = self.controller.edge
        if out.mode is Mode.CORRIDOR and not self.at_edge:
            self.report(Severity.WARNING, "corridor_edge", f"braking: {out.stop_reason} on this steering")
            self.at_edge = True
        elif self.at_edge and edge is not None and edge.clear:
            self.at_edge = False

    def _publish(self, out: Output) -> None:
        self.last = out
        self.commands += 1
        self.bus.publish(
            channels.ACTUATOR_COMMAND,
            ActuatorCommand(out.throttle, out.brake, out.steering_rad, out.stop_reason, out.reverse),
        )

    def on_stop(self) -> None:
        # Leave the vehicle braked when this process ends.
        if hasattr(self, "controller"):
            self._publish(self.controller.brake("control stopping", Mode.FAILSAFE, self.dt_s))

    def status_detail(self) -> str:
        out = self.last
        if out is None:
            return f"{self.config.controller.law}: no command yet"
        text = f"{self.config.controller.law} {out.mode.value}: "
        if not math.isnan(out.cross_track_m):
            text += f"cte {out.cross_track_m:+.2f} m, speed err {out.speed_error_mps:+.2f} m/s, "
        text += f"steer {out.steering_rad:+.3f} rad, sent {self.commands}"
        edge = self.controller.edge
        if edge is not None and out.mode in (Mode.DRIVE, Mode.CORRIDOR) and not out.reverse:
            text += f", corridor edge {edge.clearance_m:+.2f} m"
            text += "" if math.isinf(edge.cap_mps) else f" (cap {edge.cap_mps:.1f} m/s)"
        return text + (f"; {out.stop_reason}" if out.stop_reason else "")


def _input_problem(channel: str, validity: Validity, age_ns: int | None) -> str | None:
    if validity is Validity.NEVER:
        return f"{channel} missing"
    if validity is Validity.STALE:
        return f"{channel} stale ({(age_ns or 0) / 1e9:.2f} s old)"
    return None


def _stop_file(setting_value: str) -> FilePath | None:
    """The configured stop file, else one in the run directory (`rascal run`), else one in
    systemd's state directory (units from `rascal deploy units`), else none: a control started
    by hand keeps its stop order in memory only."""
    if setting_value:
        return FilePath(setting_value)
    state_dir = os.environ.get("STATE_DIRECTORY")
    fallback = FilePath(state_dir.split(":")[0]) / "control.stop.json" if state_dir else None
    return run_artefact("control.stop.json") or fallback
