"""The brain in degraded modes, as processes on the signed loopback bus: simulator, navigation
sensors, four lidars, INS, brain and control drive a straight course while the test plays a live
ESVS that sees nothing (an empty ObstacleList at 10 Hz). Then one fault each: the lidars fall
silent (RASCAL's 2005 failure), every obstacle sensor dies, or the navigation process dies. Each
test measures the time from the fault to the reaction in shared time (message stamps) and prints it.

The deadlines asserted are reaction deadlines derived from the design's own bounds (an input's
max age plus one planning or control period, plus slack for ten processes on a shared two-core
machine), not benchmarks: a stack that misses one has not noticed its fault in time.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from brain.health import HealthParams, stopping_speed_mps
from protocol import channels
from protocol.codec import Envelope
from protocol.messages import ActuatorCommand, Frame, HealthEvent, ModuleStatus, ObstacleList, Sensor, SimTruth
from protocol.messages import Path as PathMessage
from tests.conftest import Processes
from tests.integration.listener import Listener

pytestmark = pytest.mark.slow

# About 400 m due east with a 30 mph (13.4 m/s) limit and a 40 ft boundary: faster than the
# stereo-only cap, so the cap visibly lowers the planned speeds. Nothing stands on it.
RDDF = "1,34.8650000,-116.8900000,40,30\n2,34.8650000,-116.8856000,40,30\n"
SCENARIO = """
[scenario]
rddf = "course.rddf"
seed = 5
"""
LIDAR_SILENCE = """
[[fault]]
sensors = ["lidars"]
kind = "silence"
start_s = {start_s}
"""
LIDARS = {"lidar_h_left": 21, "lidar_h_right": 22, "lidar_v_left": 23, "lidar_v_right": 24}
# Every process but the simulator, by the name its heartbeat carries.
BEFORE_SIM = frozenset({"time_service", "nav_sensors", *LIDARS, "ins", "brain", "control"})

PARAMS = HealthParams()  # the brain's defaults, which it runs with here
STEREO_CAP_MPS = stopping_speed_mps(PARAMS.stereo_range_m, PARAMS)  # 10 m/s
PLAN_PERIOD_S = 0.1  # brain plan_rate_hz 10
CONTROL_PERIOD_S = 0.02  # control rate_hz 50
STATE_MAX_AGE_S = 0.2  # control state_max_age_s
SCHEDULING_SLACK_S = 0.05  # how late a periodic task may run with ten processes on two busy cores
ESVS_PERIOD_S = 0.1
DRIVING_MPS = 3.0
STOPPED_MPS = 0.3
FAULT_AT_S = 16.0  # scenario time of the lidar silence: well under way, most of the course ahead
START_TIMEOUT_S = 60.0
NS = 1e9


@dataclass
class Stack:
    """What the test hears of the running stack (each message with its envelope), and its ESVS."""

    listener: Listener
    truth: list[tuple[Envelope, SimTruth]] = field(default_factory=list)
    events: list[tuple[Envelope, HealthEvent]] = field(default_factory=list)
    paths: list[tuple[Envelope, PathMessage]] = field(default_factory=list)
    commands: list[tuple[Envelope, ActuatorCommand]] = field(default_factory=list)
    heartbeats: set[str] = field(default_factory=set)
    esvs_live: bool = True
    esvs_last_ns: int = 0

    def wait(self, done: Callable[[], bool], timeout_s: float) -> bool:
        return self.listener.wait_until(done, timeout_s)

    def publish_esvs(self) -> None:
        """A live ESVS that sees nothing, stamped now like the real one's frames (once this
        node's clock follows the time service)."""
        if self.esvs_live and self.listener.clock.synced:
            now = self.listener.clock.now_ns()
            nothing = ObstacleList(int(Sensor.ESVS), int(Frame.VEHICLE), ())
            self.listener.bus.publish(channels.OBSTACLES_ESVS, nothing, t_meas_ns=now)
            self.esvs_last_ns = now

    def now(self) -> SimTruth:
        return self.truth[-1][1]

    def scenario_time_s(self) -> float:
        return self.truth[-1][1].scenario_time_s if self.truth else -1.0

    def truth_at_scenario_time(self, t_s: float) -> tuple[Envelope, SimTruth] | None:
        """The first truth sample at or after scenario time ``t_s``: a scheduled fault's onset."""
        return next(((env, truth) for env, truth in self.truth if truth.scenario_time_s >= t_s), None)

    def wait_for_scenario_time(self, t_s: float) -> tuple[Envelope, SimTruth]:
        """Wait (bounded) for the first truth sample at scenario time ``t_s`` and return it."""
        assert self.scenario_time_s() < t_s - 2.0, "the stack started too late for the fault schedule"
        reached = self.wait(lambda: self.truth_at_scenario_time(t_s) is not None, t_s + 10.0)
        sample = self.truth_at_scenario_time(t_s)
        assert reached and sample is not None, f"scenario time stuck at {self.scenario_time_s():.1f} s"
        return sample

    def truth_at(self, t_ns: int) -> SimTruth:
        return next(truth for env, truth in self.truth if env.t_meas_ns >= t_ns)

    def stopped_since(self, t_ns: int) -> Envelope | None:
        return next((env for env, truth in self.truth if env.t_meas_ns >= t_ns and truth.speed_mps < STOPPED_MPS), None)

    def modes(self) -> list[tuple[Envelope, str]]:
        """The brain's drive_mode events, as (envelope, text)."""
        return [(env, e.text) for env, e in self.events if e.module == "brain" and e.code == "drive_mode"]

    def entered(self, mode: str, since_ns: int) -> Envelope | None:
        """The brain's first drive_mode event into ``mode`` stamped at or after ``since_ns``."""
        return next((env for env, text in self.modes() if f"-> {mode}:" in text and env.t_meas_ns >= since_ns), None)

    def mode_before(self, t_ns: int) -> str:
        texts = [text for env, text in self.modes() if env.t_meas_ns < t_ns]
        return texts[-1] if texts else ""

    def paths_after(self, env: Envelope) -> list[PathMessage]:
        """Paths the brain published after ``env`` (its own, earlier message: same clock)."""
        return [path for path_env, path in self.paths if path_env.t_pub_ns > env.t_pub_ns]

    def report(self, processes: Processes) -> str:
        """For a failing assertion: the health events and the ends of the logs that matter."""
        heard = [f"{env.t_meas_ns / NS:.3f} {e.module} {e.code}: {e.text}" for env, e in self.events]
        speeds = [f"{t.scenario_time_s:.1f}s {t.speed_mps:.1f}m/s" for _env, t in self.truth[::100]]
        logs = [f"--- {name}\n{processes.log(name)[-1500:]}" for name in ("brain", "control", "ins", "sim")]
        return "\n".join(["health events:", *heard, "truth: " + ", ".join(speeds), *logs])


@contextmanager
def driving_stack(
    tmp_path: Path, bus_url: str, key_file: Path, processes: Processes, faults: str = ""
) -> Iterator[Stack]:
    """Start the stack on the straight course with ``faults`` in its scenario and yield once the
    vehicle drives (truth speed above 3 m/s). The simulator starts once every other process
    beats, so scenario time (on which faults run) does not count their start-up."""
    (tmp_path / "course.rddf").write_text(RDDF)
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(SCENARIO + faults)
    course = f"course={tmp_path / 'course.rddf'}"
    processes.module("time_service")
    processes.module("nav_sensors", "--set", f"scenario={scenario}")
    for name, source_id in LIDARS.items():
        set_args = ("--set", f"sensor={name}", "--set", f"scenario={scenario}")
        processes.module("lidar", "--source-id", str(source_id), *set_args, label=name)
    processes.module("ins", "--set", course)
    processes.module("brain", "--set", course, "--set", f"sensors={','.join((*LIDARS, 'esvs'))}")
    processes.module("control")
    stack = Stack(Listener(bus_url, key_file, source_id=916))
    listener = stack.listener

    def on_status(status: ModuleStatus, _env: Envelope) -> None:
        stack.heartbeats.add(status.module)

    listener.subscribe(channels.MODULE_STATUS, on_status)
    listener.subscribe(channels.SIM_TRUTH, lambda msg, env: stack.truth.append((env, msg)))
    listener.subscribe(channels.HEALTH, lambda msg, env: stack.events.append((env, msg)))
    listener.subscribe(channels.PATH, lambda msg, env: stack.paths.append((env, msg)))
    listener.subscribe(channels.ACTUATOR_COMMAND, lambda msg, env: stack.commands.append((env, msg)))
    listener.every(ESVS_PERIOD_S, stack.publish_esvs)
    try:
        started = time.monotonic()
        up = stack.wait(lambda: stack.heartbeats >= BEFORE_SIM, START_TIMEOUT_S)
        assert up, f"no heartbeat from {sorted(BEFORE_SIM - stack.heartbeats)}"
        processes.module("sim", "--set", f"scenario={scenario}")
        driving = stack.wait(lambda: bool(stack.truth) and stack.now().speed_mps > DRIVING_MPS, START_TIMEOUT_S)
        assert driving, f"the vehicle never drove\n{stack.report(processes)}"
        print(
            f"\nprocesses up after {time.monotonic() - started:.1f} s; "
            f"driving at scenario time {stack.scenario_time_s():.1f} s"
        )
        yield stack
    finally:
        listener.close()


def fastest(path: PathMessage) -> float:
    return max((point.speed_mps for point in path.points), default=0.0)


def test_lidar_silence_is_stereo_only_below_the_stereo_cap_and_keeps_driving(
    bus_url: str, key_file: Path, processes: Processes, tmp_path: Path
) -> None:
    faults = LIDAR_SILENCE.format(start_s=FAULT_AT_S)
    with driving_stack(tmp_path, bus_url, key_file, processes, faults) as stack:
        onset_env, onset = stack.wait_for_scenario_time(FAULT_AT_S)
        event = None

        def reacted() -> bool:
            nonlocal event
            event = stack.entered("stereo_only", onset_env.t_meas_ns)
            return event is not None

        assert stack.wait(reacted, 5.0), stack.report(processes)
        # Drive on stereo alone for a while: the speed controller follows the cap down.
        settled_from_s = FAULT_AT_S + 3.0
        assert stack.wait(lambda: stack.scenario_time_s() >= settled_from_s + 2.0, 10.0), stack.report(processes)
    assert event is not None
    reaction_s = (event.t_meas_ns - onset_env.t_meas_ns) / NS
    print(f"lidars silent at {onset.speed_mps:.1f} m/s: '-> stereo_only' after {reaction_s * 1e3:.0f} ms")
    modes = [f"{env.t_meas_ns / NS:.2f} {text}" for env, text in stack.modes()]
    assert "-> normal:" in stack.mode_before(onset_env.t_meas_ns), f"not in normal mode at the fault: {modes}"
    # Reaction deadline, not a benchmark: the last scan is stamped before the onset, the lidars
    # are dead one max age later, and the next planning cycle reports it.
    assert 0.0 < reaction_s <= PARAMS.lidar_max_age_s + PLAN_PERIOD_S + SCHEDULING_SLACK_S
    before = [path for env, path in stack.paths if env.t_pub_ns < onset_env.t_meas_ns]
    after = stack.paths_after(event)
    assert max(fastest(path) for path in before) > STEREO_CAP_MPS, "the paths went faster than the cap before"
    assert after and max(fastest(path) for path in after) <= STEREO_CAP_MPS + 1e-6
    later = [text for env, text in stack.modes() if env.t_meas_ns > event.t_meas_ns]
    assert not later, f"stereo_only holds while the ESVS lives: {modes}"
    settled = [truth.speed_mps for _env, truth in stack.truth if truth.scenario_time_s >= settled_from_s]
    print(f"on stereo alone: {min(settled):.1f}..{max(settled):.1f} m/s (cap {STEREO_CAP_MPS:.1f} m/s)")
    assert min(settled) > DRIVING_MPS, "still driving"
    assert max(settled) <= STEREO_CAP_MPS + 0.3  # below the cap, but for the PI controller's small overshoot


def test_losing_every_obstacle_sensor_is_blind_and_stops(
    bus_url: str, key_file: Path, processes: Processes, tmp_path: Path
) -> None:
    faults = LIDAR_SILENCE.format(start_s=FAULT_AT_S)
    with driving_stack(tmp_path, bus_url, key_file, processes, faults) as stack:
        # The ESVS dies with the lidars: its stand-in stops the moment the test hears the onset.
        onset_env, onset = stack.wait_for_scenario_time(FAULT_AT_S)
        stack.esvs_live = False
        esvs_gap_s = (onset_env.t_meas_ns - stack.esvs_last_ns) / NS
        event = stopped = None

        def reacted() -> bool:
            nonlocal event, stopped
            event = stack.entered("blind", onset_env.t_meas_ns)
            stopped = stack.stopped_since(onset_env.t_meas_ns)
            return event is not None and stopped is not None

        assert stack.wait(reacted, 15.0), stack.report(processes)
        assert stack.wait(lambda: stack.truth[-1][0].t_meas_ns > stopped.t_meas_ns + int(1.0 * NS), 5.0)
    assert event is not None and stopped is not None
    reaction_s = (event.t_meas_ns - onset_env.t_meas_ns) / NS
    stop_s = (stopped.t_meas_ns - onset_env.t_meas_ns) / NS
    travel_m = stack.truth_at(stopped.t_meas_ns).progress_m - onset.progress_m
    print(
        f"all obstacle sensors lost at {onset.speed_mps:.1f} m/s (last ESVS {esvs_gap_s * 1e3:.0f} ms before): "
        f"'-> blind' after {reaction_s * 1e3:.0f} ms, stopped after {stop_s:.1f} s and {travel_m:.1f} m"
    )
    # Reaction deadline, not a benchmark: the ESVS, the longest-lived input (max age 0.5 s), was
    # last heard at the onset at the latest; then one planning cycle.
    assert 0.0 < reaction_s <= PARAMS.stereo_max_age_s + PLAN_PERIOD_S + SCHEDULING_SLACK_S
    after = stack.paths_after(event)
    assert after and all(point.speed_mps == 0.0 for path in after for point in path.points)
    # Stopping deadline, not a benchmark: the reaction, then braking at no less than the planner's
    # comfortable deceleration (full brake is three times that), plus 0.5 s of brake lag and creep.
    assert stop_s <= reaction_s + onset.speed_mps / PARAMS.braking_mps2 + 0.5
    still = [truth.speed_mps for env, truth in stack.truth if env.t_meas_ns >= stopped.t_meas_ns]
    assert max(still) < STOPPED_MPS, "and stays stopped"


def test_stale_navigation_is_nav_lost_and_control_brakes(
    bus_url: str, key_file: Path, processes: Processes, tmp_path: Path
) -> None:
    with driving_stack(tmp_path, bus_url, key_file, processes) as stack:
        assert stack.wait(lambda: stack.now().speed_mps > 2 * DRIVING_MPS, 20.0), stack.report(processes)
        speed = stack.now().speed_mps
        onset_ns = stack.listener.clock.now_ns()
        processes.children["ins"].kill()
        event = brake = stopped = None

        def reacted() -> bool:
            nonlocal event, brake, stopped
            event = stack.entered("nav_lost", onset_ns)
            brake = next(
                (
                    env
                    for env, command in stack.commands
                    if env.t_meas_ns >= onset_ns and command.brake >= 0.99 and "VEHICLE_STATE" in command.stop_reason
                ),
                None,
            )
            stopped = stack.stopped_since(onset_ns)
            return event is not None and brake is not None and stopped is not None

        assert stack.wait(reacted, 15.0), stack.report(processes)
    assert event is not None and brake is not None and stopped is not None
    nav_lost_s = (event.t_meas_ns - onset_ns) / NS
    brake_s = (brake.t_meas_ns - onset_ns) / NS
    stop_s = (stopped.t_meas_ns - onset_ns) / NS
    print(
        f"INS killed at {speed:.1f} m/s: '-> nav_lost' after {nav_lost_s * 1e3:.0f} ms, "
        f"control braking after {brake_s * 1e3:.0f} ms, stopped after {stop_s:.1f} s"
    )
    # Reaction deadlines, not benchmarks: the last state is stamped before the kill; each consumer
    # calls it stale one max age later, at its next cycle.
    assert 0.0 < nav_lost_s <= PARAMS.navigation_max_age_s + PLAN_PERIOD_S + SCHEDULING_SLACK_S
    assert 0.0 < brake_s <= STATE_MAX_AGE_S + CONTROL_PERIOD_S + SCHEDULING_SLACK_S
    assert stop_s <= brake_s + speed / PARAMS.braking_mps2 + 0.5  # as in the blind test
