"""Vehicle dynamics of a RASCAL-like ATV: a kinematic bicycle about the rear axle.

Lateral motion is kinematic (no tyre slip, no rollover); the steering angle follows the command
through a rate limit. Longitudinal motion is force based: lagged throttle and brake, a drive force
limited by traction at low speed and by power at high speed, aerodynamic drag and rolling
resistance. Speed is signed along the heading: in the reverse gear the throttle drives backwards,
governed to a low top speed, and brake and resistance oppose motion either way, stopping the
vehicle at zero without ever turning it round. The gear changes only at a standstill; asked for
the other gear while moving, the vehicle brakes instead.

``step`` runs at the simulator's 100 Hz, so it uses plain floats and ``math`` (no numpy) and
updates the state in place instead of allocating a new one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Protocol

from brain.vehicle import VehicleGeometry
from rascal.runtime.config import section, setting

GRAVITY_MPS2 = 9.81
_TAU = 2 * math.pi


class Command(Protocol):
    """What ``step`` reads from a command; ``protocol.messages.ActuatorCommand`` fits."""

    @property
    def throttle(self) -> float: ...

    @property
    def brake(self) -> float: ...

    @property
    def steering_rad(self) -> float: ...

    @property
    def reverse(self) -> bool: ...


@dataclass(frozen=True)
class VehicleParams:
    """Physical parameters. Defaults describe a RASCAL-like ATV carrying its sensors and computers."""

    mass_kg: float = setting(450.0, "mass with sensors, computers and fuel")
    geometry: VehicleGeometry = section(VehicleGeometry, "footprint and steering (brain/vehicle.py)")
    track_width_m: float = setting(1.0, "left to right wheel centres (for renderers; the bicycle model ignores it)")
    max_drive_force_n: float = setting(1200.0, "drive force at full throttle and low speed (traction, gearing)")
    max_drive_power_w: float = setting(
        6400.0, "drive power at the wheels at full throttle; with drag and rolling resistance it sets the top speed"
    )
    drag_area_m2: float = setting(1.0, "drag coefficient times frontal area (CdA)")
    air_density_kgpm3: float = setting(1.225, "air density for the drag force")
    rolling_resistance: float = setting(0.03, "rolling resistance coefficient (Crr)")
    max_brake_decel_mps2: float = setting(6.0, "deceleration from full brake alone")
    max_reverse_speed_mps: float = setting(2.5, "the reverse gear's governed top speed")
    gear_change_speed_mps: float = setting(0.1, "the gear changes only below this speed")
    actuator_lag_s: float = setting(0.15, "time constant of the first-order lag of throttle and brake")

    def __post_init__(self) -> None:
        # Parameters come from scenario files; a zero or negative value would silently yield
        # divisions by zero or a vehicle that accelerates backwards, so refuse them by name.
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name != "geometry" and (not math.isfinite(value) or value <= 0):
                raise ValueError(f"VehicleParams.{f.name}: must be finite and positive, got {value!r}")

    # The geometry read through, as the dynamics and the footprint checks use it.
    @property
    def wheelbase_m(self) -> float:
        return self.geometry.wheelbase_m

    @property
    def length_m(self) -> float:
        return self.geometry.length_m

    @property
    def width_m(self) -> float:
        return self.geometry.width_m

    @property
    def rear_overhang_m(self) -> float:
        return self.geometry.rear_overhang_m

    @property
    def max_steering_rad(self) -> float:
        return self.geometry.max_steering_rad

    @property
    def max_steering_rate_radps(self) -> float:
        return self.geometry.max_steering_rate_radps


@dataclass(slots=True)
class VehicleState:
    """The simulated vehicle. Position is the rear axle centre in ENU; yaw is counter-clockwise
    from east, kept within [-pi, pi] by step; ``speed_mps`` is signed (negative: backwards),
    ``odometer_m`` too (reversing winds it back); ``accel_mps2`` is the longitudinal acceleration
    of the last step."""

    east_m: float = 0.0
    north_m: float = 0.0
    yaw_rad: float = 0.0
    speed_mps: float = 0.0
    steering_rad: float = 0.0
    yaw_rate_radps: float = 0.0
    accel_mps2: float = 0.0
    throttle_actual: float = 0.0
    brake_actual: float = 0.0
    odometer_m: float = 0.0
    gear: float = 1.0  # the gear engaged: +1 forward, -1 reverse (a float, as every other field)


def step(state: VehicleState, command: Command, dt_s: float, params: VehicleParams) -> None:
    """Advance ``state`` by ``dt_s`` seconds under ``command``, in place.

    Inputs are clamped to their ranges (throttle and brake 0..1, steering to the wheel limit); a
    gear change asked while moving is a full brake until the vehicle stands.
    Order within a step: actuators, then speed, then pose from the mean speed and the new steering
    angle along an exact circular arc, which keeps the scheme stable and the turning radius exact.
    """
    if not dt_s > 0.0:
        raise ValueError(f"step: dt_s must be positive, got {dt_s!r}")
    p = params

    # Throttle and brake: the exact discretisation of a first-order lag, stable for any dt.
    alpha = 1.0 - math.exp(-dt_s / p.actuator_lag_s)
    throttle = command.throttle
    throttle = 0.0 if throttle < 0.0 else 1.0 if throttle > 1.0 else throttle
    brake = command.brake
    brake = 0.0 if brake < 0.0 else 1.0 if brake > 1.0 else brake
    v = state.speed_mps
    gear = -1.0 if command.reverse else 1.0
    if gear != state.gear:
        if abs(v) < p.gear_change_speed_mps:
            state.gear = gear
        else:
            throttle, brake = 0.0, 1.0
    throttle_actual = state.throttle_actual + (throttle - state.throttle_actual) * alpha
    brake_actual = state.brake_actual + (brake - state.brake_actual) * alpha

    # Steering: towards the saturated command, at most the actuator's rate per step.
    limit = p.max_steering_rad
    target = command.steering_rad
    target = -limit if target < -limit else limit if target > limit else target
    max_change = p.max_steering_rate_radps * dt_s
    change = target - state.steering_rad
    change = -max_change if change < -max_change else max_change if change > max_change else change
    steering = state.steering_rad + change

    # Speed: drive force is traction-limited at low speed and power-limited above; the reverse
    # gear's is governed, fading to nothing at its top speed.
    mass = p.mass_kg
    drive = p.max_drive_force_n
    speed = abs(v)
    gear = state.gear
    if gear < 0.0:
        drive *= max(0.0, 1.0 - speed / p.max_reverse_speed_mps)
    elif speed * drive > p.max_drive_power_w:
        drive = p.max_drive_power_w / speed
    # Brake and resistance oppose the motion, or at rest the way the gear pushes.
    motion = 1.0 if v > 0.0 else -1.0 if v < 0.0 else gear
    force = (
        gear * throttle_actual * drive
        - motion * brake_actual * p.max_brake_decel_mps2 * mass
        - motion * p.rolling_resistance * mass * GRAVITY_MPS2
        - motion * 0.5 * p.air_density_kgpm3 * p.drag_area_m2 * v * v
    )
    v_new = v + force / mass * dt_s
    # They bring the vehicle to rest, never turn it round.
    if v_new * motion < 0.0:
        v_new = 0.0

    # Pose: with constant speed and steering over the step the rear axle follows a circular arc;
    # its chord has length ds*sin(h)/h at the mid-step heading (h = half the heading change).
    # Backwards, ds and h are both negative: the same arc, travelled the other way.
    v_mean = 0.5 * (v + v_new)
    distance = v_mean * dt_s
    yaw_rate = v_mean * math.tan(steering) / p.wheelbase_m
    half_turn = 0.5 * yaw_rate * dt_s
    chord = distance * math.sin(half_turn) / half_turn if half_turn != 0.0 else distance
    heading = state.yaw_rad + half_turn
    yaw = state.yaw_rad + 2.0 * half_turn
    if yaw > math.pi or yaw < -math.pi:
        yaw = math.remainder(yaw, _TAU)

    state.east_m += chord * math.cos(heading)
    state.north_m += chord * math.sin(heading)
    state.yaw_rad = yaw
    state.speed_mps = v_new
    state.steering_rad = steering
    state.yaw_rate_radps = yaw_rate
    state.accel_mps2 = (v_new - v) / dt_s
    state.throttle_actual = throttle_actual
    state.brake_actual = brake_actual
    state.odometer_m += distance


def top_speed_mps(params: VehicleParams) -> float:
    """Steady speed at full throttle on flat ground, where drive force equals drag plus rolling."""

    def surplus_n(v: float) -> float:
        drive = min(params.max_drive_force_n, params.max_drive_power_w / v) if v > 0 else params.max_drive_force_n
        rolling = params.rolling_resistance * params.mass_kg * GRAVITY_MPS2
        return drive - rolling - 0.5 * params.air_density_kgpm3 * params.drag_area_m2 * v * v

    if surplus_n(0.0) <= 0:
        return 0.0
    # The surplus falls monotonically with speed. Drive force is at most power / v and drag alone
    # must stay below it, which bounds the answer from above.
    low, high = 0.0, (2 * params.max_drive_power_w / (params.air_density_kgpm3 * params.drag_area_m2)) ** (1 / 3)
    for _ in range(100):
        mid = 0.5 * (low + high)
        low, high = (mid, high) if surplus_n(mid) > 0 else (low, mid)
    return 0.5 * (low + high)
