"""``rascal run [DEPLOY] [--host NAME]``: this host's part of a deployment, supervised and shown live.

Starts the host's modules (rascal/supervisor.py), follows the drive from the navigation
solution (course progress, speed) and every module's heartbeat, and ends when the vehicle has
reached the end of the course and stopped, after ``--duration``, or on Ctrl-C. Ending is
graceful: the vehicle is paused (StopCommand) and seen to stop before the modules are.
Everything goes to ``runs/<timestamp>/``: each module's log, the whole bus traffic as MCAP
(``run.mcap``, by a recorder process started first and stopped last) and ``summary.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from collections import Counter
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table

from brain.course_config import load_course
from brain.planning.frame import CorridorFrame
from protocol import channels
from protocol.auth import default_keyring, load_keyring
from protocol.codec import Envelope
from protocol.messages import HealthEvent, Severity, StopCommand, StopMode, VehicleState
from rascal.logread import RecordingError, read_metadata
from rascal.record_twins import add_json_twins
from rascal.recording import END_METADATA
from rascal.report import report_run
from rascal.runtime.bus import Bus
from rascal.runtime.clock import SharedClock
from rascal.runtime.cpu import CpuMeter
from rascal.runtime.deployment import (
    DEFAULT_DEPLOYMENT,
    LOCALHOST,
    Deployment,
    DeploymentError,
    ModuleSpec,
    load_deployment,
)
from rascal.runtime.module import Runtime
from rascal.supervisor import SUPERVISOR_SOURCE_ID, Child, Supervisor, module_state
from rascal.view.module import viewer_spec

VIEW_PERIOD_S = 0.5
# This close to the end of the course, and stopped, is finished. Control reads its target speed
# at least 2 m ahead and holds once that is below its stop speed, so it stops 2-3 m short of the
# end (measured 2.0-3.0 m); 3 m left runs that stopped at 3.0 m waiting for --duration.
FINISH_DISTANCE_M = 5.0
STOPPED_MPS = 0.3
SHUTDOWN_STOP_TIMEOUT_S = 5.0
RECENT_EVENTS = 6
RECORDER_SOURCE_ID = 8


class RunSupervisor(Supervisor):
    """The supervisor plus what a run needs: progress, the live view, the end, the summary."""

    def __init__(
        self,
        runtime: Runtime,
        deployment: Deployment,
        host: str,
        run_dir: Path,
        duration_s: float | None,
        console: Console,
        view_port: int | None = None,
    ) -> None:
        recorder = ModuleSpec(
            label="recorder",
            module="recorder",
            host=host,
            source_id=deployment.host_source_id(host, RECORDER_SOURCE_ID),
            heartbeat_timeout_s=5.0,
            settings={
                "out": str((run_dir / "run.mcap").resolve()),
                "info": f"deployment={deployment.name},host={host}",
                # JSON twins and foxglove channels are added after the run (rascal/record_twins.py),
                # which rewrites the file anyway: made live too, they would double the recorder's CPU.
                "json_channels": "false",
                "foxglove": "false",
                # The corridor is not on the bus: the course in the run metadata draws it for Foxglove.
                **({"course": str(deployment.course), "origin": deployment.origin} if deployment.course else {}),
            },
            entry="rascal.recording",
        )
        viewer = () if view_port is None else (viewer_spec(deployment, host, view_port),)
        super().__init__(runtime, deployment, host, run_dir, extra=(recorder, *viewer))
        self.run_dir = run_dir
        self.duration_s = duration_s
        self.console = console
        course = load_course(deployment.course, deployment.origin) if deployment.course else None
        self.frame = CorridorFrame(course.interpolate()) if course else None
        self.station_m: float | None = None
        self.state: VehicleState | None = None
        self.events: list[HealthEvent] = []
        self.finished = False
        self.started_s = time.monotonic()
        self.own_cpu = CpuMeter(children=False)  # over the whole run, for the summary
        self.live: Live | None = None

    def on_start(self) -> None:
        super().on_start()
        # The INS's 100 Hz does not wake the supervisor: the view reads the newest at its own rate.
        self.bus.subscribe(channels.VEHICLE_STATE, self.on_vehicle_state, wake=False)
        self.bus.subscribe(channels.HEALTH, lambda event, _env: self.events.append(event))
        self.every(VIEW_PERIOD_S, self.refresh, priority=1)
        # Drawn when the view changes (every VIEW_PERIOD_S), not by rich's own 4 Hz refresh thread.
        self.live = Live(self.view(), console=self.console, auto_refresh=False, transient=False)
        self.live.start()

    def on_vehicle_state(self, state: VehicleState, _envelope: Envelope) -> None:
        self.state = state  # located on the course at the view's rate, not the INS's 100 Hz

    def refresh(self) -> None:
        if self.frame is not None and self.state is not None:
            s, _ = self.frame.locate(self.state.east_m, self.state.north_m, self.station_m)
            self.station_m = float(s)
        if self.live is not None:
            self.live.update(self.view(), refresh=True)
        elapsed = time.monotonic() - self.started_s
        if self.duration_s is not None and elapsed >= self.duration_s:
            self.runtime.stop()
        if self.frame is not None and self.station_m is not None and self.state is not None:
            at_end = self.frame.length_m - self.station_m < FINISH_DISTANCE_M
            if at_end and abs(self.state.speed_mps) < STOPPED_MPS:
                self.finished = True
                self.runtime.stop()

    def on_stop(self) -> None:
        self._stop_vehicle()
        super().on_stop()
        if self.live is not None:
            self.live.update(self.view(), refresh=True)
            self.live.stop()
        summary = self.summary()
        drive = self.run_dir / "drive.json"  # the referee's measures, in simulated deployments
        if drive.exists():
            summary["drive"] = json.loads(drive.read_text())
        (self.run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
        self.console.print_json(data={k: summary[k] for k in ("finished", "elapsed_s", "drive") if k in summary})

    def _stop_vehicle(self) -> None:
        """Pause the vehicle and wait (bounded) until the navigation solution says it stopped."""
        if self.state is None:
            return
        deadline = time.monotonic() + SHUTDOWN_STOP_TIMEOUT_S
        pause = StopCommand(int(StopMode.PAUSE), "rascal run is shutting down")
        while time.monotonic() < deadline:
            self.bus.publish(channels.STOP, pause)
            self.bus.poll(0.1)
            if self.state is not None and abs(self.state.speed_mps) < STOPPED_MPS:
                return
        self.report(Severity.WARNING, "shutdown", "the vehicle did not report a stop before the modules were ended")

    # -- presentation -------------------------------------------------------------------------

    def progress_line(self) -> str:
        elapsed = time.monotonic() - self.started_s
        parts = [f"{self.deployment.name}: {elapsed:5.0f} s"]
        if self.state is not None:
            parts.append(f"speed {self.state.speed_mps:4.1f} m/s")
        if self.frame is not None and self.station_m is not None:
            share = 100.0 * max(0.0, self.station_m) / self.frame.length_m
            parts.append(f"course {share:5.1f} % ({self.station_m:.0f}/{self.frame.length_m:.0f} m)")
        now = [child.status.cpu_pct for child in self.children if child.status and child.status.cpu_pct >= 0]
        if now:
            parts.append(f"modules' CPU {sum(now):.0f} % of one core")
        return "   ".join(parts)

    def view(self) -> Group:
        modules = Table(title=self.progress_line(), title_justify="left", expand=False)
        for column in ("module", "state", "restarts", "uptime s", "cpu %", "jitter ms", "detail"):
            modules.add_column(column, justify="left" if column in ("module", "state", "detail") else "right")
        for child in self.children:
            status = child.status
            modules.add_row(
                child.spec.label,
                module_state(child),
                str(child.restarts),
                f"{status.uptime_s:.0f}" if status else "",
                _cpu_cell(child),
                f"{status.jitter_ns / 1e6:.1f}" if status else "",
                (status.detail if status else "")[:70],
            )
        recent = Table(title="recent health events", title_justify="left", show_header=False, expand=False)
        recent.add_column("event")
        for event in self.events[-RECENT_EVENTS:]:
            recent.add_row(f"{Severity(event.severity).name:8} {event.module}: {event.code} {event.text}"[:110])
        return Group(modules, recent)

    def summary(self) -> dict[str, Any]:
        elapsed = time.monotonic() - self.started_s
        cpu = {child.spec.label: child.cpu.mean_pct for child in self.children}
        own_cpu_pct = self.own_cpu.sample()
        return {
            "deployment": self.deployment.name,
            "deployment_file": str(self.deployment.path.resolve()),  # for rascal report RUN_DIR
            "finished": self.finished,
            "elapsed_s": round(elapsed, 2),
            "course_length_m": self.frame.length_m if self.frame else None,
            "station_m": self.station_m,
            "modules": {
                child.spec.label: {
                    "restarts": child.restarts,
                    "restart_reasons": child.exits,
                    "jitter_ms": child.status.jitter_ns / 1e6 if child.status else None,
                    "overruns": child.status.overruns if child.status else None,
                    "rx_rejected": child.status.rx_rejected if child.status else None,
                    "detail": child.status.detail if child.status else None,
                    "cpu_pct": _rounded(child.cpu.mean_pct),
                    "cpu_peak_pct": round(child.cpu.peak_pct, 1),
                    "cpu_budget_pct": child.cpu.budget_pct,
                }
                for child in self.children
            },
            # % of one core, each module's mean over its heartbeats (children included), and
            # this supervisor's own over the run.
            "cpu_pct": {
                "modules": _rounded(sum(pct for pct in cpu.values() if pct is not None)),
                "supervisor": round(own_cpu_pct, 1),
            },
            "messages_per_s": self.traffic(elapsed),
            "health_events": Counter(f"{e.module}:{e.code}" for e in self.events),
        }

    def traffic(self, elapsed_s: float) -> dict[str, float]:
        """Messages per second on each channel, as the recorder (which hears every channel, so
        the supervisor need not) counted them in its end-of-recording metadata."""
        try:
            counts = read_metadata(self.run_dir / "run.mcap").get(END_METADATA, {})
        except RecordingError:
            return {}
        prefix = "received/"
        return {
            key.removeprefix(prefix): round(int(count) / elapsed_s, 1)
            for key, count in sorted(counts.items())
            if key.startswith(prefix)
        }


def _cpu_cell(child: Child) -> str:
    """This heartbeat's CPU, marked when over the module's budget."""
    status = child.status
    if status is None or status.cpu_pct < 0:
        return ""
    return f"{status.cpu_pct:.1f}" + ("!" if status.cpu_pct > child.cpu.budget_pct else "")


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 1)


def run(
    deployment: Deployment,
    host: str,
    runs_dir: Path = Path("runs"),
    duration_s: float | None = None,
    console: Console | None = None,
    view_port: int | None = None,
    images: bool = True,
) -> tuple[int, Path]:
    """Run this host's modules until the course is done, ``duration_s`` or a signal; then the
    report (its images only with ``images``: drawing them takes seconds a run batch can spare)."""
    if console is None:
        console = Console()
        console.width = max(console.width, 140)  # piped (make demo, logs): still one line per module
    run_dir = runs_dir / datetime.now().strftime("%Y%m%d-%H%M%S")
    run_dir.mkdir(parents=True, exist_ok=True)
    keyring = load_keyring(deployment.key_file) if deployment.key_file else default_keyring()
    clock = SharedClock()
    source_id = deployment.host_source_id(host, SUPERVISOR_SOURCE_ID)
    bus = Bus.open(deployment.bus_on(host), source_id=source_id, clock=clock, keyring=keyring)
    runtime = Runtime(bus, clock)
    supervisor = RunSupervisor(runtime, deployment, host, run_dir, duration_s, console, view_port)
    if view_port is not None:
        console.print(f"live view: http://127.0.0.1:{view_port}/")
    runtime.run(supervisor)
    console.print(f"run {'finished the course' if supervisor.finished else 'ended'}; logs and summary in {run_dir}/")
    report = report_run(run_dir, deployment, console, images)
    if report is not None and report.latency_ms:
        # Read back from the recording, so it lands in the summary after the run.
        summary_path = run_dir / "summary.json"
        summary = json.loads(summary_path.read_text())
        summary["latency_ms"] = {"obstacle_to_actuator": report.latency_ms}
        summary_path.write_text(json.dumps(summary, indent=2))
        console.print(f"obstacle measurement to actuator command: {_latency_line(report.latency_ms)}")
    _add_json_twins(run_dir / "run.mcap", console)
    return 0, run_dir


def _add_json_twins(recording: Path, console: Console) -> None:
    """Make the recording Foxglove-ready: JSON twins beside the raw channels, written now rather
    than by the recorder while the vehicle drove."""
    started = time.monotonic()
    try:
        messages = add_json_twins(recording)
    except (RecordingError, OSError) as exc:
        console.print(f"{recording}: kept raw only, no JSON channels: {exc}", markup=False, highlight=False)
        return
    console.print(f"{recording}: JSON channels added for {messages} messages in {time.monotonic() - started:.1f} s")


def _latency_line(latency_ms: dict[str, float | int]) -> str:
    return f"p50 {latency_ms['p50']} ms, p99 {latency_ms['p99']} ms over {latency_ms['samples']} paths"


def cpu_list(text: str) -> set[int]:
    """CPU numbers as taskset and cgroups write them: ``0``, ``0,2``, ``1-3``."""
    cpus: set[int] = set()
    try:
        for part in text.split(","):
            low, dash, high = part.partition("-")
            cpus.update(range(int(low), int(high if dash else low) + 1))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected CPU numbers like 0 or 0,2-3, got {text!r}") from None
    if not cpus or min(cpus) < 0:
        raise argparse.ArgumentTypeError(f"expected CPU numbers like 0 or 0,2-3, got {text!r}")
    return cpus


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="rascal run", description=__doc__.splitlines()[0])
    parser.add_argument("deployment", nargs="?", default=str(DEFAULT_DEPLOYMENT), help="deployment TOML")
    parser.add_argument("--host", help="which host's modules to run (default: the only host, or localhost)")
    parser.add_argument("--duration", type=float, help="end after this many seconds")
    parser.add_argument("--runs-dir", type=Path, default=Path("runs"), help="where run directories go")
    parser.add_argument("--view", action="store_true", help="serve the live view (rascal view) alongside the drive")
    parser.add_argument("--view-port", type=int, default=8090, help="HTTP port of the live view")
    parser.add_argument(
        "--cpus",
        type=cpu_list,
        help="run the supervisor and every module on these CPUs only, e.g. 0 or 0,2-3 (does the stack fit?)",
    )
    parser.add_argument(
        "--no-images",
        action="store_true",
        help="summarise the run without drawing the report images (rascal report RUN_DIR draws them later)",
    )
    args = parser.parse_args(argv)
    try:
        deployment = load_deployment(args.deployment)
        host = args.host or (next(iter(deployment.hosts)) if len(deployment.hosts) == 1 else LOCALHOST)
        deployment.on_host(host)
    except DeploymentError as exc:
        parser.error(str(exc))
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        parser.error("--duration must be a positive number of seconds")
    if args.cpus is not None:
        try:
            os.sched_setaffinity(0, args.cpus)  # the modules inherit it
        except (OSError, AttributeError) as exc:
            parser.error(f"--cpus: cannot confine this process to CPUs {sorted(args.cpus)}: {exc}")
    view_port = args.view_port if args.view else None
    status, _ = run(deployment, host, args.runs_dir, args.duration, view_port=view_port, images=not args.no_images)
    return status
