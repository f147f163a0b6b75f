"""The simulated vehicle in its world: applies actuator commands and publishes the truth.

Each 100 Hz tick applies the newest ActuatorCommand to the vehicle dynamics, checks the footprint
against the scenario's obstacles and the RDDF corridor, and publishes SimTruth on its sim-only
channel. Collisions and corridor exits are counted in SimTruth and reported once each, when they
begin, as HealthEvents. Like real actuators, the vehicle keeps executing the last command it got
until a new one arrives: stopping a vehicle whose commands went stale is the control module's job.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from brain.vehicle import VehicleGeometry
from modules.sim.collision import collides, footprint
from modules.sim.scenario import DEFAULT_SCENARIO, Scenario, load_scenario
from modules.sim.vehicle import VehicleParams, VehicleState, step
from modules.sim.world import WorldObstacle
from protocol import channels
from protocol.codec import Envelope
from protocol.messages import ActuatorCommand, Severity, SimTruth
from rascal.runtime.config import section, setting
from rascal.runtime.module import Module
from rascal.runtime.ports import Port

PARKED = ActuatorCommand(throttle=0.0, brake=1.0, steering_rad=0.0, stop_reason="not yet commanded")
# A late tick steps the physics by the time that really passed, so simulated time stays shared
# time: every truth stamp, and every sensor stamp made from it, then agrees with how far the
# vehicle moved. Longer gaps (a stopped process) are not caught up.
MAX_CATCH_UP_S = 0.2
PROGRESS_SEARCH_M = 60  # route points searched around the last match each step
WATCH_SLACK_M = 1e-6  # for rounding: a watched answer is asked again this much before it could change


@dataclass(frozen=True)
class SimConfig:
    scenario: str = setting(str(DEFAULT_SCENARIO), "scenario TOML file")
    rate_hz: float = setting(100.0, "simulation and SimTruth rate")
    vehicle: VehicleGeometry = section(VehicleGeometry, "the simulated vehicle's footprint and steering")


class Simulator(Module):
    """Vehicle dynamics and world: ActuatorCommand in, SimTruth (100 Hz) and collision events out."""

    name = "sim"
    default_source_id = 5
    Config = SimConfig
    interface = (
        Port("in", "`ACTUATOR_COMMAND`", "ActuatorCommand", "50 Hz (control)", "none: the last command is held"),
        Port(
            "out",
            "`SIM_TRUTH`",
            "SimTruth (pose, speed, progress, collisions, corridor exits, scenario time)",
            "`rate_hz` (100)",
        ),
        Port("out", "`HEALTH`", "HealthEvent `collision`, `corridor_exit` (once each, when it begins)", "on event"),
        Port("out", "`MODULE_STATUS`", "ModuleStatus", "1 Hz"),
    )

    def __init__(self, config: SimConfig, runtime: object, scenario: Scenario | None = None) -> None:
        super().__init__(config, runtime)  # type: ignore[arg-type]
        self.scenario = scenario

    def on_start(self) -> None:
        if self.scenario is None:
            self.scenario = load_scenario(self.config.scenario)
        self.world = WorldState(self.scenario, VehicleParams(geometry=self.config.vehicle))
        self.command = PARKED
        self.dt_s = 1.0 / self.config.rate_hz
        self.last_tick_ns: int | None = None
        # Read when the next tick's wait ends, as the tick only uses the newest command: a command
        # need not wake the simulator between ticks.
        self.bus.subscribe(channels.ACTUATOR_COMMAND, self.on_command, wake=False)
        self.every(self.dt_s, self.tick, priority=5)

    def on_command(self, command: ActuatorCommand, _envelope: Envelope) -> None:
        self.command = command

    def tick(self) -> None:
        now = self.now_ns()
        elapsed_s = self.dt_s if self.last_tick_ns is None else (now - self.last_tick_ns) / 1e9
        self.last_tick_ns = now
        elapsed_s = min(max(elapsed_s, 0.0), MAX_CATCH_UP_S)
        # Steps no longer than the nominal one, so a late tick integrates exactly as punctual ones.
        steps = max(1, math.ceil(elapsed_s / self.dt_s - 1e-6))
        for _ in range(steps):
            for code, text in self.world.advance(self.command, elapsed_s / steps):
                self.report(Severity.ERROR, code, text)
        self.bus.publish(channels.SIM_TRUTH, self.world.truth(), t_meas_ns=now)

    def status_detail(self) -> str:
        world = self.world
        return (
            f"{world.progress_m:.0f}/{world.route_length_m:.0f} m, {world.state.speed_mps:.1f} m/s, "
            f"collisions {world.collisions}, corridor exits {world.corridor_exits}"
        )


class Watch:
    """When a yes/no question about the footprint can next change its answer. Its measure (the
    corridor clearance, the gap to the obstacles) changes no faster than the footprint moves, so
    after an evaluation that left ``margin_m`` between it and the answer's edge, the answer stands
    until the footprint has moved that far."""

    def __init__(self) -> None:
        self.margin_m = 0.0
        self.moved_m = 0.0

    def due(self) -> bool:
        return self.moved_m >= self.margin_m

    def evaluated(self, margin_m: float) -> None:
        self.margin_m = margin_m - WATCH_SLACK_M
        self.moved_m = 0.0


class WorldState:
    """The vehicle in the scenario, stepped without any I/O (so tests and benchmarks drive it)."""

    def __init__(self, scenario: Scenario, params: VehicleParams) -> None:
        self.scenario = scenario
        self.params = params
        east, north, yaw = scenario.start_pose()
        self.state = VehicleState(east_m=east, north_m=north, yaw_rad=yaw)
        self.obstacles = scenario.world.obstacles
        self.corridor = scenario.course.corridor
        self.route_east = scenario.route.east_m
        self.route_north = scenario.route.north_m
        self.route_s = scenario.route.s_m
        self.route_length_m = float(scenario.route.length_m)
        self._route_index = 0
        self.progress_m = 0.0
        self.collisions = 0
        self.corridor_exits = 0
        self._touching: str | None = None
        self._outside = False
        self.elapsed_s = 0.0
        # Every point of the footprint lies within this of the rear axle, so a turn by an angle
        # moves none of them farther than this times the angle.
        self._reach_m = math.hypot(
            max(params.length_m - params.rear_overhang_m, params.rear_overhang_m), params.width_m / 2
        )
        self._obstacle_xy = np.array([(o.east_m, o.north_m) for o in self.obstacles], dtype=float).reshape(-1, 2)
        # Within these of an obstacle's centre, collides() looks closer (its prefilter).
        half_diagonal = 0.5 * math.hypot(params.length_m, params.width_m)
        self._obstacle_limit_m = half_diagonal + np.array(
            [o.radius_m + 0.5 * (o.length_m + o.width_m) for o in self.obstacles], dtype=float
        )
        self._corridor_watch = Watch()
        self._obstacle_watch = Watch()

    def advance(self, command: ActuatorCommand, dt_s: float) -> list[tuple[str, str]]:
        """One step; returns the events that began in it as (code, text)."""
        state = self.state
        east, north, yaw = state.east_m, state.north_m, state.yaw_rad
        step(state, command, dt_s, self.params)
        moved = math.hypot(state.east_m - east, state.north_m - north) + self._reach_m * abs(
            math.remainder(state.yaw_rad - yaw, math.tau)
        )
        self._corridor_watch.moved_m += moved
        self._obstacle_watch.moved_m += moved
        self.elapsed_s += dt_s
        self._update_progress()
        events = []
        hit = self._collision()
        if hit is not None and hit.name != self._touching:
            self.collisions += 1
            events.append(("collision", f"hit {hit.name} at {self.progress_m:.0f} m, {state.speed_mps:.1f} m/s"))
        self._touching = hit.name if hit is not None else None
        outside = self._outside_corridor()
        if outside and not self._outside:
            self.corridor_exits += 1
            events.append(("corridor_exit", f"left the corridor at {self.progress_m:.0f} m"))
        self._outside = outside
        return events

    def _collision(self) -> WorldObstacle | None:
        """collides(), asked only when the footprint may have come within its prefilter's reach
        of an obstacle since it was last farther than that from all of them."""
        watch = self._obstacle_watch
        if not watch.due():
            return None
        state = self.state
        centre = footprint(state, self.params)
        gaps = np.hypot(self._obstacle_xy[:, 0] - centre.east_m, self._obstacle_xy[:, 1] - centre.north_m)
        gap = float((gaps - self._obstacle_limit_m).min()) if len(gaps) else math.inf
        watch.evaluated(gap)
        return collides(state, self.obstacles, self.params) if gap <= 0.0 else None

    def _outside_corridor(self) -> bool:
        """Whether a footprint corner is outside the corridor, evaluated only when the answer may
        have changed: the corridor's edge distance is the watched measure."""
        watch = self._corridor_watch
        if not watch.due():
            return self._outside
        corners = np.array(footprint(self.state, self.params).corners())
        clearance = self.corridor.distance_to_edge(corners[:, 0], corners[:, 1])
        nearest = float(clearance.min())
        watch.evaluated(abs(nearest))
        return nearest < 0.0

    def truth(self) -> SimTruth:
        s = self.state
        return SimTruth(
            s.east_m,
            s.north_m,
            s.yaw_rad,
            s.speed_mps,
            s.yaw_rate_radps,
            s.steering_rad,
            self.progress_m,
            self.collisions,
            s.accel_mps2,
            self.corridor_exits,
            self.elapsed_s,
        )

    def _update_progress(self) -> None:
        # The nearest route point near the last one: progress along the course, never a jump to
        # a distant part of the route that happens to pass close by.
        low = max(0, self._route_index - PROGRESS_SEARCH_M)
        high = min(len(self.route_s), self._route_index + PROGRESS_SEARCH_M)
        d = np.hypot(self.route_east[low:high] - self.state.east_m, self.route_north[low:high] - self.state.north_m)
        self._route_index = low + int(np.argmin(d))
        self.progress_m = float(self.route_s[self._route_index])

    @property
    def finished(self) -> bool:
        return self.route_length_m - self.progress_m < 1.5
