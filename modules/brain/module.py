"""The brain process: fuses every sensor's descriptors into the hazard map, judges sensor health,
and plans inside the RDDF corridor (brain/fusion, brain/health, brain/planning).

Each planning cycle (``plan_rate_hz``, 10 by default) reads the newest vehicle state, the cost
map and the drive mode's speed cap, and publishes a Path stamped with the state's measurement
time. A change of drive mode (lidars silent, blind, navigation lost...) is a HealthEvent the
moment a cycle sees it. A map snapshot goes out on MAP_SNAPSHOT once a second. Standing still
is watched (brain/stall.py): a blocked corridor is reported, a stall re-planned, and where either
lasts, the vehicle backs up along the way it came (brain/planning/backup.py) and plans afresh.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from brain.course_config import DEFAULT_COURSE, load_course
from brain.fusion.cost import CostConfig, CostMap
from brain.fusion.fusion import FusionConfig, HazardFusion
from brain.health import HORIZONTAL_LIDARS, LIDARS, STEREO, DriveMode, HealthParams, SensorHealth
from brain.planning.backup import BackUp, BackUpSettings, FloatArray, Trail, back_up
from brain.planning.config import PlannerConfig
from brain.planning.planner import PlanMode, Planner, PlanResult
from brain.stall import STANDING_MPS, StallWatch, Standing, leads_on
from protocol import channels
from protocol.codec import Envelope
from protocol.messages import (
    GroundSweep,
    LaneBorders,
    ObstacleList,
    Path,
    PathPoint,
    Sensor,
    Severity,
    StopCommand,
    StopMode,
    SurfaceProfile,
    VehicleState,
)
from rascal.runtime.config import section, setting
from rascal.runtime.module import Module, Runtime
from rascal.runtime.ports import Port

SENSOR_NAMES = {
    Sensor.LIDAR_H_LEFT: "lidar_h_left",
    Sensor.LIDAR_H_RIGHT: "lidar_h_right",
    Sensor.LIDAR_V_LEFT: "lidar_v_left",
    Sensor.LIDAR_V_RIGHT: "lidar_v_right",
    Sensor.LIDAR_SWEEP: "lidar_sweep",
    Sensor.ESVS: STEREO,
}
OBSTACLE_SENSORS = (*HORIZONTAL_LIDARS, STEREO)  # whose age a path's t_input_ns reports
CYCLES_KEPT = 3000  # planning cycles the heartbeat's p99 spans: 5 min at 10 Hz
NO_CAP_MPS = 100.0  # "no cap" for the planner, which wants a finite limit (the course's apply anyway)
FINISH_M = 5.0  # standing this close to the course's end is the finish (the referee's distance)
BLOCKED_SEARCH_PERIOD_S = 1.0  # standing at a blocked corridor: how often to look for a way again
BACKED_UP_M = 1.0  # standing this close to a back-up's end: it is over (control stops ~0.5 m short)
MODE_SEVERITY = {
    DriveMode.NORMAL: Severity.INFO,
    DriveMode.LIDAR_DEGRADED: Severity.WARNING,
    DriveMode.STEREO_ONLY: Severity.WARNING,
    DriveMode.LIDAR_ONLY: Severity.WARNING,
    DriveMode.BLIND: Severity.CRITICAL,
    DriveMode.NAV_LOST: Severity.CRITICAL,
}


@dataclass(frozen=True)
class BrainConfig:
    course: str = setting(str(DEFAULT_COURSE), "RDDF file: the corridor and speed limits planned in")
    origin: str = setting("", "ENU origin 'lat,lon[,alt]' overriding the course's first waypoint")
    plan_rate_hz: float = setting(10.0, "planning cycles (and Path messages) per second")
    plan_on_stereo: bool = setting(
        True, "a stereo report (the slowest obstacle input) is planned on at once; the rate is the fallback"
    )
    snapshot_rate_hz: float = setting(1.0, "map snapshots per second on MAP_SNAPSHOT (0: none)")
    snapshot_downsample: int = setting(2, "snapshot cells are this many map cells a side (max of each block)")
    sensors: tuple[str, ...] = setting((*LIDARS, STEREO), "obstacle sensors this vehicle has (health expects them)")
    lidar_max_age_s: float = setting(0.2, "a lidar silent this long is dead")
    stereo_max_age_s: float = setting(0.5, "the ESVS silent this long is dead")
    navigation_max_age_s: float = setting(0.2, "vehicle state this old is lost")
    blocked_after_s: float = setting(3.0, "standing this long with nothing reachable ahead: corridor_blocked")
    stall_after_s: float = setting(5.0, "standing this long with a way ahead: stalled, plan afresh (and again)")
    back_up_m: float = setting(6.0, "a stall or blockage that lasts backs the vehicle up this far along its trail")
    back_up_speed_mps: float = setting(1.0, "backing-up speed")
    fusion: FusionConfig = section(FusionConfig, "the hazard map: window, evidence and how it fades")
    cost: CostConfig = section(CostConfig, "the hazard map's costs: what is lethal, what is caution")
    planner: PlannerConfig = section(PlannerConfig, "the planner: footprint, margins, candidates, searches")


class Brain(Module):
    """Bird's-eye hazard map from every sensor, sensor health, and the planner in the corridor."""

    name = "brain"
    default_source_id = 30
    Config = BrainConfig
    interface = (
        Port(
            "in",
            "`VEHICLE_STATE`",
            "VehicleState (pose, covariance, quality)",
            "100 Hz",
            "`navigation_max_age_s` 0.2 s",
        ),
        Port("in", "`OBSTACLES_LIDAR`", "ObstacleList (horizontal lidars)", "2 x 25 Hz", "`lidar_max_age_s` 0.2 s"),
        Port(
            "in",
            "`OBSTACLES_ESVS`",
            "ObstacleList (stereo): a report starts a planning cycle at once",
            "10 Hz",
            "`stereo_max_age_s` 0.5 s",
        ),
        Port("in", "`SURFACE_PROFILE`", "SurfaceProfile (vertical lidars)", "2 x 25 Hz", "`lidar_max_age_s`"),
        Port("in", "`GROUND_SWEEP`", "GroundSweep (sweeping lidar)", "37.5 Hz", "`lidar_max_age_s`"),
        Port("in", "`LANE_BORDERS`", "LaneBorders", "as published"),
        Port("in", "`STOP`", "StopCommand: an operator's hold is not a stall", "on order"),
        Port("out", "`PATH`", "Path, stamped with the vehicle state's measurement time", "`plan_rate_hz` (10)"),
        Port(
            "out",
            "`MAP_SNAPSHOT`",
            "MapSnapshot (hazard probability, `snapshot_downsample` cells a side)",
            "`snapshot_rate_hz` (1)",
        ),
        Port(
            "out",
            "`HEALTH`",
            "`drive_mode`, `plan_refused`, `corridor_blocked`, `stalled`, `backing_up`, `moving_again`",
            "on event",
        ),
        Port("out", "`MODULE_STATUS`", "ModuleStatus: mode, plan, cycle time and its p99, messages fused", "1 Hz"),
    )

    def __init__(self, config: BrainConfig, runtime: Runtime) -> None:
        super().__init__(config, runtime)
        self.state: VehicleState | None = None
        self.state_t_ns = 0
        self.mode: DriveMode | None = None
        self.last: PlanResult | None = None
        self.cycle_ms = 0.0
        self.cycles_ms: deque[float] = deque(maxlen=CYCLES_KEPT)  # for the heartbeat's p99
        self.plain_cycles_ms: deque[float] = deque(maxlen=CYCLES_KEPT)  # ... of those that ran no search
        self.last_rephase_ns = 0  # monotonic time a stereo report last started a cycle
        self.last_search_ns = 0  # monotonic time the planner last ran
        self.published = 0
        self.refused = 0
        self.trail = Trail()  # where the vehicle came from: known drivable
        self.backing: Backing | None = None

    def on_start(self) -> None:
        config = self.config
        unknown = sorted(set(config.sensors) - set(SENSOR_NAMES.values()))
        if unknown or not config.plan_rate_hz > 0 or config.snapshot_rate_hz < 0:
            raise ValueError(f"brain: bad settings (unknown sensors {unknown}, or rates not positive)")
        if not set(config.sensors) & {*HORIZONTAL_LIDARS, STEREO}:
            raise ValueError("brain: sensors must include an obstacle sensor (a horizontal lidar or esvs)")
        cv2.setNumThreads(1)  # the fusion and planning budgets are shares of one core
        course = load_course(config.course, config.origin)
        bus = self.bus
        self.planner = Planner.for_course(course, config.planner)
        finish_m = course.interpolate().length_m - FINISH_M
        self.stall = StallWatch(finish_m, config.blocked_after_s, config.stall_after_s)
        self.corridor = course.corridor
        self.back_up_settings = BackUpSettings(
            config.back_up_m, config.back_up_speed_mps, trail_clearance_m=config.planner.corridor_clearance_m
        )
        # Only to tell an operator's hold from a stall. The operator's orders, not control's 50 Hz
        # commands: those are signed, and verifying each would cost more than the stall watch.
        self.held_by_operator = False
        bus.subscribe(channels.STOP, self.on_stop_order)
        self.fusion = HazardFusion(config.fusion, cost=config.cost)
        params = HealthParams(config.lidar_max_age_s, config.stereo_max_age_s, config.navigation_max_age_s)
        self.health = SensorHealth(params, expected=tuple(config.sensors))
        bus.subscribe(channels.VEHICLE_STATE, self.on_vehicle_state)
        bus.subscribe(channels.OBSTACLES_LIDAR, self.on_obstacles)
        bus.subscribe(channels.OBSTACLES_ESVS, self.on_obstacles)
        bus.subscribe(channels.SURFACE_PROFILE, self.on_profile)
        bus.subscribe(channels.GROUND_SWEEP, self.on_sweep)
        bus.subscribe(channels.LANE_BORDERS, self.on_lanes)
        self.every(1.0 / config.plan_rate_hz, self.plan, priority=5)
        if config.snapshot_rate_hz > 0:
            self.every(1.0 / config.snapshot_rate_hz, self.snapshot, priority=1)

    # -- inputs -------------------------------------------------------------------------------

    def on_vehicle_state(self, state: VehicleState, envelope: Envelope) -> None:
        self.fusion.add_pose(envelope.t_meas_ns, state)
        if envelope.t_meas_ns >= self.state_t_ns:  # a late state must not replace a newer one
            self.state, self.state_t_ns = state, envelope.t_meas_ns
            self.health.heard_navigation(state, envelope.t_meas_ns)

    def on_obstacles(self, message: ObstacleList, envelope: Envelope) -> None:
        self._heard(message.sensor, envelope.t_meas_ns)
        self.fusion.add_obstacles(envelope.t_meas_ns, message)
        if message.sensor == Sensor.ESVS and self.config.plan_on_stereo:
            self._plan_soon()

    def on_stop_order(self, order: StopCommand, _envelope: Envelope) -> None:
        self.held_by_operator = order.mode != StopMode.RUN

    def _plan_soon(self) -> None:
        """Plan now: the ESVS's report is the obstacle input that waits longest (exposure,
        processing), so planning on its arrival, not up to a period later, is what keeps
        obstacle-to-actuator latency low. The grid becomes the fallback, next due 1.5 periods
        on: while reports come at the planning rate it never fires just ahead of one (with
        stale stereo data), and when they stop it plans on at its rate. At most one report per
        half period plans, so a faster ESVS cannot more than double the planning rate."""
        period_s = 1.0 / self.config.plan_rate_hz
        now = time.monotonic_ns()
        if now - self.last_rephase_ns < period_s * 0.5e9:
            return
        self.last_rephase_ns = now
        self.plan()
        self.runtime.set_period("plan", period_s, first_in_s=1.5 * period_s)

    def on_profile(self, message: SurfaceProfile, envelope: Envelope) -> None:
        self._heard(message.sensor, envelope.t_meas_ns)
        self.fusion.add_profile(envelope.t_meas_ns, message)

    def on_sweep(self, message: GroundSweep, envelope: Envelope) -> None:
        self._heard(message.sensor, envelope.t_meas_ns)
        self.fusion.add_ground_sweep(envelope.t_meas_ns, message)

    def on_lanes(self, message: LaneBorders, envelope: Envelope) -> None:
        self.fusion.add_lane_borders(envelope.t_meas_ns, message)

    def _heard(self, sensor: int, t_meas_ns: int) -> None:
        try:
            name = SENSOR_NAMES.get(Sensor(sensor))
        except ValueError:
            return  # a sensor id this build does not know: fusion counts it too
        if name is not None:
            self.health.heard(name, t_meas_ns)

    # -- cycles -------------------------------------------------------------------------------

    def plan(self) -> None:
        started = time.perf_counter()
        assessment = self.health.assess(self.now_ns())
        if assessment.mode is not self.mode:
            before, self.mode = self.mode, assessment.mode
            text = f"{before.value if before else 'start'} -> {assessment.mode.value}: {assessment.reason}"
            self.report(MODE_SEVERITY[assessment.mode], "drive_mode", text)
        state = self.state
        cost_map = self.fusion.cost_map() if self.fusion.window is not None else None
        if state is None or cost_map is None:
            return  # nothing to plan from: control brakes on the missing path
        cap = min(assessment.speed_cap_mps, NO_CAP_MPS)
        # The planner plans forwards: to it, rolling backwards is standing (and the filter's speed
        # wanders a few mm/s below zero at rest). Backing up is moving, though, to the stall watch.
        pose = state._replace(speed_mps=max(0.0, state.speed_mps))
        if self.backing is not None and (cap <= 0.0 or self.backing.over(state, self.now_ns())):
            self.end_backing()  # done, or the drive mode no longer lets it drive
        if state.speed_mps > STANDING_MPS:
            self.trail.add(state.east_m, state.north_m)
        backing = self.backing is not None
        resting = backing or self.resting_at_a_blockage(pose.speed_mps)
        if not resting:
            try:
                self.last = self.planner.plan(pose, cost_map.window, cost_map.hazard_probability, cost_map.cost, cap)
            except ValueError as exc:  # a non-finite state: no path this cycle, control brakes on its age
                self.refused += 1
                if self.refused == 1 or self.refused % 100 == 0:
                    self.report(Severity.ERROR, "plan_refused", f"{exc} ({self.refused} cycles so far)")
                return
            self.last_search_ns = time.monotonic_ns()
        assert self.last is not None
        if not backing:
            self.watch_standing(abs(state.speed_mps), self.last, state, cost_map if cap > 0.0 else None)
        oldest = self.health.oldest_live_ns(OBSTACLE_SENSORS, self.now_ns())
        path = (self.backing.path if self.backing is not None else self.last.path)._replace(t_input_ns=oldest or 0)
        self.bus.publish(channels.PATH, path, t_meas_ns=self.state_t_ns)
        self.published += 1
        if not resting:
            self.cycle_ms = (time.perf_counter() - started) * 1e3
            self.cycles_ms.append(self.cycle_ms)
            if self.last.expansions == 0:  # searches are benchmarked apart (100 ms, not 20 ms)
                self.plain_cycles_ms.append(self.cycle_ms)

    def resting_at_a_blockage(self, speed_mps: float) -> bool:
        """Standing at a blocked corridor, the search that finds nothing runs once a second, not
        every cycle (up to its expansion cap each time: most of a core at 10 Hz); between, the
        stop path is sent again, so control keeps a fresh path and holds the vehicle."""
        return (
            self.last is not None
            and self.stall.state is Standing.BLOCKED
            and speed_mps < STANDING_MPS
            and time.monotonic_ns() - self.last_search_ns < BLOCKED_SEARCH_PERIOD_S * 1e9
        )

    def watch_standing(self, speed_mps: float, plan: PlanResult, state: VehicleState, cost_map: CostMap | None) -> None:
        """Report a blocked corridor or a stall; on a stall, plan afresh from where it stands, or
        back up first when that did not help (only with a map, and never while the drive mode
        forbids driving: ``cost_map`` None)."""
        # A search that ends short of its goal leads only to the reachable cells nearest it.
        searched_through = plan.mode is PlanMode.SEARCH and plan.reached_goal
        planned_on = plan.mode in (PlanMode.KEEP, PlanMode.REPLAN) or searched_through
        way_ahead = planned_on and leads_on(plan.path, state.east_m, state.north_m)
        way_back = self.way_back(state, cost_map) if speed_mps < STANDING_MPS and cost_map is not None else None
        now = self.now_ns()
        events = self.stall.update(
            now, speed_mps, plan.station_m, way_ahead, self.held_by_operator, way_back is not None
        )
        for event in events:
            self.report(event.severity, event.code, event.text)
            if event.back_up and way_back is not None:
                self.start_backing(way_back, now)
            elif event.recover:
                self.planner.reset()

    def way_back(self, state: VehicleState, cost_map: CostMap) -> BackUp | None:
        """Back along the trail, inside the corridor; beyond the trail, clear on the map too."""
        settings = self.back_up_settings
        window, hazard = cost_map.window, np.asarray(cost_map.hazard_probability)
        caution = self.planner.config.caution_probability
        offsets = np.arange(-settings.clearance_m, settings.clearance_m + 1e-9, window.resolution_m)

        def to_edge(east: FloatArray, north: FloatArray) -> FloatArray:
            return np.asarray(self.corridor.distance_to_edge(east, north), dtype=float)

        def free(east: FloatArray, north: FloatArray) -> np.ndarray:
            # Every known cell in a square of the clearance around each point is below caution.
            square_east, square_north = np.broadcast_arrays(
                east[:, None, None] + offsets[None, None, :], north[:, None, None] + offsets[None, :, None]
            )
            rows, cols = window.cell_of(square_east, square_north)
            known = window.inside(rows, cols)
            risky = np.zeros(rows.shape, dtype=bool)
            risky[known] = hazard[rows[known], cols[known]] >= caution
            return ~risky.any(axis=(1, 2))

        return back_up(self.trail, state.east_m, state.north_m, state.yaw_rad, to_edge, free, settings)

    def start_backing(self, way: BackUp, now_ns: int) -> None:
        speed = self.back_up_settings.speed_mps
        points = tuple(PathPoint(e, n, v) for (e, n), v in zip(way.points, way.speeds(speed), strict=True))
        path = Path(self.planner.new_path_id(), points, slow_mode=True, reverse=True)
        # Time enough to change gear twice and drive it at half the speed.
        deadline_ns = now_ns + int((10.0 + 2.0 * way.length_m / speed) * 1e9)
        self.backing = Backing(path, deadline_ns)
        self.trail.drop_newest(way.trail_used)

    def end_backing(self) -> None:
        self.backing = None
        self.stall.backed_up()
        self.planner.reset()

    def snapshot(self) -> None:
        if self.fusion.window is not None:
            self.bus.publish(channels.MAP_SNAPSHOT, self.fusion.snapshot(self.config.snapshot_downsample))

    def status_detail(self) -> str:
        mode = self.mode.value if self.mode else "starting"
        if self.last is None:
            return f"{mode}; no path yet (vehicle state or map missing)"
        plan = self.last
        speed = plan.path.points[0].speed_mps if plan.path.points else 0.0
        stats = self.fusion.stats
        standing = "" if self.stall.state is Standing.MOVING else f" [{self.stall.state.value}]"
        return (
            f"{mode}{standing}; {plan.mode.value} path {plan.path.path_id} at s={plan.station_m:.0f} m, "
            f"{speed:.1f} m/s{' SLOW' if plan.slow_mode else ''}; cycle {self.cycle_ms:.1f} ms "
            f"(p99 {_p99(self.cycles_ms)}, {_p99(self.plain_cycles_ms)} without a search); "
            f"fused {stats.messages} msgs, refused no-pose {stats.no_pose}"
        )


def _p99(values: deque[float]) -> str:
    return f"{np.percentile(values, 99):.1f}" if values else "-"


@dataclass(frozen=True)
class Backing:
    """A back-up under way: its path, sent each cycle until the vehicle stands at its end (or time runs out)."""

    path: Path
    deadline_ns: int

    def over(self, state: VehicleState, now_ns: int) -> bool:
        end = self.path.points[-1]
        arrived = math.hypot(state.east_m - end.east_m, state.north_m - end.north_m) < BACKED_UP_M
        return (arrived and abs(state.speed_mps) < STANDING_MPS) or now_ns > self.deadline_ns
