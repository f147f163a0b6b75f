"""The whole stack under `rascal run` on a short test-written course, and what a test hears of it.

``drive(...)`` writes the course, the scenario and a deployment (every module of the closed loop,
each its own process on the test's private signed bus), starts `rascal run` on it, and yields a
:class:`Heard` that records the traffic a fault test judges: the simulator's truth, the brain's
paths and mode events, control's commands, heartbeats, stereo reports and GPS fixes. When the
``with`` block ends it waits (bounded) for the run to end by itself at the end of the course and
reads the run's ``summary.json`` (with the referee's drive measures) into ``Heard.summary``.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from modules.sim.lidar.process import SOURCE_IDS as LIDAR_SOURCE_IDS
from protocol import channels
from protocol.codec import Envelope
from protocol.messages import (
    ActuatorCommand,
    HealthEvent,
    ModuleStatus,
    ObstacleList,
    SimTruth,
    VehicleState,
)
from protocol.messages import Path as PathMessage
from tests.conftest import ROOT
from tests.integration.listener import Listener

NS = 1e9
LIDARS = LIDAR_SOURCE_IDS  # all five, as the default deployment has them
LIDAR_SETTINGS: dict[str, dict[str, Any]] = {"lidar_sweep": {"rate_hz": 37.5}}  # as in deploy/localhost.toml
LISTENER_SOURCE_ID = 914

# The closed loop, one table per process: {label: {key: value}} with "set" the config overrides.
# Each test's deployment is these, changed by its own overrides (None drops a module).
MODULES: dict[str, dict[str, Any]] = {
    "time_service": {},
    "sim": {},
    "nav_sensors": {},
    **{
        name: {"module": "lidar", "source_id": sid, "set": {"sensor": name, **LIDAR_SETTINGS.get(name, {})}}
        for name, sid in LIDARS.items()
    },
    "stereo_camera": {"set": {"ring_name": "{ring}"}},
    "esvs": {"set": {"ring_name": "{ring}"}},
    "ins": {},
    "brain": {},
    "control": {},
    "referee": {},
}


def rddf(points: list[tuple[float, float]], width_ft: float, speed_mph: float) -> str:
    """RDDF text for waypoints given as (lat, lon), one boundary width and speed limit throughout."""
    return "".join(
        f"{n},{lat:.7f},{lon:.7f},{width_ft:g},{speed_mph:g}\n" for n, (lat, lon) in enumerate(points, start=1)
    )


def scenario(seed: int, *tables: tuple[str, dict[str, Any]]) -> str:
    """Scenario TOML on ``course.rddf`` with road edges 3 m either side, then ``tables`` as
    (array name, table), e.g. ``rock(120.0, 0.8)`` or ``("fault", {...})``."""
    lines = ["[scenario]", 'rddf = "course.rddf"', f"seed = {seed}", "", "[road]", "half_width_m = 3.0"]
    for name, table in tables:
        lines += ["", f"[[{name}]]", *(f"{key} = {_toml_value(value)}" for key, value in table.items())]
    return "\n".join(lines) + "\n"


def rock(at_m: float, offset_m: float) -> tuple[str, dict[str, Any]]:
    """A rock on the route, ``offset_m`` left of the centreline: 1.2 m across, 1 m tall."""
    return "obstacle", {
        "name": "rock",
        "shape": "cylinder",
        "at_m": at_m,
        "offset_m": offset_m,
        "radius_m": 0.6,
        "height_m": 1.0,
    }


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + " }"
    return json.dumps(str(value))


def write_deployment(
    tmp_path: Path,
    bus_url: str,
    course: str,
    scenario_toml: str,
    overrides: dict[str, dict[str, Any] | None] | None = None,
    extra: str = "",
) -> Path:
    """The course (RDDF text), the scenario (its [scenario] table names ``course.rddf``) and a
    deployment of MODULES changed by ``overrides`` (a module's keys replace, its "set" merges;
    None drops the module), with ``extra`` TOML appended (e.g. link faults)."""
    (tmp_path / "course.rddf").write_text(course)
    (tmp_path / "scenario.toml").write_text(scenario_toml)
    ring = f"rascal-test-{os.getpid()}-{tmp_path.name[-8:]}"
    lines = [
        "[deployment]",
        'name = "short"',
        f'bus = "{bus_url}"',
        'scenario = "scenario.toml"',
        'course = "course.rddf"',
    ]
    for label, table in {**MODULES, **(overrides or {})}.items():
        if table is None:
            continue
        merged = {**MODULES.get(label, {}), **table}
        settings = {**MODULES.get(label, {}).get("set", {}), **table.get("set", {})}
        if settings:
            merged["set"] = {k: v.format(ring=ring) if isinstance(v, str) else v for k, v in settings.items()}
        lines.append(f"[modules.{label}]")
        lines += [f"{key} = {_toml_value(value)}" for key, value in merged.items()]
    deploy = tmp_path / "deploy.toml"
    deploy.write_text("\n".join(lines) + "\n" + extra)
    return deploy


@dataclass
class Heard:
    """What the test hears of the running stack; each message with its envelope, and how many
    messages each source had delivered on each channel heard."""

    listener: Listener
    log: Path
    truth: list[tuple[Envelope, SimTruth]] = field(default_factory=list)
    paths: list[tuple[Envelope, PathMessage]] = field(default_factory=list)
    events: list[tuple[Envelope, HealthEvent]] = field(default_factory=list)
    commands: list[tuple[float, Envelope, ActuatorCommand]] = field(default_factory=list)  # (arrival, ...)
    statuses: list[tuple[Envelope, ModuleStatus]] = field(default_factory=list)
    stereo: list[tuple[Envelope, ObstacleList]] = field(default_factory=list)
    gps: list[Envelope] = field(default_factory=list)
    nav_quality: list[tuple[int, int]] = field(default_factory=list)  # (t_meas_ns, NavQuality)
    delivered: Counter[tuple[int, str]] = field(default_factory=Counter)  # (source id, channel)
    summary: dict[str, Any] = field(default_factory=dict)
    run: subprocess.Popen[bytes] | None = None  # `rascal run`: a test may end it early (SIGTERM)
    run_dir: Path | None = None  # the run's directory, once it has ended

    def subscribe(self) -> None:
        def on(channel: str, handler: Callable[[Any, Envelope], None]) -> None:
            def counted(msg: Any, env: Envelope) -> None:
                self.delivered[(env.source_id, env.channel)] += 1
                handler(msg, env)

            self.listener.subscribe(channel, counted)

        on(channels.OBSTACLES_LIDAR, lambda _msg, _env: None)
        on(channels.SIM_TRUTH, lambda msg, env: self.truth.append((env, msg)))
        on(channels.PATH, lambda msg, env: self.paths.append((env, msg)))
        on(channels.HEALTH, lambda msg, env: self.events.append((env, msg)))
        on(channels.ACTUATOR_COMMAND, lambda msg, env: self.commands.append((time.monotonic(), env, msg)))
        on(channels.MODULE_STATUS, lambda msg, env: self.statuses.append((env, msg)))
        on(channels.OBSTACLES_ESVS, lambda msg, env: self.stereo.append((env, msg)))
        on(channels.GPS, lambda _msg, env: self.gps.append(env))
        on(channels.VEHICLE_STATE, self._on_state)

    def _on_state(self, state: VehicleState, env: Envelope) -> None:
        if not self.nav_quality or self.nav_quality[-1][1] != state.quality:
            self.nav_quality.append((env.t_meas_ns, state.quality))

    def wait(self, done: Callable[[], bool], timeout_s: float) -> bool:
        return self.listener.wait_until(done, timeout_s)

    def progress_m(self) -> float:
        return self.truth[-1][1].progress_m if self.truth else 0.0

    def wait_for_progress(self, metres: float, timeout_s: float) -> tuple[Envelope, SimTruth]:
        """Wait (bounded) until the vehicle has driven ``metres`` along the course; the first such sample."""
        assert self.wait(lambda: self.progress_m() >= metres, timeout_s), self.tail(
            f"stuck at {self.progress_m():.0f} m"
        )
        return next((env, truth) for env, truth in self.truth if truth.progress_m >= metres)

    def modes(self) -> list[tuple[Envelope, str]]:
        """The brain's drive_mode events, as (envelope, text such as 'normal -> stereo_only: ...')."""
        return [(env, e.text) for env, e in self.events if e.module == "brain" and e.code == "drive_mode"]

    def entered(self, mode: str, since_ns: int) -> Envelope | None:
        """The brain's first drive_mode event into ``mode`` stamped at or after ``since_ns``."""
        return next((env for env, text in self.modes() if f"-> {mode}:" in text and env.t_meas_ns >= since_ns), None)

    def worker_pid(self) -> int:
        """The ESVS's newest vision worker, from its worker_started events."""
        started = [e.text for _env, e in self.events if e.module == "esvs" and e.code == "worker_started"]
        assert started, "the vision worker never started"
        match = re.search(r"pid=(\d+)", started[-1])
        assert match is not None, started[-1]
        return int(match.group(1))

    def worker_restarts(self) -> list[tuple[Envelope, HealthEvent]]:
        return [(env, e) for env, e in self.events if e.module == "esvs" and e.code == "worker_restart"]

    def tail(self, why: str = "") -> str:
        """For a failing assertion: why, the brain's modes and the end of the run's output."""
        modes = [f"{env.t_meas_ns / NS:.2f} {text}" for env, text in self.modes()]
        return "\n".join([why, "brain modes:", *modes, self.log.read_text()[-3000:]])

    @property
    def drive(self) -> dict[str, Any]:
        """The referee's measures of the finished drive."""
        return self.summary["drive"]


def rascal_run_command(deploy: Path, runs: Path, duration_s: float, *extra: str) -> list[str]:
    """`rascal run` on ``deploy`` for at most ``duration_s``, its run directory under ``runs``,
    without the report's images (no test but the wash test looks at them)."""
    command = [sys.executable, "-m", "rascal.cli", "run", str(deploy), "--duration", f"{duration_s:g}"]
    return [*command, "--runs-dir", str(runs), "--no-images", *extra]


@contextmanager
def drive(
    tmp_path: Path,
    bus_url: str,
    key_file: Path,
    deploy: Path,
    duration_s: float = 240.0,
    cpus: str | None = None,
    images: bool = False,
) -> Iterator[Heard]:
    """`rascal run` on ``deploy`` (on the CPUs ``cpus`` names only, if given); the ``with`` body
    runs while the stack drives, then the run is awaited (it ends at the end of the course, or
    after ``duration_s``) and its summary read. The report's images are drawn only with
    ``images`` (seconds a run that most tests do not look at)."""
    runs = tmp_path / "runs"
    log_path = tmp_path / "run.log"
    command = rascal_run_command(deploy, runs, duration_s, *(("--cpus", cpus) if cpus is not None else ()))
    if images:
        command.remove("--no-images")
    with log_path.open("wb") as log:
        supervisor = subprocess.Popen(command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    heard = Heard(Listener(bus_url, key_file, source_id=LISTENER_SOURCE_ID), log_path, run=supervisor)
    heard.subscribe()
    try:
        yield heard
        # Keep listening until the run ends by itself: what the test asserts on comes after.
        heard.wait(lambda: supervisor.poll() is not None, duration_s + 60.0)
    finally:
        heard.listener.close()
        if supervisor.poll() is None:
            supervisor.terminate()
        supervisor.wait(timeout=60)
    assert supervisor.returncode == 0, heard.tail("rascal run failed")
    (run_dir,) = runs.iterdir()
    heard.run_dir = run_dir
    heard.summary = json.loads((run_dir / "summary.json").read_text())
    print(json.dumps(heard.summary.get("drive")))


def max_gap_s(stamps_ns: list[int]) -> float:
    """The longest interval between consecutive stamps, in seconds (0 for fewer than two)."""
    return max((b - a for a, b in itertools.pairwise(stamps_ns)), default=0) / NS
