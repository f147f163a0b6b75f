"""The brain's planner, sans IO: pose and fused map in, a protocol `Path` out, once per cycle.

RASCAL's behaviour (paper II.C), with a search as the fallback (Hybrid A*, or Kratos' 4.5.3):

1. Keep the current path while it is clear: its polyline over the next ``horizon_m`` passes the
   `PathGate` (hazard clearance, corridor) and the vehicle is still near it. Same ``path_id``.
   Without one (start, slow mode, off the path), the first try is a blend from the vehicle's own
   offset and heading back to the centre line. A kept path slowed for a hazard close beside it
   gives way to a candidate (step 2) that drives the horizon sooner.
2. Otherwise generate candidates from the current speed and take the cheapest that passes
   (`brain.planning.candidates`). New ``path_id``. If none passes for the whole horizon, one that
   is clear well beyond the stopping distance will do, ending in a stop short of the hazard, as
   long as the cells show a way past it (and never to leave slow mode); nearing that stop, a
   search that gets through takes over while there is still room to turn.
3. If none is left, search a way to the furthest reachable goal along the course in the window,
   driven at up to ``search_speed_mps`` if it gets there, or else in slow mode at
   ``slow_speed_mps`` (RASCAL's 1 m/s) to a stop where the search ended. By default (``search_method="hybrid"``)
   Hybrid A* over the vehicle's poses (`brain.planning.hybrid`): its arcs are drivable and were
   checked as the gate checks them, so its polyline is published as it is. With ``"lattice"``,
   A* over the footprint-cost grid, smoothed (`brain.planning.search`,
   `brain.planning.smoothing`), and the track the vehicle makes along it is published
   (`brain.planning.pursuit`). A search path that reached its goal is kept while it stays
   clear; candidates are tried again every cycle to leave slow mode.
4. If nothing is reachable, stand still: a one-point path at speed 0, in slow mode. So does a
   map window that does not contain the vehicle, and the end of the course.

Speeds come from `brain.planning.speed`. Cells outside the grid window count as unknown and
free: the window must cover what the vehicle can reach before the next cycles see more.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
from dataclasses import dataclass
from typing import Protocol, TypedDict, Unpack

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from brain.corridor import Corridor, Course, CoursePath
from brain.grid import GridWindow
from brain.planning.bounds import LocalCorridor
from brain.planning.candidates import choose, stations
from brain.planning.checks import PathGate
from brain.planning.config import PlannerConfig
from brain.planning.frame import CorridorFrame
from brain.planning.hazards import HazardField
from brain.planning.hybrid import Terrain, hybrid_search
from brain.planning.profile import LateralProfile, swerve
from brain.planning.pursuit import pursue
from brain.planning.search import Lattice, SearchResult, search
from brain.planning.smoothing import FreeCells, smooth
from brain.planning.speed import arc_length, clearance_cap, curvature, reachable, steering_rate_cap, travel_time_s
from brain.pose import Pose, PoseLike
from protocol.messages import Path, PathPoint

FloatArray = NDArray[np.float64]

_MAX_START_SLOPE = 1.0  # a start heading beyond 45 degrees off the course is taken as 45
_MIN_PATH_M = 0.05  # shorter than this, a path is a stop
_SAME_PATH_M = 0.01  # a re-plan this close to the current path everywhere keeps its id
_TRACK_SPACING_M = 0.5  # a searched track's published points: chords within 1.4 cm of its tightest turn


class PlanMode(enum.Enum):
    KEEP = "keep"  # the current path is still clear
    REPLAN = "replan"  # a new candidate path (RASCAL's re-plan)
    SEARCH = "search"  # no candidate: a searched path at slow speed
    STOP = "stop"  # nothing reachable (or the course is done): stand still


class MovingPose(PoseLike, Protocol):
    """What the planner reads of the vehicle: its pose and speed; `protocol.messages.VehicleState` fits."""

    @property
    def speed_mps(self) -> float: ...


@dataclass(frozen=True)
class PlanResult:
    """One cycle's output and what it took: the Path to publish plus figures for logs."""

    path: Path
    mode: PlanMode
    station_m: float
    lateral_m: float
    candidates: int = 0
    candidates_clear: int = 0
    gated: int = 0
    expansions: int = 0
    reached_goal: bool = True
    partial: bool = False  # a candidate clear for part of the horizon only: the path ends in a stop

    @property
    def slow_mode(self) -> bool:
        return self.path.slow_mode


class Counts(TypedDict, total=False):
    """What the candidate step counted, passed on to whichever step publishes."""

    candidates: int
    candidates_clear: int
    gated: int


class SearchCounts(Counts, total=False):
    expansions: int


class Figures(SearchCounts, total=False):
    """PlanResult's figures beyond the path."""

    reached_goal: bool
    partial: bool


@dataclass(frozen=True)
class _Current:
    """The path being followed: a lateral profile (candidates) or a fixed polyline (search)."""

    path_id: int
    profile: LateralProfile | None = None
    polyline: FloatArray | None = None
    reached_goal: bool = True


class Planner:
    """Plans on a course's centre path and corridor; holds the current path between cycles."""

    def __init__(
        self,
        course_path: CoursePath,
        corridor: Corridor,
        config: PlannerConfig | None = None,
        first_path_id: int = 1,
    ) -> None:
        self.config = config or PlannerConfig()
        self.frame = CorridorFrame(course_path, rounding_m=self.config.centre_rounding_m)
        self.corridor = LocalCorridor(corridor)
        self.map_reach_m = self.config.map_reach_m(float(np.max(course_path.speed_mps)))
        self._next_id = first_path_id
        self._current: _Current | None = None
        self._station: float | None = None
        self._published: FloatArray | None = None  # the last path's points and speeds (N x 3)
        self._look_again_at: tuple[int, float] | None = None  # kept path, station to look for a better one again

    @classmethod
    def for_course(cls, course: Course, config: PlannerConfig | None = None, first_path_id: int = 1) -> Planner:
        """A planner on ``course.interpolate()`` (its default limits) and ``course.corridor``. The
        course's speed does not ramp up from a standstill at its start: each profile accelerates
        from the vehicle's own speed, and a ramp from 0 would hold a vehicle that has backed up
        behind the start there for good."""
        return cls(course.interpolate(initial_speed_mps=math.inf), course.corridor, config, first_path_id)

    def reset(self) -> None:
        """Forget the current path and the station (e.g. after a long outage or a manual drive)."""
        self._current = None
        self._station = None
        self._published = None
        self._look_again_at = None

    def plan(
        self,
        pose: MovingPose,
        window: GridWindow,
        hazard_probability: ArrayLike,
        cost: ArrayLike,
        max_speed_mps: float,
    ) -> PlanResult:
        """One planning cycle. ``max_speed_mps`` is the health monitor's speed limit."""
        east, north, yaw, speed = (float(v) for v in (pose.east_m, pose.north_m, pose.yaw_rad, pose.speed_mps))
        if not all(math.isfinite(v) for v in (east, north, yaw, speed, max_speed_mps)):
            raise ValueError("the pose, speed and speed limit must be finite")
        if speed < 0.0 or max_speed_mps < 0.0:
            raise ValueError("speed and speed limit must not be negative")
        cfg = self.config
        if self._station is None:
            self._station = self.frame.locate_start(east, north, yaw)
        s0, d0 = (
            float(v) for v in self.frame.locate(east, north, self._station, cfg.station_behind_m, cfg.station_ahead_m)
        )
        self._station = s0
        s_end = min(s0 + cfg.horizon_m, self.frame.length_m)
        hazards = self._hazards(window, hazard_probability, cost, east, north, s0, s_end)
        gate = PathGate(
            hazards,
            self.corridor,
            cfg.clearance_m,
            cfg.corridor_clearance_m,
            cfg.check_spacing_m,
            cfg.front_swing,
        )
        cycle = _Cycle(self, gate, east, north, yaw, speed, max_speed_mps, s0, d0)
        # A map that does not cover the vehicle says nothing about where it is: do not drive on it.
        if s_end - s0 < _MIN_PATH_M or not window.inside(*window.cell_of(east, north)):
            return cycle.stop()
        return cycle.run(s_end)

    def _hazards(
        self,
        window: GridWindow,
        hazard_probability: ArrayLike,
        cost: ArrayLike,
        east: float,
        north: float,
        s0: float,
        s_end: float,
    ) -> HazardField:
        """The cycle's layers on the part of the map it can touch: the corridor from the vehicle to
        the horizon (and a vehicle length on, for the nose) and round the vehicle itself, widened
        by `map_reach_m`. The fused window is a square round the heading, most of it beside the
        corridor; the crop is 25-68 % of it (42 % at p50 on the default drive), and the layers cost
        in proportion. The cut edges are walls."""
        cfg = self.config
        hazard, cost_array = np.asarray(hazard_probability), np.asarray(cost)
        low_e, low_n, high_e, high_n = self.frame.band_box(s0, s_end + cfg.vehicle.length_m, self.map_reach_m)
        around = cfg.vehicle.length_m + self.map_reach_m
        crop = window.crop(
            min(low_e, east - around),
            min(low_n, north - around),
            max(high_e, east + around),
            max(high_n, north + around),
        )
        if crop is None or hazard.shape != window.shape or cost_array.shape != window.shape:
            return HazardField(window, hazard, cost_array, cfg.clearance_m, cfg.cost_cap, cfg.caution_probability)
        rows, cols = crop.rows, crop.cols
        return HazardField(
            crop.window,
            hazard[rows, cols],
            cost_array[rows, cols],
            cfg.clearance_m,
            cfg.cost_cap,
            cfg.caution_probability,
            walls=crop.cut,
        )

    def new_path_id(self) -> int:
        """An id no path of this planner has had or will have, for a path made beside it (a back-up)."""
        return self._new_id()

    def _new_id(self) -> int:
        path_id = self._next_id
        self._next_id += 1
        return path_id


class _Cycle:
    """One call of `Planner.plan`: the steps share the pose, the gate and the planner's state."""

    def __init__(
        self,
        planner: Planner,
        gate: PathGate,
        east: float,
        north: float,
        yaw: float,
        speed: float,
        max_speed: float,
        s0: float,
        d0: float,
    ) -> None:
        self.planner = planner
        self.cfg = planner.config
        self.frame = planner.frame
        self.gate = gate
        self.east, self.north, self.yaw, self.speed, self.max_speed = east, north, yaw, speed, max_speed
        self.s0, self.d0 = s0, d0
        self._space: _SearchSpace | None = None
        self._way_through: bool | None = None
        self._searched = False
        self._found: tuple[FloatArray, bool, int] | None = None

    def run(self, s_end: float) -> PlanResult:
        cfg = self.cfg
        current = self.planner._current
        s = stations(self.s0, s_end, cfg.point_spacing_m)
        base = None
        followed = current.profile if current is not None else None
        if followed is not None and abs(float(followed.at(self.s0)[0]) - self.d0) <= cfg.max_path_deviation_m:
            base = followed.since(self.s0 - cfg.point_spacing_m)
        fresh = base is None
        if base is None:
            base = self.default_profile()
        points = np.column_stack(self.frame.to_enu(s, base.at(s)[0]))
        # A path to the horizon goes on next cycle; only one to the end of the course stops there.
        verdict = self.gate.check(points, nose=s_end >= self.frame.length_m - 1e-6)
        if verdict.ok:
            if fresh or current is None:
                path_id = self.planner._new_id()
                self.planner._current = _Current(path_id, profile=base)
                return self.publish(path_id, PlanMode.REPLAN, points, s, slow=False)
            faster = self.faster_way_past(base, points, s, s_end)
            if faster is not None:
                return faster
            return self.publish(current.path_id, PlanMode.KEEP, points, s, slow=False)
        conflict = min(self.s0 + verdict.first_failure_m, s_end)
        braking_m = self.speed**2 / (2.0 * cfg.max_decel_mps2)
        min_length = braking_m + cfg.min_partial_m
        choice = choose(self.frame, self.gate, cfg, base, self.s0, s_end, conflict, self.speed, True, min_length)
        counts: Counts = {"candidates": choice.generated, "candidates_clear": choice.clear, "gated": choice.gated}
        if choice.partial and not cfg.allow_partial:
            choice = dataclasses.replace(choice, profile=None)
        elif choice.partial and choice.stations_m is not None:
            # Never a way out of slow mode: that takes a candidate clear all the way. Near its
            # stop, only worth it if there is a way past the hazard it stops short of; a stop far
            # off is driven towards regardless (a hazard far ahead is mapped coarsely, and a lane
            # through it often shows only from closer), so it does not slow the vehicle yet.
            far = float(choice.stations_m[-1]) - self.s0 >= braking_m + cfg.far_partial_m
            slow = current is not None and current.polyline is not None
            if slow or (not far and (not self.way_through(s_end) or self.search_instead(choice.stations_m, s_end))):
                choice = dataclasses.replace(choice, profile=None)
        if choice.profile is not None and choice.points is not None and choice.stations_m is not None:
            chosen = choice.stations_m
            same = (
                not fresh
                and current is not None
                and current.profile is not None
                and float(np.max(np.abs(choice.profile.at(chosen)[0] - current.profile.at(chosen)[0]))) < _SAME_PATH_M
            )
            if same and current is not None:
                path_id, mode = current.path_id, PlanMode.KEEP
            else:
                path_id, mode = self.planner._new_id(), PlanMode.REPLAN
            self.planner._current = _Current(path_id, profile=choice.profile)
            return self.publish(
                path_id,
                mode,
                choice.points,
                chosen,
                slow=False,
                stop_at_end=choice.partial,
                partial=choice.partial,
                **counts,
            )
        kept = self.kept_search_path()
        if kept is not None and current is not None:
            further = None if current.reached_goal else self.search_further(kept, s_end, counts)
            if further is not None:
                return further
            return self.publish_searched(current.path_id, kept, current.reached_goal, **counts)
        found = self.search_path(s_end)
        if found is None:
            return self.stop(**counts)
        points, reached, expansions = found
        path_id = self.planner._new_id()
        self.planner._current = _Current(path_id, polyline=points, reached_goal=reached)
        return self.publish_searched(path_id, points, reached, expansions=expansions, **counts)

    def publish_searched(
        self, path_id: int, points: FloatArray, reached: bool, **figures: Unpack[SearchCounts]
    ) -> PlanResult:
        """A searched path ends in a stop where the search did. One that gets through is driven at
        up to the search speed; one that does not, in slow mode (RASCAL's 1 m/s) to its stop."""
        return self.publish(
            path_id,
            PlanMode.SEARCH,
            points,
            None,
            slow=not reached,
            stop_at_end=True,
            top_speed_mps=self.cfg.search_speed_mps,
            reached_goal=reached,
            **figures,
        )

    def faster_way_past(
        self, base: LateralProfile, points: FloatArray, s: FloatArray, s_end: float
    ) -> PlanResult | None:
        """A clear path keeps its slowdowns: one that passes a hazard close by (legal, but at the
        near-hazard speed) is never re-planned by itself. While the kept path is slowed for a
        hazard by more than ``faster_min_gain_mps`` at least ``faster_lead_s`` ahead, candidates
        are generated as if it failed there, and the cheapest clear one replaces it if it drives
        the horizon ``faster_min_saving_s`` sooner. Having found none, it looks again once the
        vehicle is ``faster_retry_m`` further on: the search costs a re-plan each time."""
        cfg, planner = self.cfg, self.planner
        current = planner._current
        tried = planner._look_again_at
        if current is not None and tried is not None and tried[0] == current.path_id and self.s0 < tried[1]:
            return None
        near = self.near_cap(points)
        slowed = np.flatnonzero(near < self.frame.speed_at(s) - cfg.faster_min_gain_mps)
        if len(slowed) == 0 or s[slowed[0]] - self.s0 < cfg.faster_lead_s * max(self.speed, cfg.start_speed_mps):
            return None
        slowdown_m = float(s[slowed[0]])
        choice = choose(self.frame, self.gate, cfg, base, self.s0, s_end, slowdown_m, self.speed, True, math.inf)
        if (
            choice.profile is None
            or choice.points is None
            or choice.stations_m is None
            or self.travel_time(choice.points, choice.stations_m)
            > self.travel_time(points, s) - cfg.faster_min_saving_s
        ):
            if current is not None:
                planner._look_again_at = (current.path_id, self.s0 + cfg.faster_retry_m)
            return None
        path_id = planner._new_id()
        planner._current = _Current(path_id, profile=choice.profile)
        counts: Counts = {"candidates": choice.generated, "candidates_clear": choice.clear, "gated": choice.gated}
        return self.publish(path_id, PlanMode.REPLAN, choice.points, choice.stations_m, slow=False, **counts)

    def search_further(self, kept: FloatArray, s_end: float, counts: Counts) -> PlanResult | None:
        """A kept search that stops short is searched again each time the vehicle is
        ``faster_retry_m`` further on. The map ahead firms up and the window moves on as it
        drives, and a search within its expansion budget may get further from a pose nearer the
        gap: a new one replaces the kept one if it gets through, or stops at least
        ``faster_retry_m`` further along the course. Otherwise the vehicle creeps to the kept
        stop and stands before the hazard with no room left to turn past it. Progress decides,
        so searches that stop as short as before change nothing (no flapping)."""
        cfg, planner = self.cfg, self.planner
        current, tried = planner._current, planner._look_again_at
        if current is None:
            return None
        if tried is None or tried[0] != current.path_id:
            planner._look_again_at = (current.path_id, self.s0 + cfg.faster_retry_m)
            return None
        if self.s0 < tried[1]:
            return None
        planner._look_again_at = (current.path_id, self.s0 + cfg.faster_retry_m)
        found = self.search_path(s_end)
        if found is None:
            return None
        points, reached, expansions = found
        if not reached and self.station_of(points[-1]) < self.station_of(kept[-1]) + cfg.faster_retry_m:
            return None
        path_id = planner._new_id()
        planner._current = _Current(path_id, polyline=points, reached_goal=reached)
        return self.publish_searched(path_id, points, reached, expansions=expansions, **counts)

    def station_of(self, point: FloatArray) -> float:
        """The course station of a point between the vehicle and the horizon."""
        s, _d = self.frame.locate(point[0], point[1], self.s0, self.cfg.station_behind_m, self.cfg.horizon_m)
        return float(s)

    def default_profile(self) -> LateralProfile:
        """From the vehicle's own lateral state (its offset, and its heading relative to the
        course) back to the centre line over a middle transition length for its speed."""
        cfg = self.cfg
        relative = math.remainder(self.yaw - float(self.frame.heading_at(self.s0)), math.tau)
        slope = float(np.clip(math.tan(np.clip(relative, -1.5, 1.5)), -_MAX_START_SLOPE, _MAX_START_SLOPE))
        start = LateralProfile(np.array([self.s0]), np.array([self.s0]), np.array([[self.d0, slope, 0, 0, 0, 0.0]]))
        times = sorted(cfg.transition_times_s)
        length = float(np.clip(times[len(times) // 2] * self.speed, cfg.min_transition_m, cfg.max_transition_m))
        return swerve(start, self.s0, 0.0, length, self.s0 + length)

    def kept_search_path(self) -> FloatArray | None:
        """The current searched path from the vehicle on, while it is still clear: to its end if
        it reached its goal; if it did not, while at least ``min_partial_m`` of it is left, so
        the vehicle follows one search decisively instead of a new one every cycle."""
        current = self.planner._current
        if current is None or current.polyline is None:
            return None
        trimmed, deviation = _trim(current.polyline, np.array([self.east, self.north]))
        left = arc_length(trimmed)[-1]
        if deviation > self.cfg.max_path_deviation_m or left < (
            _MIN_PATH_M if current.reached_goal else self.cfg.min_partial_m
        ):
            return None
        return trimmed if self.gate.check(trimmed).ok else None

    def search_space(self, s_end: float) -> _SearchSpace | None:
        """The vehicle's cell, the goal and the free cells of this cycle's search (built once)."""
        if self._space is not None:
            return self._space
        cfg, window = self.cfg, self.gate.hazards.window
        res = window.resolution_m
        start = tuple(int(v) for v in window.cell_of(self.east, self.north))
        goal = self.goal(s_end)
        if not window.inside(*start) or goal is None:
            return None
        point, normal, half_width = goal
        # Thresholds at cell centres such that any point between two free centres passes the gate
        # (sure), and such that a cell holding any point that passes it is in (possible): no point
        # of a cell is further than half its diagonal from the centre, and both fields are
        # 1-Lipschitz. Whether there is a way at all is asked of the possible cells: the sure ones
        # close a lane a few cells wide, which a pose search threads.
        diagonal = res * math.sqrt(2.0) / 2.0
        depth, clearance = self.planner.corridor.depth(window), self.gate.hazards.clearance_m[1:-1, 1:-1]

        def cells(slack: float) -> NDArray[np.bool_]:
            return (depth >= cfg.corridor_clearance_m + slack) & (clearance >= cfg.clearance_m + slack)

        # The lattice's track turns as pure pursuit makes it: its cells keep the swing at full lock.
        free = cells(cfg.check_spacing_m / 2.0 + diagonal + float(cfg.front_swing.at(1.0 / cfg.turning_radius_m)))
        possible = cells(cfg.check_spacing_m / 2.0 - diagonal)
        heading = math.atan2(-normal[0], normal[1])  # the course's: the normal turned clockwise
        self._space = _SearchSpace(
            (start[0], start[1]),
            point - half_width * normal,
            point + half_width * normal,
            heading,
            free,
            depth,
            possible,
        )
        return self._space

    def lattice_search(self, space: _SearchSpace, stride: int) -> SearchResult:
        """A* on the lattice of every ``stride``-th cell through the vehicle's cell."""
        cfg, window = self.cfg, self.gate.hazards.window
        lattice = Lattice.build(space.free, stride, space.start)
        rows, cols = lattice.node_centres()
        east, north = window.centre_of(rows, cols)
        distance = _distance_to_segment(east, north, space.goal_a, space.goal_b)
        goal_mask = distance <= lattice.stride * window.resolution_m
        # Short of the goal, end nearest it, and among equals nearest the centre line.
        middle = (space.goal_a + space.goal_b) / 2.0
        shortfall = distance + 0.01 * np.hypot(east - middle[0], north - middle[1])
        return search(
            lattice,
            lattice.node_of(space.start),
            goal_mask,
            distance,
            self.step_weight[rows, cols],
            window.resolution_m,
            cfg.search_heuristic_weight * (1.0 + cfg.search_cost_weight * cfg.search_unseen_cost),
            shortfall,
        )

    @functools.cached_property
    def step_weight(self) -> FloatArray:
        """Each cell's search cost per metre: 1 + weight x footprint-mean cost, plus the room term.
        Keep to the middle of gaps: a path hugging a wall round a corner is one the vehicle,
        turning no tighter than its radius, swings wide of (and into the wall)."""
        cfg, hazards = self.cfg, self.gate.hazards
        weight = 1.0 + cfg.search_cost_weight * hazards.footprint_cost.astype(float)
        spare = (hazards.clearance_m[1:-1, 1:-1] - cfg.clearance_m) / cfg.search_room_m
        return weight + cfg.search_room_weight * np.clip(1.0 - spare, 0.0, 1.0)

    def way_through(self, s_end: float) -> bool:
        """Whether any free path of cells joins the vehicle to the goal (a labelling, no search)."""
        if self._way_through is None:
            self._way_through = self._label_way_through(s_end)
        return self._way_through

    def _label_way_through(self, s_end: float) -> bool:
        space = self.search_space(s_end)
        if space is None or not space.possible[space.start]:
            return False
        window = self.gate.hazards.window
        _, labels = cv2.connectedComponents(space.possible.astype(np.uint8), connectivity=8)
        reach = self.cfg.search_stride * window.resolution_m
        low = np.minimum(space.goal_a, space.goal_b) - reach
        high = np.maximum(space.goal_a, space.goal_b) + reach
        (row_lo, row_hi), (col_lo, col_hi) = window.cell_of([low[0], high[0]], [low[1], high[1]])
        rows = slice(max(int(row_lo), 0), min(int(row_hi) + 1, window.rows))
        cols = slice(max(int(col_lo), 0), min(int(col_hi) + 1, window.cols))
        east, north = window.centre_of(*np.mgrid[rows, cols])
        near = _distance_to_segment(east, north, space.goal_a, space.goal_b) <= reach
        return bool(np.any(labels[rows, cols][near] == labels[space.start]))

    def search_instead(self, partial_stations: FloatArray | None, s_end: float) -> bool:
        """Whether to leave a partial path for a search that gets through: once its stop is
        within braking distance plus room to turn (a nose and two turning radii) the vehicle
        must start turning towards the way past, or it stands boxed in where it cannot."""
        cfg = self.cfg
        if partial_stations is None or len(partial_stations) == 0:
            return False
        left = float(partial_stations[-1]) - self.s0
        room = self.speed**2 / (2.0 * cfg.max_decel_mps2) + self.gate.nose_m + 2.0 * cfg.turning_radius_m
        if left > room:
            return False
        found = self.search_path(s_end)
        return found is not None and found[1]

    def search_path(self, s_end: float) -> tuple[FloatArray, bool, int] | None:
        """The searched path to the furthest goal in the window, gated, whether it reached the
        goal, and the expansions (once a cycle: the partial path's check and the search step
        share it)."""
        if not self._searched:
            self._found, self._searched = self._search_path(s_end), True
        return self._found

    def _search_path(self, s_end: float) -> tuple[FloatArray, bool, int] | None:
        space = self.search_space(s_end)
        if space is None:
            return None
        if self.cfg.search_method == "hybrid":
            return self.hybrid_path(space)
        return self.lattice_path(space, s_end)

    def hybrid_path(self, space: _SearchSpace) -> tuple[FloatArray, bool, int] | None:
        """Hybrid A* from the vehicle's pose: its chords are what the vehicle drives and what
        the gate was checked against during the search, so they are published as they are."""
        gate = self.gate
        terrain = Terrain(
            gate.hazards.window,
            gate.hazards.clearance_m,
            space.corridor_depth_m,
            space.possible,
            self.step_weight,
            gate.clearance_m + gate.spacing_m / 2.0,
            gate.corridor_clearance_m + gate.spacing_m / 2.0,
            gate.spacing_m,
            gate.swing,
        )
        pose = Pose(self.east, self.north, self.yaw)
        result = hybrid_search(terrain, self.cfg.hybrid, pose, space.goal_a, space.goal_b, space.goal_heading)
        points, reached = self.nose_clear_end(result.points, result.reached_goal)
        if len(points) < 2 or not gate.check(points).ok:
            return None
        return points, reached, result.expansions

    def lattice_path(self, space: _SearchSpace, s_end: float) -> tuple[FloatArray, bool, int] | None:
        """A* over the cell lattice, smoothed, published as the track pure pursuit makes along it."""
        cfg, window = self.cfg, self.gate.hazards.window
        free = space.free
        result = self.lattice_search(space, cfg.search_stride)
        stride = cfg.search_stride
        while not result.reached_goal and stride > 1 and self.way_through(s_end):
            # The lattice missed a channel the cells have: a finer lattice, down to every cell.
            stride -= 1
            finer = self.lattice_search(space, stride)
            expansions = result.expansions + finer.expansions
            result = dataclasses.replace(finer if finer.reached_goal else result, expansions=expansions)
        if len(result.cells) < 2:
            return None
        centres = np.column_stack(window.centre_of(result.cells[:, 0], result.cells[:, 1]))
        centres, reached = self.nose_clear_end(centres, result.reached_goal)
        if len(centres) < 2:
            return None
        for candidate in (smooth(centres, FreeCells(window, free)), centres):
            # What the vehicle drives along it, not the polyline itself, is published and gated.
            track = pursue(candidate, self.east, self.north, self.yaw, cfg.bicycle)
            if track is None or len(track) < 2:
                continue
            points = _decimate(track, _TRACK_SPACING_M)
            if self.gate.check(points).ok:
                return points, reached, result.expansions
        return None

    def nose_clear_end(self, points: FloatArray, reached: bool) -> tuple[FloatArray, bool]:
        """The path cut back until a stop at its end leaves the nose clear (then not reached)."""
        while len(points) >= 2 and not self.gate.nose_clear(points):
            points, reached = points[:-1], False
        return points, reached

    def goal(self, s_end: float) -> tuple[FloatArray, FloatArray, float] | None:
        """The centre-line point furthest along (up to ``s_end``) before the course leaves the
        window shrunk by the goal margin, its frame normal and the corridor half width there."""
        window = self.gate.hazards.window
        res, margin = window.resolution_m, self.cfg.goal_margin_m
        s = np.append(np.arange(self.s0, s_end, res), s_end)
        east, north = self.frame.to_enu(s, np.zeros_like(s))
        inside = (
            (east >= window.origin_east_m + margin)
            & (east <= window.origin_east_m + window.cols * res - margin)
            & (north >= window.origin_north_m + margin)
            & (north <= window.origin_north_m + window.rows * res - margin)
        )
        if not inside[0]:
            return None
        last = len(s) - 1 if inside.all() else int(np.argmin(inside)) - 1
        station = float(s[last])
        heading = float(self.frame.heading_at(station))
        normal = np.array([-math.sin(heading), math.cos(heading)])
        point = np.array([east[last], north[last]])
        return point, normal, float(self.frame.half_width_at(station))

    def publish(
        self,
        path_id: int,
        mode: PlanMode,
        points: FloatArray,
        stations_m: FloatArray | None,
        slow: bool,
        stop_at_end: bool = False,
        top_speed_mps: float = math.inf,
        **figures: Unpack[Figures],
    ) -> PlanResult:
        """The Path for ``points`` with speeds under every cap and ``top_speed_mps``; it ends at
        speed 0 in slow mode and when ``stop_at_end``."""
        cfg = self.cfg
        along = arc_length(points)
        if stations_m is None:
            # A searched path's stations, estimated as the start's plus the length along it, are
            # never behind the true ones: its course speeds come from slightly further on, and the
            # course's end is seen early.
            stations_m = self.s0 + along
        cap = np.minimum(self.speed_caps(points, stations_m), top_speed_mps)
        if slow:
            cap = np.minimum(cap, cfg.slow_speed_mps)
        final = 0.0 if slow or stop_at_end else float(cap[-1])
        speeds = reachable(along, cap, self.start_speed(), final, cfg.max_accel_mps2, cfg.max_decel_mps2)
        self.planner._published = np.column_stack([points, speeds])
        path = Path(
            path_id,
            tuple(PathPoint(float(e), float(n), float(v)) for (e, n), v in zip(points, speeds, strict=True)),
            slow,
        )
        return PlanResult(path, mode, self.s0, self.d0, **figures)

    def speed_caps(self, points: FloatArray, stations_m: FloatArray) -> FloatArray:
        """Each point's speed cap: the course's speed slowed by the footprint cost, the path's
        curvature, the steering rate, the clearance to caution cells, and the health monitor's limit."""
        cfg = self.cfg
        with np.errstate(divide="ignore"):
            turn_cap = np.sqrt(cfg.max_lateral_accel_mps2 / curvature(points, cfg.curvature_window_m))
        course_cap = self.frame.speed_at(stations_m) / (
            1.0 + cfg.cost_speed_gain * self.gate.hazards.cost_at(points[:, 0], points[:, 1])
        )
        vehicle = cfg.vehicle
        steering_cap = steering_rate_cap(
            points, cfg.curvature_window_m, vehicle.wheelbase_m, vehicle.max_steering_rate_radps
        )
        return np.minimum.reduce(
            [turn_cap, course_cap, steering_cap, self.near_cap(points), np.full(len(points), self.max_speed)]
        )

    def near_cap(self, points: FloatArray) -> FloatArray:
        """The speed allowed at each point by its clearance to caution cells."""
        cfg = self.cfg
        return clearance_cap(
            self.gate.hazards.caution_clearance(points[:, 0], points[:, 1]),
            cfg.clearance_m,
            cfg.near_hazard_speed_mps,
            cfg.hazard_speed_gain_mps_per_m,
        )

    def travel_time(self, points: FloatArray, stations_m: FloatArray) -> float:
        """Seconds to drive ``points`` from the vehicle's start speed under their speed caps."""
        cfg = self.cfg
        along = arc_length(points)
        caps = self.speed_caps(points, stations_m)
        speeds = reachable(along, caps, self.start_speed(), np.inf, cfg.max_accel_mps2, cfg.max_decel_mps2)
        return float(travel_time_s(along, speeds))

    def start_speed(self) -> float:
        """The speed a new profile starts from: the vehicle's, or while it is on the last path,
        that path's speed where it is, up to ``speed_lead_mps`` more. Starting every cycle from
        the measured speed would hold the target just ahead of a vehicle that lags its
        acceleration, and the lag would set the acceleration."""
        cfg = self.cfg
        start = max(self.speed, cfg.start_speed_mps)
        last = self.planner._published
        if last is None or len(last) < 2:
            return start
        here = np.array([self.east, self.north])
        step = np.diff(last[:, :2], axis=0)
        length2 = np.maximum(np.einsum("ij,ij->i", step, step), 1e-12)
        t = np.clip(np.einsum("ij,ij->i", here - last[:-1, :2], step) / length2, 0.0, 1.0)
        gap = np.hypot(*(last[:-1, :2] + t[:, None] * step - here).T)
        k = int(np.argmin(gap))
        if gap[k] > cfg.max_path_deviation_m:
            return start
        planned = float(last[k, 2] + t[k] * (last[k + 1, 2] - last[k, 2]))
        return max(start, min(planned, self.speed + cfg.speed_lead_mps))

    def stop(self, **figures: Unpack[Figures]) -> PlanResult:
        """Stand still where the vehicle is: a new one-point path at speed 0, slow mode."""
        path_id = self.planner._new_id()
        self.planner._current = None
        self.planner._published = None
        path = Path(path_id, (PathPoint(self.east, self.north, 0.0),), True)
        figures.setdefault("reached_goal", False)
        return PlanResult(path, PlanMode.STOP, self.s0, self.d0, **figures)


@dataclass(frozen=True)
class _SearchSpace:
    start: tuple[int, int]  # the vehicle's cell
    goal_a: FloatArray  # the goal: the corridor's cross-section from goal_a to goal_b
    goal_b: FloatArray
    goal_heading: float  # the course's heading there
    free: NDArray[np.bool_]  # cells the lattice search may use: every point between them passes, turning
    corridor_depth_m: FloatArray  # how far inside the corridor each cell's centre is (-inf: outside)
    possible: NDArray[np.bool_]  # cells with a point that may pass: where a way can be at all


def _decimate(track: FloatArray, spacing_m: float) -> FloatArray:
    """Every point of a finely stepped track at least ``spacing_m`` of arc after the last kept
    one, and its end: chords of that length stay within spacing^2 / (8 R) of the arcs."""
    step = np.hypot(*np.diff(track, axis=0).T)
    along = np.concatenate(([0.0], np.cumsum(step)))
    keep = np.unique(np.searchsorted(along, np.arange(0.0, along[-1], spacing_m)))
    return np.vstack([track[keep], track[-1:]]) if keep[-1] != len(track) - 1 else track[keep]


def _trim(polyline: FloatArray, point: FloatArray) -> tuple[FloatArray, float]:
    """The polyline from the projection of ``point`` on it, and the distance to that projection."""
    if len(polyline) < 2:
        return polyline, float(np.hypot(*(polyline[0] - point)))
    start, step = polyline[:-1], np.diff(polyline, axis=0)
    length2 = np.einsum("ij,ij->i", step, step)
    t = np.clip(np.einsum("ij,ij->i", point - start, step) / np.maximum(length2, 1e-12), 0.0, 1.0)
    foot = start + t[:, None] * step
    gap = np.hypot(*(foot - point).T)
    best = int(np.argmin(gap))
    return np.vstack([foot[best], polyline[best + 1 :]]), float(gap[best])


def _distance_to_segment(east: FloatArray, north: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distance from points to the segment a-b."""
    direction = b - a
    length2 = float(direction @ direction)
    rel_e, rel_n = east - a[0], north - a[1]
    t = np.clip((rel_e * direction[0] + rel_n * direction[1]) / max(length2, 1e-12), 0.0, 1.0)
    return np.hypot(rel_e - t * direction[0], rel_n - t * direction[1])
