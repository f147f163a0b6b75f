"""The control process over an in-process bus with a hand-set clock: fail-safe, stop channel."""

from __future__ import annotations

import uuid
from dataclasses import dataclass, field
from pathlib import Path as FilePath
from typing import Any

import numpy as np
import pytest

from brain.course_config import load_course
from modules.control.module import Control, ControlConfig
from protocol import channels
from protocol.auth import Keyring
from protocol.messages import (
    ActuatorCommand,
    HealthEvent,
    NavQuality,
    Path,
    PathPoint,
    Severity,
    StopCommand,
    StopMode,
    VehicleState,
)
from protocol.transport import MemTransport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import ManualClock
from rascal.runtime.config import ConfigError, build_config
from rascal.runtime.module import Runtime

TICK_NS = 20_000_000
PATH = Path(7, tuple(PathPoint(float(x), 0.0, 5.0) for x in range(0, 60)), False)
NARROW_RDDF = "1,34.8650000,-116.8900000,6,25\n2,34.8650000,-116.8897266,6,25\n"  # 25 m due east, 3.7 m wide


def nav_state(
    east_m: float, speed_mps: float = 2.0, quality: NavQuality = NavQuality.DGPS, north_m: float = 0.3
) -> VehicleState:
    return VehicleState(east_m, north_m, 0.0, 0.0, speed_mps, speed_mps, 0.0, 0.0, (0.0,) * 25, int(quality))


@dataclass
class Harness:
    control: Control
    clock: ManualClock
    feeder: Bus
    commands: list[ActuatorCommand] = field(default_factory=list)
    health: list[HealthEvent] = field(default_factory=list)
    listener: Bus | None = None

    def tick(self, state: VehicleState | None = None, path: Path | None = None) -> ActuatorCommand:
        """Advance 20 ms, publish what is given, let control receive it and run one tick."""
        self.clock.advance(TICK_NS)
        if state is not None:
            self.feeder.publish(channels.VEHICLE_STATE, state)
        if path is not None:
            self.feeder.publish(channels.PATH, path)
        self.control.bus.poll()
        self.control.tick()
        return self.drain()[-1]

    def drain(self) -> list[ActuatorCommand]:
        before = len(self.commands)
        assert self.listener is not None
        self.listener.poll()
        return self.commands[before:]

    def events(self, code: str) -> list[HealthEvent]:
        self.drain()
        return [event for event in self.health if event.code == code]

    def drive(self, ticks: int, east_m: float = 5.0) -> ActuatorCommand:
        out = None
        for k in range(ticks):
            out = self.tick(nav_state(east_m + 0.04 * k), PATH if k % 10 == 0 else None)
        assert out is not None
        return out


def make(**config: Any) -> Harness:
    hub, keyring, clock = uuid.uuid4().hex, Keyring.generate(), ManualClock()
    runtime = Runtime(Bus(MemTransport(hub), 40, keyring, clock), clock)
    control = Control(build_config(ControlConfig, config), runtime)
    control.on_start()
    harness = Harness(control, clock, Bus(MemTransport(hub), 20, keyring, clock))
    listener = Bus(MemTransport(hub), 99, keyring, clock)
    listener.subscribe(channels.ACTUATOR_COMMAND, lambda msg, _env: harness.commands.append(msg))
    listener.subscribe(channels.HEALTH, lambda msg, _env: harness.health.append(msg))
    harness.listener = listener
    return harness


def operator(harness: Harness, mode: int, reason: str) -> list[ActuatorCommand]:
    """Publish a StopCommand and let control receive it WITHOUT running a tick."""
    harness.feeder.publish(channels.STOP, StopCommand(mode, reason))
    harness.control.bus.poll()
    return harness.drain()


def test_without_inputs_it_brakes_and_says_what_is_missing() -> None:
    h = make()
    outs = [h.tick() for _ in range(10)]
    assert all((o.throttle, o.brake) == (0.0, 1.0) for o in outs)
    assert outs[-1].stop_reason == "VEHICLE_STATE missing; PATH missing"
    assert len(h.events("control_failsafe")) == 1
    assert (
        h.control.status_detail() == "stanley failsafe: steer +0.000 rad, sent 10; VEHICLE_STATE missing; PATH missing"
    )


def test_with_fresh_inputs_it_drives_and_reports_leaving_the_failsafe_once() -> None:
    h = make()
    h.tick()
    out = h.drive(30)
    assert out.throttle > 0.0 and out.brake == 0.0 and out.stop_reason == ""
    assert out.steering_rad < 0.0  # 0.3 m left of the path
    assert len(h.events("control_resumed")) == 1
    detail = h.control.status_detail()
    assert detail.startswith("stanley drive: cte +0.") and "speed err +" in detail


def test_a_stale_path_brakes_once_its_max_age_has_passed() -> None:
    h = make(path_max_age_s=0.5)
    h.drive(20)
    outs = [h.tick(nav_state(6.0 + 0.04 * k)) for k in range(40)]  # 0.8 s of state without any path
    driving = [o for o in outs if o.brake == 0.0]
    braking = [o for o in outs if o.brake == 1.0]
    assert driving and braking and outs[-1].brake == 1.0 and outs[-1].throttle == 0.0
    # PATH was last published 9 ticks before these: fresh while its age is <= 0.5 s (25 ticks).
    assert len(driving) == 25 - 9
    assert outs[-1].stop_reason.startswith("PATH stale (")
    assert outs[-1].steering_rad == driving[-1].steering_rad  # steering held
    assert len(h.events("control_failsafe")) == 1
    h.drive(5)
    assert len(h.events("control_resumed")) == 1


def test_a_stale_vehicle_state_brakes() -> None:
    h = make(state_max_age_s=0.2)
    h.drive(20)
    outs = [h.tick(None, PATH) for _ in range(15)]  # 0.3 s without state
    assert outs[5].brake == 0.0  # 0.12 s old: still fresh
    assert outs[-1].brake == 1.0 and outs[-1].stop_reason.startswith("VEHICLE_STATE stale")


def test_an_invalid_navigation_solution_brakes() -> None:
    h = make()
    out = h.tick(nav_state(5.0, quality=NavQuality.INVALID), PATH)
    assert out.brake == 1.0 and "invalid" in out.stop_reason


def test_an_unusable_path_brakes_and_names_the_path() -> None:
    h = make()
    h.drive(5)
    bad = Path(8, (PathPoint(5.0, 0.0, 3.0),), False)
    out = h.tick(nav_state(5.2), bad)
    assert out.brake == 1.0 and out.stop_reason.startswith("PATH 8 unusable: path needs at least 2")
    assert h.tick(nav_state(5.2), PATH).brake == 0.0  # a good path again


def test_pause_brakes_inside_the_handler_and_run_resumes() -> None:
    h = make()
    h.drive(20)
    immediate = operator(h, StopMode.PAUSE, "operator")
    assert len(immediate) == 1  # published by the handler, before any tick
    assert (immediate[0].throttle, immediate[0].brake) == (0.0, 1.0)
    assert immediate[0].stop_reason == "pause: operator"
    assert all(o.brake == 1.0 for o in (h.tick(nav_state(6.0), PATH) for _ in range(20)))
    operator(h, StopMode.RUN, "go")
    assert h.tick(nav_state(6.0, speed_mps=0.0), PATH).throttle > 0.0


def test_estop_brakes_at_once_and_stays_stopped_until_restart() -> None:
    h = make()
    h.drive(20)
    immediate = operator(h, StopMode.ESTOP, "red button")
    assert len(immediate) == 1 and immediate[0].brake == 1.0 and immediate[0].stop_reason == "estop: red button"
    assert operator(h, StopMode.RUN, "go") == []
    assert operator(h, StopMode.PAUSE, "pause") == []
    outs = [h.tick(nav_state(6.0, speed_mps=0.0), PATH) for _ in range(20)]
    assert all((o.throttle, o.brake) == (0.0, 1.0) and o.stop_reason == "estop: red button" for o in outs)
    assert [e.severity for e in h.events("estop")] == [3]


def test_an_unknown_stop_mode_is_held_as_a_pause() -> None:
    h = make()
    h.drive(5)
    immediate = operator(h, 9, "garbled")
    assert immediate[0].brake == 1.0 and immediate[0].stop_reason.startswith("pause")
    assert len(h.events("stop_unknown")) == 1


def test_the_pd_law_is_selectable() -> None:
    h = make(controller={"law": "pd"})
    out = h.drive(30)
    assert out.steering_rad < 0.0 and out.throttle > 0.0
    assert h.control.status_detail().startswith("pd drive")


def test_stopping_the_process_leaves_the_vehicle_braked() -> None:
    h = make()
    h.drive(10)
    h.control.on_stop()
    last = h.drain()[-1]
    assert (last.throttle, last.brake) == (0.0, 1.0) and last.stop_reason == "control stopping"


def test_with_the_course_it_brakes_short_of_the_corridor_edge_and_reports_each_stop_once(tmp_path: FilePath) -> None:
    rddf = tmp_path / "course.rddf"
    rddf.write_text(NARROW_RDDF)
    end_m = float(load_course(rddf).east_m[-1])  # PATH runs on past the corridor's end

    def at(east_m: float, speed_mps: float = 2.0) -> VehicleState:
        return nav_state(east_m, speed_mps, north_m=0.0)

    there, back = np.arange(5.0, end_m - 1.0, 0.1), np.arange(end_m - 1.0, 5.0, -0.1)
    free = make()
    assert all(free.tick(at(x), PATH).throttle > 0.0 for x in there)  # without the course: on it drives
    h = make(course=str(rddf))
    outs = [h.tick(at(x), PATH) for x in there]
    assert outs[0].throttle > 0.0 and outs[-1].brake == 1.0 and outs[-1].stop_reason.startswith("corridor edge ")
    assert "; corridor edge " in h.control.status_detail()
    # Standing with its front corners 0.3 m inside the corridor's rounded end: its first half metre would cross it.
    stands = [h.tick(at(end_m - 0.3, speed_mps=0.0), PATH) for _ in range(25)]
    assert all((o.throttle, o.brake) == (0.0, 1.0) and o.stop_reason.startswith("corridor edge") for o in stands)
    assert [e.severity for e in h.events("corridor_edge")] == [int(Severity.WARNING)]  # once for the whole stop
    for x in back:  # back where the footprint keeps its margin (as reversing would): that stop is over
        h.tick(at(x), PATH)
    assert h.control.controller.edge is not None and h.control.controller.edge.clear
    for x in there:
        h.tick(at(x), PATH)
    assert len(h.events("corridor_edge")) == 2


@pytest.mark.parametrize(
    ("config", "name"),
    [
        ({"controller": {"law": "bang_bang"}}, "bang_bang"),
        ({"rate_hz": 0.0}, "rate_hz"),
        ({"path_max_age_s": -1.0}, "path_max_age_s"),
        ({"controller": {"stanley": {"gain": 0.0}}}, r"control\.controller\.stanley: Stanley gains"),
        ({"guard": {"horizon_s": 0.0}}, r"control\.guard: corridor guard horizon_s"),
        ({"vehicle": {"wheelbase_m": 0.0}}, r"control\.vehicle: vehicle\.wheelbase_m"),
    ],
)
def test_bad_configuration_is_refused_by_name(config: dict[str, Any], name: str) -> None:
    with pytest.raises(ConfigError, match=name):
        build_config(ControlConfig, config, "control")
