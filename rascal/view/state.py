"""What the view shows, gathered from bus messages: sans-IO, so the live bus and a recording
feed it the same way (:meth:`ViewState.count` for every message, :meth:`ViewState.handle` for
the decoded ones it draws).

Everything is kept in the ENU frame of the course. Descriptors in the vehicle frame (lidar and
ESVS obstacles, lane borders) are placed with the navigation pose nearest their measurement time.
"""

from __future__ import annotations

import base64
import bisect
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from brain.corridor import Course
from brain.fusion.snapshot import SnapshotError, decode_snapshot
from protocol import channels
from protocol.messages import (
    Frame,
    HealthEvent,
    LaneBorders,
    MapSnapshot,
    ModuleState,
    ModuleStatus,
    ObstacleList,
    Path,
    Sensor,
    Severity,
    VehicleState,
)
from rascal.runtime.bus import ChannelStats

OBSTACLE_CHANNELS = (channels.OBSTACLES_LIDAR, channels.OBSTACLES_ESVS, channels.OBSTACLES_BEACON)
DRAWN_CHANNELS = (
    channels.VEHICLE_STATE,
    channels.PATH,
    channels.MAP_SNAPSHOT,
    channels.LANE_BORDERS,
    channels.MODULE_STATUS,
    channels.HEALTH,
    *OBSTACLE_CHANNELS,
)
POSE_HISTORY = 256  # ~2.5 s of 100 Hz navigation: enough to place any descriptor still drawn
POSE_MATCH_NS = 300_000_000  # a descriptor is placed only with a pose this close to its measurement
TRAIL_SPACING_M = 0.5
TRAIL_POINTS = 4000
DESCRIPTOR_MAX_AGE_NS = 1_000_000_000  # a sensor silent this long has its obstacles taken off the map
RECENT_EVENTS = 30
BORDER_SAMPLES = 12
MAX_NAMES = 128  # modules or sensors a peer can make us keep: a key holder cycling names stays bounded
NS = 1_000_000_000


@dataclass
class _Module:
    status: ModuleStatus
    heard_ns: int
    restart_reports: int = 0


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


class ViewState:
    """The latest of everything drawn, and the health books, as JSON-ready dictionaries."""

    def __init__(self, course: Course | None = None) -> None:
        self.course = course
        self.now_ns = 0  # the newest receive time seen: the view's "now", live or replayed
        self.start_ns: int | None = None  # the first: times on the page count from it
        self.vehicle: VehicleState | None = None
        self.poses: deque[tuple[int, float, float, float]] = deque(maxlen=POSE_HISTORY)
        self._pose_times: deque[int] = deque(maxlen=POSE_HISTORY)
        self.trail: deque[tuple[float, float]] = deque(maxlen=TRAIL_POINTS)
        self.path: Path | None = None
        self.map: MapSnapshot | None = None
        self.map_seq = 0
        self.obstacles: dict[str, tuple[int, list[dict[str, Any]]]] = {}  # sensor name -> (t_meas, boxes)
        self.lanes: dict[str, tuple[int, list[list[list[float]]]]] = {}
        self.modules: dict[str, _Module] = {}
        self.events: deque[dict[str, Any]] = deque(maxlen=RECENT_EVENTS)
        self.channel_stats: dict[str, ChannelStats] = {}
        self.bad: dict[str, int] = {}  # messages that decoded but could not be drawn, by reason
        self._handlers: dict[str, Callable[[Any, int], None]] = {
            channels.VEHICLE_STATE: self._vehicle_state,
            channels.PATH: self._path,
            channels.MAP_SNAPSHOT: self._map,
            channels.LANE_BORDERS: self._lanes,
            channels.MODULE_STATUS: self._status,
            channels.HEALTH: self._health,
            **dict.fromkeys(OBSTACLE_CHANNELS, self._obstacles),
        }

    # -- input ----------------------------------------------------------------------------------

    def count(self, channel: str, recv_ns: int) -> None:
        """Every message seen on the bus, for channel rates (bounded: the bus caps channels)."""
        stats = self.channel_stats.get(channel)
        if stats is None:
            stats = self.channel_stats[channel] = ChannelStats()
        stats.messages += 1
        stats.arrivals_ns.append(recv_ns)
        self._advance(recv_ns)

    def handle(self, channel: str, msg: Any, t_meas_ns: int, recv_ns: int) -> None:
        """One decoded message of a drawn channel (others are ignored)."""
        handler = self._handlers.get(channel)
        if handler is None:
            return
        self._advance(recv_ns)
        handler(msg, t_meas_ns)

    def _advance(self, recv_ns: int) -> None:
        self.now_ns = max(self.now_ns, recv_ns)
        if self.start_ns is None:
            self.start_ns = recv_ns

    def elapsed_s(self) -> float:
        """Seconds from the first message to :attr:`now_ns`."""
        return round((self.now_ns - (self.start_ns or self.now_ns)) / NS, 3)

    def _vehicle_state(self, state: VehicleState, t_meas_ns: int) -> None:
        if not _finite(state.east_m, state.north_m, state.yaw_rad):
            self._bad("vehicle_state_not_finite")
            return
        if self._pose_times and t_meas_ns < self._pose_times[-1]:
            return  # late: the newer state stays
        self.vehicle = state
        self.poses.append((t_meas_ns, state.east_m, state.north_m, state.yaw_rad))
        self._pose_times.append(t_meas_ns)
        if not self.trail or math.dist(self.trail[-1], (state.east_m, state.north_m)) >= TRAIL_SPACING_M:
            self.trail.append((round(state.east_m, 2), round(state.north_m, 2)))

    def _path(self, path: Path, _t_meas_ns: int) -> None:
        self.path = path

    def _map(self, snapshot: MapSnapshot, _t_meas_ns: int) -> None:
        try:
            decode_snapshot(snapshot)  # the browser inflates it; refuse what it could not
        except SnapshotError:
            self._bad("map_snapshot_undecodable")
            return
        self.map = snapshot
        self.map_seq += 1

    def _obstacles(self, message: ObstacleList, t_meas_ns: int) -> None:
        pose = self._pose_at(t_meas_ns) if message.frame == Frame.VEHICLE else (0.0, 0.0, 0.0)
        if pose is None:
            self._bad("obstacles_without_a_pose_at_their_time")
            return
        boxes = []
        for obstacle in message.obstacles:
            east, north = _to_enu(pose, obstacle.x_m, obstacle.y_m)
            yaw = obstacle.yaw_rad + pose[2]
            if _finite(east, north, yaw, obstacle.length_m, obstacle.width_m):
                boxes.append(
                    {
                        "e": round(east, 2),
                        "n": round(north, 2),
                        "l": round(obstacle.length_m, 2),
                        "w": round(obstacle.width_m, 2),
                        "yaw": round(yaw, 3),
                    }
                )
        if self._room(self.obstacles, sensor_name(message.sensor)):
            self.obstacles[sensor_name(message.sensor)] = (t_meas_ns, boxes)

    def _lanes(self, message: LaneBorders, t_meas_ns: int) -> None:
        pose = self._pose_at(t_meas_ns)
        if pose is None:
            self._bad("lane_borders_without_a_pose_at_their_time")
            return
        lines = []
        for border in message.borders:
            if not (_finite(border.c0_m, border.c1, border.c2_per_m) and border.x_min_m < border.x_max_m):
                continue
            step = (border.x_max_m - border.x_min_m) / (BORDER_SAMPLES - 1)
            points = []
            for i in range(BORDER_SAMPLES):
                x = border.x_min_m + i * step
                y = border.c0_m + border.c1 * x + border.c2_per_m * x * x
                east, north = _to_enu(pose, x, y)
                if _finite(east, north):
                    points.append([round(east, 2), round(north, 2)])
            lines.append(points)
        if self._room(self.lanes, sensor_name(message.sensor)):
            self.lanes[sensor_name(message.sensor)] = (t_meas_ns, lines)

    def _status(self, status: ModuleStatus, _t_meas_ns: int) -> None:
        known = self.modules.get(status.module)
        if known is None and not self._room(self.modules, status.module):
            return
        reports = known.restart_reports if known else 0
        self.modules[status.module] = _Module(status, self.now_ns, reports)

    def _health(self, event: HealthEvent, _t_meas_ns: int) -> None:
        self.events.append(
            {"t_s": round(self.elapsed_s(), 1), "module": event.module, "severity": _severity(event.severity),
             "code": event.code, "text": event.text[:200]}
        )  # fmt: skip
        if event.code == "module_restart":  # the supervisor's: "<label> exited with ...; restarting"
            label = event.text.split(" ", 1)[0]
            known = self.modules.get(label)
            if known is not None:
                known.restart_reports += 1

    def _pose_at(self, t_ns: int) -> tuple[float, float, float] | None:
        if not self.poses:
            return None
        i = bisect.bisect_left(self._pose_times, t_ns)
        candidates = [j for j in (i - 1, i) if 0 <= j < len(self.poses)]
        t_pose, east, north, yaw = self.poses[min(candidates, key=lambda j: abs(self._pose_times[j] - t_ns))]
        return (east, north, yaw) if abs(t_pose - t_ns) <= POSE_MATCH_NS else None

    def _room(self, books: dict[str, Any], name: str) -> bool:
        if name in books or len(books) < MAX_NAMES:
            return True
        self._bad("too_many_names")
        return False

    def _bad(self, reason: str) -> None:
        self.bad[reason] = self.bad.get(reason, 0) + 1

    # -- output ---------------------------------------------------------------------------------

    def course_view(self) -> dict[str, Any]:
        """The RDDF corridor: waypoints in ENU with each segment's half width (static)."""
        course = self.course
        if course is None:
            return {"waypoints": [], "half_widths_m": []}
        return {
            "waypoints": [[round(e, 2), round(n, 2)] for e, n in zip(course.east_m, course.north_m, strict=True)],
            "half_widths_m": [round(float(w), 2) for w in course.half_width_m],
        }

    def map_view(self) -> dict[str, Any] | None:
        snapshot = self.map
        if snapshot is None:
            return None
        return {
            "seq": self.map_seq,
            "origin_e": snapshot.origin_east_m,
            "origin_n": snapshot.origin_north_m,
            "res": snapshot.resolution_m,
            "rows": snapshot.rows,
            "cols": snapshot.cols,
            "zlib_b64": base64.b64encode(snapshot.cells).decode("ascii"),
        }

    def scene_view(self) -> dict[str, Any]:
        """Vehicle, path, obstacles by sensor and lane borders, as of :attr:`now_ns`."""
        vehicle = None
        if self.vehicle is not None:
            v = self.vehicle
            vehicle = {"e": round(v.east_m, 3), "n": round(v.north_m, 3), "yaw": round(v.yaw_rad, 4),
                       "speed": round(v.speed_mps, 2), "quality": v.quality}  # fmt: skip
        fresh = self.now_ns - DESCRIPTOR_MAX_AGE_NS
        return {
            "t_s": self.elapsed_s(),
            "vehicle": vehicle,
            "path": [[round(p.east_m, 2), round(p.north_m, 2)] for p in self.path.points] if self.path else [],
            "slow": bool(self.path.slow_mode) if self.path else False,
            "obstacles": {name: boxes for name, (t, boxes) in self.obstacles.items() if t >= fresh},
            "lanes": {name: lines for name, (t, lines) in self.lanes.items() if t >= fresh},
        }

    def trail_view(self) -> list[tuple[float, float]]:
        return list(self.trail)

    def health_view(self, rejected: dict[str, int]) -> dict[str, Any]:
        """Every module's heartbeat, channel rates, recent events and rejected datagrams
        (``rejected``: this node's own, by reason; each module's total is in its row)."""
        now = self.now_ns
        modules = []
        for name, known in sorted(self.modules.items()):
            s = known.status
            modules.append(
                {
                    "name": name,
                    "state": _state(s.state),
                    "age_s": round(max(0, now - known.heard_ns) / NS, 1),
                    "uptime_s": round(s.uptime_s),
                    "loop_hz": round(NS / s.loop_period_ns, 1) if s.loop_period_ns > 0 else 0.0,
                    "jitter_ms": round(s.jitter_ns / 1e6, 2),
                    "overruns": s.overruns,
                    "restarts": max(s.restarts, known.restart_reports),
                    "rx_rejected": s.rx_rejected,
                    "stale": list(s.stale_inputs),
                    "detail": s.detail[:160],
                }
            )
        rates = {name: round(stats.rate_hz(now), 1) for name, stats in sorted(self.channel_stats.items())}
        return {
            "t_s": round(self.elapsed_s(), 1),
            "modules": modules,
            "rates_hz": rates,
            "events": list(self.events),
            "rejected": dict(sorted(rejected.items())),
            "undrawable": dict(sorted(self.bad.items())),
        }


def _to_enu(pose: tuple[float, float, float], x: float, y: float) -> tuple[float, float]:
    east, north, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return east + c * x - s * y, north + s * x + c * y


def sensor_name(sensor: int) -> str:
    try:
        return Sensor(sensor).name.lower()
    except ValueError:
        return f"sensor_{sensor}"


def _state(state: int) -> str:
    try:
        return ModuleState(state).name
    except ValueError:
        return f"STATE_{state}"


def _severity(severity: int) -> str:
    try:
        return Severity(severity).name
    except ValueError:
        return f"SEVERITY_{severity}"
