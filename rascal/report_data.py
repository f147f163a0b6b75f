"""What the run report shows, read back from a run directory: the drive (true and estimated
tracks, planned paths, map snapshots) from ``run.mcap`` through rascal/logread.py, the course and
obstacles from the run's deployment, each module's timing from its heartbeats, and the
measurement-to-actuator latency (rascal/latency.py).

Tracks are thinned to ``TRACK_PERIOD_S`` (the report's resolution; the simulator's truth comes at
100 Hz), and only the messages the report draws are decoded.
"""

from __future__ import annotations

import json
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brain.corridor import Course
from brain.course_config import load_course
from brain.planning.frame import CorridorFrame
from modules.sim.scenario import load_scenario
from modules.sim.world import WorldObstacle
from protocol import channels
from protocol.errors import ProtocolError
from protocol.messages import MapSnapshot, ModuleStatus
from rascal.latency import measurement_to_actuator_ms
from rascal.logread import RecordingError, decode, iter_datagrams
from rascal.runtime.deployment import Deployment, load_deployment

TRACK_PERIOD_S = 0.1
LOCATE_BATCH = 10  # track samples located along the course together (1 s: well inside locate's window)
BUS_CHANNELS = {channels.MODULE_STATUS, channels.TIME_SYNC, channels.HEALTH}  # not a module's output
FloatArray = NDArray[np.float64]


class ReportError(ValueError):
    """A run directory the report cannot be made from; the message says what is missing."""


@dataclass
class Track:
    """A vehicle track: time since the run's first message, position, speed, and where along
    the course each sample is (station ``s_m``, left offset ``d_m`` from the centre line)."""

    t_s: FloatArray
    east_m: FloatArray
    north_m: FloatArray
    speed_mps: FloatArray
    s_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    d_m: FloatArray = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return len(self.t_s)


@dataclass
class ModuleTiming:
    """One module process as its heartbeats (and the messages it sent) describe it."""

    module: str
    source_id: int
    heartbeats: int = 0
    loop_period_ns: int = 0
    jitter_ms: list[float] = field(default_factory=list)
    overruns: int = 0
    restarts: int = 0
    rx_rejected: int = 0
    cpu_pct: list[float] = field(default_factory=list)  # per heartbeat, measured ones only
    outputs_hz: dict[str, float] = field(default_factory=dict)

    @property
    def mean_cpu_pct(self) -> float | None:
        return sum(self.cpu_pct) / len(self.cpu_pct) if self.cpu_pct else None


@dataclass
class RunData:
    run_dir: Path
    summary: dict[str, Any]
    deployment: Deployment
    course: Course
    frame: CorridorFrame
    obstacles: tuple[WorldObstacle, ...]
    duration_s: float
    truth: Track | None  # the simulator's truth, in simulated deployments
    nav: Track | None  # the navigation solution (VEHICLE_STATE)
    paths: list[tuple[float, FloatArray]]  # (time, planned points N x 2), in order
    snapshots: list[tuple[float, MapSnapshot]]
    modules: dict[str, ModuleTiming]
    latency_ms: FloatArray  # measurement to actuator, one per path that carried its input time


def read_run(run_dir: Path, deployment: Deployment | None = None) -> RunData:
    """Everything the report needs from ``run_dir``; ``deployment`` defaults to the one the
    run's summary names."""
    summary_path = run_dir / "summary.json"
    try:
        summary = json.loads(summary_path.read_text())
    except FileNotFoundError:
        raise ReportError(f"{run_dir}: no summary.json (not a run directory, or the run has not ended)") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise ReportError(f"{summary_path}: {exc}") from None
    if deployment is None:
        named = summary.get("deployment_file")
        if not named:
            raise ReportError(f"{summary_path}: names no deployment file; pass --deployment FILE")
        deployment = load_deployment(named)
    if deployment.course is None:
        raise ReportError(f"{deployment.path}: the deployment has no course to draw the drive on")
    course = load_course(deployment.course, deployment.origin)
    frame = CorridorFrame(course.interpolate())
    obstacles = load_scenario(deployment.scenario).world.obstacles if deployment.scenario else ()
    reader = _Reader()
    mcap = run_dir / "run.mcap"
    if not mcap.exists():
        raise ReportError(f"{run_dir}: no run.mcap")
    try:
        for datagram in iter_datagrams(mcap):
            reader.add(datagram)
    except RecordingError as exc:
        raise ReportError(str(exc)) from None
    truth, nav = reader.track(channels.SIM_TRUTH), reader.track(channels.VEHICLE_STATE)
    for track in (truth, nav):
        if track is not None:
            track.s_m, track.d_m = _locate(frame, track)
    return RunData(
        run_dir,
        summary,
        deployment,
        course,
        frame,
        obstacles,
        reader.duration_s(),
        truth,
        nav,
        reader.paths,
        reader.snapshots,
        reader.modules(),
        measurement_to_actuator_ms(reader.path_inputs, reader.commands_ns),
    )


class _Reader:
    """One pass over the recording: thin, decode and sort what the report draws."""

    def __init__(self) -> None:
        self.t0_ns: int | None = None
        self.last_ns = 0
        self.samples: dict[str, list[tuple[float, float, float, float]]] = defaultdict(list)
        self._next_sample_ns: dict[str, int] = defaultdict(int)
        self.paths: list[tuple[float, FloatArray]] = []
        self.snapshots: list[tuple[float, MapSnapshot]] = []
        self.status: dict[str, list[tuple[int, ModuleStatus]]] = defaultdict(list)
        self.sent: Counter[tuple[int, str]] = Counter()
        self.undecodable = 0
        self.path_inputs: list[tuple[int, int]] = []  # (PATH t_pub_ns, t_input_ns)
        self.commands_ns: list[int] = []  # ACTUATOR_COMMAND t_pub_ns

    def add(self, datagram: Any) -> None:
        t_ns = datagram.log_time_ns
        if self.t0_ns is None:
            self.t0_ns = t_ns
        self.last_ns = max(self.last_ns, t_ns)
        channel = datagram.channel
        self.sent[(datagram.source_id, channel)] += 1
        if channel == channels.ACTUATOR_COMMAND:
            self.commands_ns.append(datagram.t_pub_ns)
            return
        if channel in (channels.SIM_TRUTH, channels.VEHICLE_STATE):
            if t_ns < self._next_sample_ns[channel]:
                return
            self._next_sample_ns[channel] = t_ns + int(TRACK_PERIOD_S * 1e9)
        elif channel not in (channels.PATH, channels.MAP_SNAPSHOT, channels.MODULE_STATUS):
            return
        try:
            msg = decode(datagram)
        except ProtocolError:
            self.undecodable += 1
            return
        t_s = (t_ns - self.t0_ns) / 1e9
        if channel in (channels.SIM_TRUTH, channels.VEHICLE_STATE):
            self.samples[channel].append((t_s, msg.east_m, msg.north_m, msg.speed_mps))
        elif channel == channels.PATH:
            self.path_inputs.append((datagram.t_pub_ns, msg.t_input_ns))
            if len(msg.points) >= 2:
                self.paths.append((t_s, np.array([(p.east_m, p.north_m) for p in msg.points])))
        elif channel == channels.MAP_SNAPSHOT:
            self.snapshots.append((t_s, msg))
        else:
            self.status[msg.module].append((datagram.source_id, msg))

    def duration_s(self) -> float:
        return 0.0 if self.t0_ns is None else (self.last_ns - self.t0_ns) / 1e9

    def track(self, channel: str) -> Track | None:
        samples = self.samples.get(channel)
        if not samples:
            return None
        t, east, north, speed = (np.array(column, dtype=float) for column in zip(*samples, strict=True))
        return Track(t, east, north, speed)

    def modules(self) -> dict[str, ModuleTiming]:
        span_s = max(self.duration_s(), 1e-9)
        timings: dict[str, ModuleTiming] = {}
        for name, beats in sorted(self.status.items(), key=lambda item: item[1][0][0]):
            source_id = beats[-1][0]
            timing = timings[name] = ModuleTiming(name, source_id, heartbeats=len(beats))
            for _source, status in beats:
                timing.jitter_ms.append(status.jitter_ns / 1e6)
                timing.overruns += status.overruns
                if status.cpu_pct >= 0:
                    timing.cpu_pct.append(status.cpu_pct)
            last = beats[-1][1]
            timing.loop_period_ns, timing.restarts, timing.rx_rejected = (
                last.loop_period_ns,
                max(status.restarts for _s, status in beats),
                last.rx_rejected,
            )
            timing.outputs_hz = {
                channel: count / span_s
                for (source, channel), count in sorted(self.sent.items())
                if source == source_id and channel not in BUS_CHANNELS
            }
        return timings


def _locate(frame: CorridorFrame, track: Track) -> tuple[FloatArray, FloatArray]:
    """Station and offset of every sample, each batch searched near the one before (a course
    that passes near itself cannot make the station jump)."""
    s = np.empty(len(track))
    d = np.empty(len(track))
    near: float | None = None
    for start in range(0, len(track), LOCATE_BATCH):
        part = slice(start, start + LOCATE_BATCH)
        s[part], d[part] = frame.locate(track.east_m[part], track.north_m[part], near)
        near = float(s[part][-1])
    return s, d


def drive_line(data: RunData) -> str:
    """The drive in one line: the referee's measures when the run has them."""
    drive = data.summary.get("drive") or {}
    finished = drive.get("finished", data.summary.get("finished"))
    parts = [
        f"{'finished' if finished else 'not finished'}: "
        + (
            f"{100 * drive['completion']:.1f} % of {drive.get('route_length_m', data.frame.length_m):.0f} m"
            if "completion" in drive
            else f"course {data.frame.length_m:.0f} m"
        )
        + f" in {drive.get('time_s', data.duration_s):.0f} s"
    ]
    for key, text in (
        ("mean_speed_mps", "mean {:.1f} m/s"),
        ("collisions", "collisions {}"),
        ("corridor_exits", "corridor exits {}"),
        ("hazard_entries", "ditch/berm entries {}"),
        ("min_clearance_m", "min clearance {:.2f} m"),
    ):
        if drive.get(key) is not None:
            parts.append(text.format(drive[key]))
    return ", ".join(parts)
