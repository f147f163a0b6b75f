"""Vehicle dynamics: top speed, braking, steering limits, turning geometry, determinism, robustness."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brain.vehicle import VehicleGeometry
from modules.sim.vehicle import GRAVITY_MPS2, VehicleParams, VehicleState, step, top_speed_mps
from protocol.messages import ActuatorCommand

DT_S = 0.01
PARAMS = VehicleParams()
FULL_THROTTLE = ActuatorCommand(1.0, 0.0, 0.0)
FULL_BRAKE = ActuatorCommand(0.0, 1.0, 0.0)


def run(state: VehicleState, command: ActuatorCommand, seconds: float) -> list[VehicleState]:
    """Step ``state`` under a constant command; a copy of the state after every step."""
    history = []
    for _ in range(round(seconds / DT_S)):
        step(state, command, DT_S, PARAMS)
        history.append(VehicleState(*(getattr(state, name) for name in state.__slots__)))
    return history


def test_full_throttle_on_flat_ground_reaches_17_8_mps_and_settles_below_20() -> None:
    history = run(VehicleState(), FULL_THROTTLE, 90.0)
    speeds = [s.speed_mps for s in history]
    assert max(speeds) >= 17.8
    assert speeds[-1] < 20.0
    # Settled: the last ten seconds change speed by less than a centimetre per second.
    assert speeds[-1] - speeds[-1000] < 0.01
    assert speeds[-1] == pytest.approx(top_speed_mps(PARAMS), abs=0.01)


def test_full_brake_from_10_mps_stops_within_the_physical_distance_and_never_reverses() -> None:
    state = VehicleState(speed_mps=10.0)
    history = run(state, FULL_BRAKE, 5.0)
    assert all(s.speed_mps >= 0.0 for s in history)
    assert history[-1].speed_mps == 0.0
    distance_m = history[-1].odometer_m
    v = 10.0
    # Upper bound: the brake alone, applied after a dead time equal to the actuator lag (a lag
    # builds up force faster than a dead time does). Lower bound: full brake plus the largest drag
    # and rolling resistance from the first instant.
    no_lag_m = v * v / (2 * PARAMS.max_brake_decel_mps2)
    assert distance_m <= no_lag_m + v * PARAMS.actuator_lag_s
    resist_mps2 = PARAMS.rolling_resistance * GRAVITY_MPS2 + 0.5 * 1.225 * PARAMS.drag_area_m2 * v * v / PARAMS.mass_kg
    assert distance_m >= v * v / (2 * (PARAMS.max_brake_decel_mps2 + resist_mps2))


def test_a_stopped_vehicle_with_the_brake_on_stays_put() -> None:
    state = VehicleState(brake_actual=1.0)
    history = run(state, ActuatorCommand(0.3, 1.0, 0.2), 2.0)
    assert all(s.speed_mps == 0.0 and s.odometer_m == 0.0 for s in history)


@given(st.lists(st.floats(-2.0, 2.0), min_size=1, max_size=40))
@settings(max_examples=100, deadline=None)
def test_steering_never_turns_faster_than_the_rate_limit_nor_beyond_the_stop(targets: list[float]) -> None:
    state = VehicleState(speed_mps=5.0)
    max_step = PARAMS.max_steering_rate_radps * DT_S
    for target in targets:
        for _ in range(10):
            before = state.steering_rad
            step(state, ActuatorCommand(0.5, 0.0, target), DT_S, PARAMS)
            assert abs(state.steering_rad - before) <= max_step + 1e-12
            assert abs(state.steering_rad) <= PARAMS.max_steering_rad


def test_steady_turning_radius_is_wheelbase_over_tan_steering() -> None:
    steering_rad = 0.3
    state = VehicleState(steering_rad=steering_rad)
    # Speed changes (and so the arc steps vary) while the steering holds: the radius must not care.
    history = run(state, ActuatorCommand(0.4, 0.0, steering_rad), 20.0)
    points = np.array([(s.east_m, s.north_m) for s in history[500:]])
    # Algebraic circle fit: x^2 + y^2 = 2ax + 2by + c, radius^2 = c + a^2 + b^2.
    design = np.column_stack([2 * points[:, 0], 2 * points[:, 1], np.ones(len(points))])
    (a, b, c), *_ = np.linalg.lstsq(design, (points**2).sum(axis=1), rcond=None)
    radius_m = math.sqrt(c + a * a + b * b)
    assert radius_m == pytest.approx(PARAMS.wheelbase_m / math.tan(steering_rad), rel=0.02)


def test_zero_steering_keeps_heading_constant_and_the_path_straight() -> None:
    yaw_rad = 0.7
    state = VehicleState(east_m=3.0, north_m=-2.0, yaw_rad=yaw_rad)
    history = run(state, FULL_THROTTLE, 10.0)
    assert all(s.yaw_rad == yaw_rad and s.yaw_rate_radps == 0.0 for s in history)
    direction = (math.cos(yaw_rad), math.sin(yaw_rad))
    for s in history:
        offset = (s.east_m - 3.0, s.north_m + 2.0)
        assert abs(offset[0] * direction[1] - offset[1] * direction[0]) < 1e-9
    assert history[-1].odometer_m == pytest.approx(math.hypot(history[-1].east_m - 3.0, history[-1].north_m + 2.0))


def test_same_inputs_give_bit_identical_states() -> None:
    commands = [
        ActuatorCommand(0.5 + 0.5 * math.sin(k / 37), (k % 50) / 60, 0.6 * math.sin(k / 23)) for k in range(3000)
    ]

    def trajectory() -> list[tuple[float, ...]]:
        state = VehicleState(speed_mps=4.0)
        out = []
        for command in commands:
            step(state, command, DT_S, PARAMS)
            out.append(tuple(getattr(state, name) for name in state.__slots__))
        return out

    first, second = trajectory(), trajectory()
    assert [tuple(x.hex() for x in row) for row in first] == [tuple(x.hex() for x in row) for row in second]


finite = st.floats(allow_nan=False, allow_infinity=False)


@given(
    st.lists(st.tuples(finite, finite, finite), min_size=1, max_size=200),
    st.floats(min_value=1e-4, max_value=0.1),
)
@settings(max_examples=150, deadline=None)
def test_any_finite_command_sequence_keeps_the_state_finite(
    commands: list[tuple[float, float, float]], dt_s: float
) -> None:
    state = VehicleState(speed_mps=15.0)
    for throttle, brake, steering_rad in commands:
        step(state, ActuatorCommand(throttle, brake, steering_rad), dt_s, PARAMS)
        values = [getattr(state, name) for name in state.__slots__]
        assert all(math.isfinite(v) for v in values)
        assert state.speed_mps >= 0.0
        assert 0.0 <= state.throttle_actual <= 1.0 and 0.0 <= state.brake_actual <= 1.0
        assert -math.pi <= state.yaw_rad <= math.pi


def test_dt_must_be_positive() -> None:
    with pytest.raises(ValueError, match="dt_s"):
        step(VehicleState(), FULL_THROTTLE, 0.0, PARAMS)


def test_params_reject_non_positive_values_by_name() -> None:
    with pytest.raises(ValueError, match="mass_kg"):
        VehicleParams(mass_kg=0.0)
    with pytest.raises(ValueError, match="max_steering_rad"):
        VehicleParams(geometry=VehicleGeometry(max_steering_rad=2.0))


# -- the reverse gear ---------------------------------------------------------------------------

FULL_REVERSE = ActuatorCommand(1.0, 0.0, 0.0, reverse=True)


def test_full_throttle_in_reverse_drives_backwards_at_a_governed_low_speed() -> None:
    state = VehicleState(yaw_rad=0.4)
    history = run(state, FULL_REVERSE, 20.0)
    assert history[-1].gear == -1.0
    assert all(s.speed_mps <= 0.0 for s in history)
    assert -PARAMS.max_reverse_speed_mps < history[-1].speed_mps < -2.0
    # Straight back along the heading, and the odometer winds back by the distance.
    back_m = math.hypot(history[-1].east_m, history[-1].north_m)
    assert math.atan2(-history[-1].north_m, -history[-1].east_m) == pytest.approx(0.4, abs=1e-9)
    assert history[-1].odometer_m == pytest.approx(-back_m)
    assert all(s.yaw_rad == 0.4 for s in history)


def test_reversing_with_the_wheels_turned_follows_the_same_circle_backwards() -> None:
    steering_rad = 0.3
    radius_m = PARAMS.wheelbase_m / math.tan(steering_rad)
    state = VehicleState(steering_rad=steering_rad)
    history = run(state, ActuatorCommand(0.6, 0.0, steering_rad, reverse=True), 3.0)
    # The centre of the turn is left of the rear axle, forwards or backwards; backing up with the
    # wheels turned left swings the nose right (yaw falls).
    for s in history:
        assert math.hypot(s.east_m, s.north_m - radius_m) == pytest.approx(radius_m, abs=1e-9)
    assert -math.pi / 2 < history[-1].yaw_rad < -0.3 and history[-1].east_m < 0.0
    assert history[-1].yaw_rate_radps < 0.0


def test_reverse_asked_while_moving_brakes_to_a_standstill_before_the_gear_changes() -> None:
    state = VehicleState(speed_mps=5.0)
    history = run(state, FULL_REVERSE, 6.0)
    braked = run(VehicleState(speed_mps=5.0), FULL_BRAKE, 6.0)
    changed = next(k for k, s in enumerate(history) if s.gear == -1.0)
    assert history[changed - 1].speed_mps >= 0.0 and abs(history[changed - 1].speed_mps) < PARAMS.gear_change_speed_mps
    # Until the change it is exactly a full brake; after it, the throttle drives backwards.
    assert [s.speed_mps for s in history[: changed - 1]] == [s.speed_mps for s in braked[: changed - 1]]
    assert all(s.gear == 1.0 for s in history[:changed])
    assert history[-1].speed_mps < -1.0


def test_forward_asked_while_reversing_brakes_first_too() -> None:
    state = VehicleState(speed_mps=-2.0, gear=-1.0)
    history = run(state, FULL_THROTTLE, 4.0)
    changed = next(k for k, s in enumerate(history) if s.gear == 1.0)
    assert all(s.speed_mps <= 0.0 for s in history[:changed])
    assert history[-1].speed_mps > 1.0


def test_brake_and_resistance_stop_a_reversing_vehicle_without_turning_it_round() -> None:
    history = run(VehicleState(speed_mps=-2.0, gear=-1.0), ActuatorCommand(0.0, 1.0, 0.0, reverse=True), 2.0)
    assert all(s.speed_mps <= 0.0 for s in history) and history[-1].speed_mps == 0.0
    coasting = run(VehicleState(speed_mps=-2.0, gear=-1.0), ActuatorCommand(0.0, 0.0, 0.0, reverse=True), 20.0)
    assert all(s.speed_mps <= 0.0 for s in coasting) and coasting[-1].speed_mps == 0.0
