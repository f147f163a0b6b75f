"""Control as a real process: sim and time service alongside, the test standing in for the INS
(VehicleState from the simulator's truth -- only a test may do that) and the planner (Path)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path as FilePath

import numpy as np
import pytest

from modules.sim.scenario import load_scenario
from protocol import channels
from protocol.codec import Envelope
from protocol.messages import (
    ActuatorCommand,
    HealthEvent,
    NavQuality,
    Path,
    PathPoint,
    SimTruth,
    StopCommand,
    StopMode,
    VehicleState,
)
from tests.conftest import Processes
from tests.integration.listener import Listener
from tests.modules.control.closed_loop import signed_distance
from tests.modules.control.short_course import SCENARIO

pytestmark = pytest.mark.slow

PATH_SPEED_MPS = 8.0  # the test's planner caps the course speeds, to keep the run short
PATH_AHEAD_M = 80
ESTOP_DEADLINE_S = 0.2  # a reaction deadline for the stop channel, not a benchmark
NARROW_RDDF = "1,34.8650000,-116.8900000,6,25\n2,34.8650000,-116.8878127,6,25\n"  # 200 m due east, 3.7 m wide


class Stand:
    """The test's side of the bus: INS stand-in, planner stand-in, recorder of commands."""

    def __init__(self, bus_url: str, key_file: FilePath, scenario: FilePath) -> None:
        self.listener = Listener(bus_url, key_file, source_id=920)
        self.bus = self.listener.bus
        self.listener.every(0.2, self.send_path)
        self.route = load_scenario(scenario).route
        self.truth: SimTruth | None = None
        self.commands: list[tuple[float, ActuatorCommand]] = []  # (monotonic arrival, command)
        self.cross_track: list[float] = []
        self.publish_path = True
        self._hint = 0
        self.bus.subscribe(channels.SIM_TRUTH, self.on_truth)
        self.bus.subscribe(channels.ACTUATOR_COMMAND, lambda msg, _env: self.commands.append((time.monotonic(), msg)))

    def on_truth(self, truth: SimTruth, envelope: Envelope) -> None:
        self.truth = truth
        v = truth.speed_mps
        state = VehicleState(
            truth.east_m,
            truth.north_m,
            0.0,
            truth.yaw_rad,
            v,
            v * math.cos(truth.yaw_rad),
            v * math.sin(truth.yaw_rad),
            truth.yaw_rate_radps,
            (0.0,) * 25,
            int(NavQuality.DGPS),
        )
        self.bus.publish(channels.VEHICLE_STATE, state, t_meas_ns=envelope.t_meas_ns)
        error, self._hint = signed_distance(
            self.route.east_m, self.route.north_m, truth.east_m, truth.north_m, self._hint
        )
        self.cross_track.append(error)

    def path(self) -> Path:
        """The course from just behind the vehicle to PATH_AHEAD_M ahead, as a planner would send it."""
        r = self.route
        i = self._hint
        lo, hi = max(0, i - 5), min(len(r.s_m), i + PATH_AHEAD_M)
        speeds = np.minimum(r.speed_mps[lo:hi], PATH_SPEED_MPS)
        points = tuple(
            PathPoint(float(e), float(n), float(s))
            for e, n, s in zip(r.east_m[lo:hi], r.north_m[lo:hi], speeds, strict=True)
        )
        return Path(1, points, False)

    def send_path(self) -> None:
        if self.publish_path:
            self.bus.publish(channels.PATH, self.path())

    def run_until(self, done: Callable[[], bool], timeout_s: float) -> bool:
        return self.listener.wait_until(done, timeout_s)

    def speed(self) -> float:
        return self.truth.speed_mps if self.truth else 0.0

    def progress(self) -> float:
        return self.truth.progress_m if self.truth else 0.0


def test_control_drives_the_simulated_vehicle_and_stops_it_when_told_or_blind(
    bus_url: str, key_file: FilePath, processes: Processes, scenario: FilePath
) -> None:
    processes.module("time_service")
    processes.module("sim", "--set", f"scenario={scenario}")
    processes.module("control", "--set", "path_max_age_s=0.5", "--set", "state_max_age_s=0.2")
    stand = Stand(bus_url, key_file, scenario)
    try:
        # 1. It drives and follows the course through the bend.
        assert stand.run_until(lambda: stand.progress() >= 50.0, 30.0), processes.log("control") + processes.log("sim")
        driving = [cmd for _t, cmd in stand.commands[-50:]]
        assert any(cmd.throttle > 0.0 for cmd in driving) and all(cmd.stop_reason == "" for cmd in driving)
        assert stand.speed() > 3.0
        # Within 0.5 m of the course even through the sharp 48 degree RDDF corner (0.3 m in process).
        assert max(abs(e) for e in stand.cross_track) < 0.5

        # 2. The planner falls silent: braked to a stop, and the commands say why.
        stand.publish_path = False
        silent_at = len(stand.commands)
        assert stand.run_until(lambda: stand.speed() == 0.0, 10.0), processes.log("control")
        after = [cmd for _t, cmd in stand.commands[silent_at:]]
        assert after[-1].brake == 1.0 and after[-1].throttle == 0.0
        assert after[-1].stop_reason.startswith("PATH stale"), after[-1]
        stopped_at = stand.progress()
        assert stand.run_until(lambda: False, 1.0) is False
        assert stand.speed() == 0.0 and stand.progress() == pytest.approx(stopped_at, abs=0.01)

        # 3. The path comes back and it drives on.
        stand.publish_path = True
        assert stand.run_until(lambda: stand.speed() > 2.0, 10.0), processes.log("control")

        # 4. E-stop: the braking command follows at once, and the vehicle stays stopped.
        first_estop = len(stand.commands)
        sent = time.monotonic()
        stand.bus.publish(channels.STOP, StopCommand(int(StopMode.ESTOP), "test e-stop"))

        def estop_seen() -> bool:
            return any(cmd.stop_reason.startswith("estop") for _t, cmd in stand.commands[first_estop:])

        assert stand.run_until(estop_seen, 2.0), processes.log("control")
        arrival, first = next(
            (t, cmd) for t, cmd in stand.commands[first_estop:] if cmd.stop_reason.startswith("estop")
        )
        assert (first.throttle, first.brake) == (0.0, 1.0)
        assert arrival - sent < ESTOP_DEADLINE_S
        stand.bus.publish(channels.STOP, StopCommand(int(StopMode.RUN), "try to resume"))
        assert stand.run_until(lambda: stand.speed() == 0.0, 10.0)
        assert stand.run_until(lambda: False, 1.0) is False  # fresh path and state, RUN sent: still stopped
        latest = [cmd for _t, cmd in stand.commands[-20:]]
        assert all(cmd.brake == 1.0 and cmd.stop_reason == "estop: test e-stop" for cmd in latest)
        assert stand.speed() == 0.0
    finally:
        stand.listener.close()


class Astray(Stand):
    """A planner stand-in whose path leaves the corridor: straight on at 3 degrees left of the course."""

    def path(self) -> Path:
        angle, speed = math.radians(3.0), 5.0
        return Path(2, tuple(PathPoint(s * math.cos(angle), s * math.sin(angle), speed) for s in range(-2, 80)), False)


def test_control_stops_the_vehicle_inside_the_corridor_when_its_path_leads_out(
    bus_url: str, key_file: FilePath, processes: Processes, tmp_path: FilePath
) -> None:
    (tmp_path / "course.rddf").write_text(NARROW_RDDF)
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(SCENARIO)
    processes.module("time_service")
    processes.module("sim", "--set", f"scenario={scenario}")
    processes.module("control", "--set", f"course={tmp_path / 'course.rddf'}")
    stand = Astray(bus_url, key_file, scenario)
    events: list[HealthEvent] = []
    stand.bus.subscribe(channels.HEALTH, lambda msg, _env: events.append(msg))
    try:

        def stopped_at_the_edge() -> bool:
            last = stand.commands[-1][1] if stand.commands else None
            return last is not None and last.stop_reason.startswith("corridor edge") and stand.speed() == 0.0

        assert stand.run_until(stopped_at_the_edge, 30.0), processes.log("control") + processes.log("sim")
        assert stand.truth is not None and stand.truth.corridor_exits == 0
        assert stand.progress() > 10.0  # it drove before it stopped
        assert [e.code for e in events if e.module == "control" and e.code == "corridor_edge"] == ["corridor_edge"]
    finally:
        stand.listener.close()
