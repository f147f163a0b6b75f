"""Drive measures from the simulator's truth: how well the stack drove the scenario.

Sans-IO: feed every truth sample (and every planned path as it is published); read ``result()``.
Measures: completion and time; mean speed against the mean the RDDF and curvature allow (the
course path's own speed profile); cross-track error of the true position to the newest planned
path (RMS and max); collisions and corridor exits (the simulator counts them); entries onto
terrain hazards (the simulator drives through ditches and over berms, so the referee counts each
time the footprint comes onto ground more than 0.15 m off level); stalls (the vehicle below
0.1 m/s for over 30 s before the finish, once per such stop: a leaderboard's "agent blocked");
the minimum clearance between the vehicle's footprint and any obstacle.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass

import numpy as np

from modules.sim.collision import clearance_m
from modules.sim.scenario import Scenario
from modules.sim.terrain import ground_height
from modules.sim.vehicle import VehicleParams
from protocol.messages import Path, SimTruth

FINISH_DISTANCE_M = 5.0  # control stops 2-3 m short of the last waypoint; rascal run agrees (rascal/run.py)
CLEARANCE_REACH_M = 15.0  # obstacles farther from the vehicle's centre cannot set the minimum
HAZARD_STEP_M = 0.15  # ground this far off level under the footprint is on a hazard (fusion's profile step)
FOOTPRINT_SAMPLES = (7, 4)  # points along and across the footprint where the ground is looked up
STALL_SPEED_MPS = 0.1  # slower than this is standing
STALL_TIME_S = 30.0  # standing longer than this before the finish is a stall


@dataclass(frozen=True)
class DriveMeasures:
    finished: bool
    completion: float  # share of the route driven
    progress_m: float
    route_length_m: float
    time_s: float  # scenario time at the finish (or the last sample)
    mean_speed_mps: float
    allowed_mean_speed_mps: float
    speed_ratio: float  # mean speed / allowed mean speed, over the part driven
    cross_track_rms_m: float
    cross_track_max_m: float
    collisions: int
    corridor_exits: int
    hazard_entries: int  # times the footprint came onto a ditch or berm
    stalls: int  # stops of over STALL_TIME_S before the finish
    min_clearance_m: float
    samples: int

    def as_dict(self) -> dict[str, float | int | bool]:
        return {k: (round(v, 4) if isinstance(v, float) and math.isfinite(v) else v) for k, v in asdict(self).items()}


class Referee:
    def __init__(self, scenario: Scenario, params: VehicleParams | None = None) -> None:
        self.params = params or VehicleParams()
        self.route = scenario.route
        self.obstacles = scenario.world.obstacles
        self._obstacle_xy = np.array([(o.east_m, o.north_m) for o in self.obstacles]).reshape(-1, 2)
        self._reach = np.array([o.footprint_radius_m() for o in self.obstacles]) + CLEARANCE_REACH_M
        p = self.params
        self.hazards = tuple(scenario.world.hazards)
        self._hazard_xy = np.array([(h.east_m, h.north_m) for h in self.hazards]).reshape(-1, 2)
        self._hazard_reach = np.array([math.hypot(h.length_m, h.width_m) / 2 + p.length_m for h in self.hazards])
        along, across = np.meshgrid(
            np.linspace(-p.rear_overhang_m, p.length_m - p.rear_overhang_m, FOOTPRINT_SAMPLES[0]),
            np.linspace(-p.width_m / 2, p.width_m / 2, FOOTPRINT_SAMPLES[1]),
        )
        self._footprint = np.column_stack([along.ravel(), across.ravel()])
        self.hazard_entries = 0
        self._on_hazard = False
        self.stalls = 0
        self._standing_since_s: float | None = None  # scenario time the current stop began
        self._stall_counted = False
        self.path_xy: np.ndarray | None = None
        self.cross_track: list[float] = []
        self.min_clearance_m = math.inf
        self.last: SimTruth | None = None
        self.finish_time_s: float | None = None
        self.samples = 0

    def on_path(self, path: Path) -> None:
        if len(path.points) >= 2:
            self.path_xy = np.array([(p.east_m, p.north_m) for p in path.points])

    def on_truth(self, truth: SimTruth) -> None:
        self.samples += 1
        self.last = truth
        # The simulator's progress is the nearest route point's: up to half a spacing short of
        # where the vehicle stopped, which rascal run (on the continuous station) does not lose.
        to_go_m = self.route.length_m - truth.progress_m - 0.5 * self.route.spacing_m
        if self.finish_time_s is None and to_go_m < FINISH_DISTANCE_M:
            self.finish_time_s = truth.scenario_time_s
        if self.finish_time_s is not None:
            return  # after the finish only the totals matter
        self._watch_stall(truth)
        if self.path_xy is not None and truth.speed_mps > 0.5:
            self.cross_track.append(distance_to_polyline(self.path_xy, truth.east_m, truth.north_m))
        on_hazard = self._footprint_on_hazard(truth)
        if on_hazard and not self._on_hazard:
            self.hazard_entries += 1
        self._on_hazard = on_hazard
        if len(self.obstacles):
            d = np.hypot(self._obstacle_xy[:, 0] - truth.east_m, self._obstacle_xy[:, 1] - truth.north_m)
            for index in np.flatnonzero(d < self._reach):
                self.min_clearance_m = min(self.min_clearance_m, clearance_m(truth, self.obstacles[index], self.params))

    def _watch_stall(self, truth: SimTruth) -> None:
        """Count a stop once, when it has lasted over STALL_TIME_S (on scenario time, so missed
        truth samples do not shorten it)."""
        if abs(truth.speed_mps) >= STALL_SPEED_MPS:
            self._standing_since_s = None
            return
        if self._standing_since_s is None:
            self._standing_since_s, self._stall_counted = truth.scenario_time_s, False
        elif not self._stall_counted and truth.scenario_time_s - self._standing_since_s > STALL_TIME_S:
            self.stalls += 1
            self._stall_counted = True

    def _footprint_on_hazard(self, truth: SimTruth) -> bool:
        """Whether ground under the vehicle's footprint is more than a step off level."""
        if not self.hazards:
            return False
        d = np.hypot(self._hazard_xy[:, 0] - truth.east_m, self._hazard_xy[:, 1] - truth.north_m)
        near = [self.hazards[i] for i in np.flatnonzero(d < self._hazard_reach)]
        if not near:
            return False
        c, s = math.cos(truth.yaw_rad), math.sin(truth.yaw_rad)
        x, y = self._footprint[:, 0], self._footprint[:, 1]
        height = ground_height(near, truth.east_m + c * x - s * y, truth.north_m + s * x + c * y)
        return bool(np.max(np.abs(height)) > HAZARD_STEP_M)

    def result(self) -> DriveMeasures:
        last = self.last
        length = float(self.route.length_m)
        progress = last.progress_m if last else 0.0
        time_s = self.finish_time_s if self.finish_time_s is not None else (last.scenario_time_s if last else 0.0)
        mean = progress / time_s if time_s > 0 else 0.0
        allowed = self._allowed_mean_speed(progress)
        track = np.array(self.cross_track) if self.cross_track else np.array([math.nan])
        return DriveMeasures(
            finished=self.finish_time_s is not None,
            completion=progress / length if length else 0.0,
            progress_m=progress,
            route_length_m=length,
            time_s=time_s,
            mean_speed_mps=mean,
            allowed_mean_speed_mps=allowed,
            speed_ratio=mean / allowed if allowed > 0 else 0.0,
            cross_track_rms_m=float(np.sqrt(np.mean(track**2))),
            cross_track_max_m=float(np.max(track)),
            collisions=last.collisions if last else 0,
            corridor_exits=last.corridor_exits if last else 0,
            hazard_entries=self.hazard_entries,
            stalls=self.stalls,
            min_clearance_m=self.min_clearance_m,
            samples=self.samples,
        )

    def _allowed_mean_speed(self, progress_m: float) -> float:
        """Mean speed of the route's speed profile over the first ``progress_m`` metres."""
        route = self.route
        end = int(np.searchsorted(route.s_m, progress_m, side="right"))
        if end < 2:
            return 0.0
        s, v = route.s_m[:end], route.speed_mps[:end]
        segment_speed = np.maximum((v[:-1] + v[1:]) / 2.0, 1e-3)
        time_s = float(np.sum(np.diff(s) / segment_speed))
        return float(s[-1] - s[0]) / time_s if time_s > 0 else 0.0


def drove_safely(drive: Mapping[str, object]) -> bool:
    """Whether drive measures (``DriveMeasures.as_dict()``, as in summary.json) show a finished
    course with no collision, corridor exit or ditch/berm entry."""
    return bool(
        drive.get("finished")
        and drive.get("collisions") == 0
        and drive.get("corridor_exits") == 0
        and drive.get("hazard_entries", 0) == 0
    )


def distance_to_polyline(points: np.ndarray, east_m: float, north_m: float) -> float:
    """Shortest distance from a point to a polyline of (n, 2) points."""
    a, b = points[:-1], points[1:]
    ab = b - a
    length_sq = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
    p = np.array([east_m, north_m])
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / length_sq, 0.0, 1.0)
    nearest = a + t[:, None] * ab
    return float(np.min(np.hypot(nearest[:, 0] - east_m, nearest[:, 1] - north_m)))
