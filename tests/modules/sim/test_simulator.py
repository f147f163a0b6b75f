"""The simulator: commands move the vehicle; collisions and corridor exits are counted once."""

from __future__ import annotations

import itertools
import math
import uuid
from pathlib import Path

import numpy as np
import pytest

from modules.sim.collision import collides, footprint
from modules.sim.scenario import DEFAULT_SCENARIO, load_scenario
from modules.sim.simulator import SimConfig, Simulator, WorldState
from modules.sim.vehicle import VehicleParams
from protocol import channels
from protocol.auth import Keyring
from protocol.messages import ActuatorCommand, HealthEvent, SimTruth
from protocol.transport import MemTransport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import ManualClock
from rascal.runtime.module import Runtime

THROTTLE = ActuatorCommand(0.6, 0.0, 0.0)


def scenario_file(tmp_path: Path, extra: str = "") -> Path:
    (tmp_path / "course.rddf").write_text("1,34.8650000,-116.8900000,20,25\n2,34.8650000,-116.8790000,20,25\n")
    path = tmp_path / "straight.toml"
    path.write_text('[scenario]\nrddf = "course.rddf"\nseed = 1\n' + extra)
    return path


def drive(world: WorldState, command: ActuatorCommand, seconds: float) -> list[tuple[str, str]]:
    events = []
    for _ in range(round(seconds * 100)):
        events += world.advance(command, 0.01)
    return events


def test_throttle_moves_the_vehicle_along_the_course(tmp_path: Path) -> None:
    world = WorldState(load_scenario(scenario_file(tmp_path)), VehicleParams())
    drive(world, THROTTLE, 10.0)
    assert world.progress_m > 30 and world.state.speed_mps > 5
    assert world.collisions == 0 and world.corridor_exits == 0


def test_hitting_an_obstacle_counts_one_collision_and_reports_it_once(tmp_path: Path) -> None:
    rock = "[[obstacle]]\nname = 'rock'\nshape = 'box'\nat_m = 30.0\nlength_m = 1.0\nwidth_m = 3.0\nheight_m = 1.0\n"
    world = WorldState(load_scenario(scenario_file(tmp_path, rock)), VehicleParams())
    events = drive(world, ActuatorCommand(0.3, 0.0, 0.0), 15.0)
    assert world.collisions == 1
    assert [code for code, _text in events] == ["collision"]


def test_leaving_the_corridor_counts_one_exit(tmp_path: Path) -> None:
    world = WorldState(load_scenario(scenario_file(tmp_path)), VehicleParams())
    events = drive(world, ActuatorCommand(0.4, 0.0, 0.4), 8.0)
    assert world.corridor_exits >= 1
    assert events[0][0] == "corridor_exit"


def test_the_default_scenario_starts_inside_the_corridor_at_rest() -> None:
    world = WorldState(load_scenario(DEFAULT_SCENARIO), VehicleParams())
    assert world.advance(ActuatorCommand(0.0, 1.0, 0.0), 0.01) == []
    assert world.truth().speed_mps == 0.0


def test_runs_are_deterministic() -> None:
    scenario = load_scenario(DEFAULT_SCENARIO)
    first, second = WorldState(scenario, VehicleParams()), WorldState(scenario, VehicleParams())
    for world in (first, second):
        drive(world, ActuatorCommand(0.5, 0.0, 0.05), 5.0)
    assert first.truth() == second.truth()


@pytest.fixture
def rig(tmp_path: Path):
    hub, keyring, clock = uuid.uuid4().hex, Keyring.generate(), ManualClock()
    runtime = Runtime(Bus(MemTransport(hub), 5, keyring, clock), clock)
    sim = Simulator(SimConfig(), runtime, scenario=load_scenario(scenario_file(tmp_path)))
    sim.on_start()
    peer = Bus(MemTransport(hub), 9, keyring, clock)
    return sim, peer, clock


def test_module_applies_commands_and_publishes_truth(rig) -> None:
    sim, peer, clock = rig
    truths: list[SimTruth] = []
    peer.subscribe(channels.SIM_TRUTH, lambda msg, env: truths.append(msg))
    peer.publish(channels.ACTUATOR_COMMAND, THROTTLE)
    sim.bus.poll()
    for _ in range(300):
        clock.advance(10_000_000)
        sim.tick()
        peer.poll()
    assert len(truths) == 300
    assert truths[-1].speed_mps > 3 and truths[-1].scenario_time_s == pytest.approx(3.0)


def test_module_keeps_the_vehicle_braked_until_commanded(rig) -> None:
    sim, peer, clock = rig
    events: list[HealthEvent] = []
    peer.subscribe(channels.HEALTH, lambda msg, env: events.append(msg))
    for _ in range(100):
        clock.advance(10_000_000)
        sim.tick()
    assert sim.world.truth().progress_m == 0.0 and sim.world.state.speed_mps == 0.0


def test_late_ticks_step_the_time_that_passed_so_stamps_match_the_motion(rig) -> None:
    """A tick 35 ms late steps 35 ms of physics (in 10 ms steps): scenario time follows shared
    time, and a sensor differentiating or integrating over the stamps sees the true motion."""
    sim, peer, clock = rig
    stamped: list[tuple[int, SimTruth]] = []
    peer.subscribe(channels.SIM_TRUTH, lambda msg, env: stamped.append((env.t_meas_ns, msg)))
    peer.publish(channels.ACTUATOR_COMMAND, THROTTLE)
    sim.bus.poll()
    gaps_ms = [10, 10, 45, 10, 25, 10, 10, 300, 10] * 20
    for gap in gaps_ms:
        clock.advance(gap * 1_000_000)
        sim.tick()
        peer.poll()
    (t_first, first), (t_last, last) = stamped[0], stamped[-1]
    # Every gap but the 300 ms ones (beyond the catch-up limit, which step 200 ms) is stepped in full.
    assert last.scenario_time_s - first.scenario_time_s == pytest.approx((t_last - t_first) / 1e9 - 20 * 0.1)
    for (t0, a), (t1, b) in itertools.pairwise(stamped):
        dt = (t1 - t0) / 1e9
        if dt <= 0.2:
            assert b.scenario_time_s - a.scenario_time_s == pytest.approx(dt)


def test_collisions_and_corridor_exits_are_found_on_the_step_they_begin_however_seldom_they_are_asked() -> None:
    # A weaving drive through the default course: every step, the answers asked only when the
    # footprint may have moved far enough to change them are the answers of asking every step.
    scenario = load_scenario(DEFAULT_SCENARIO)
    world = WorldState(scenario, VehicleParams())
    params, corridor = world.params, scenario.course.corridor
    route = scenario.route
    touching, outside = None, False
    for k in range(12_000):
        state = world.state
        ahead = min(world._route_index + 6, len(route.s_m) - 1)
        bearing = math.atan2(route.north_m[ahead] - state.north_m, route.east_m[ahead] - state.east_m)
        weave = (0.0, 1.2, 0.0, -1.2)[k // 400 % 4]
        steering = 1.5 * math.remainder(bearing - state.yaw_rad, math.tau) + weave
        events = world.advance(ActuatorCommand(0.7 if state.speed_mps < 8.0 else 0.0, 0.0, steering), 0.01)
        hit = collides(world.state, world.obstacles, params)
        corners = np.array(footprint(world.state, params).corners())
        now_outside = not bool(np.all(corridor.contains(corners[:, 0], corners[:, 1])))
        expected = []
        if hit is not None and hit.name != touching:
            expected.append("collision")
        if now_outside and not outside:
            expected.append("corridor_exit")
        assert [code for code, _text in events] == expected, k
        touching, outside = (hit.name if hit is not None else None), now_outside
    assert world.collisions > 0 and world.corridor_exits > 0
