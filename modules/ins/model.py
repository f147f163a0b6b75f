"""The planar navigation model both filters share: state layout, motion, measurements, noises.

State (``x``, 9 entries; indices below)::

    east_m, north_m     rear-axle reference point in the deployment's ENU frame
    yaw_rad             counter-clockwise from east
    speed_mps           along the body x axis
    gyro_bias_radps     z-gyro bias
    speed_scale         speedometer reading / true speed (tyre radius error)
    mag1_bias_rad       magnetometer 1's heading bias (clockwise from north, as it reports)
    mag2_bias_rad       magnetometer 2's heading bias
    accel_bias_mps2     x-accelerometer bias

Motion model: yaw integrates the bias-corrected gyro, speed the bias-corrected accelerometer, and
the position moves *along the yaw* over the mid-step heading. That is the no-sideslip constraint,
built into the model rather than applied as a pseudo-measurement: the vehicle is a kinematic
bicycle about the rear axle (modules/sim/vehicle.py), so its velocity has no lateral component
and the lateral accelerometer (centripetal, v * yaw rate) carries no new information.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rascal.runtime.angles import wrap_angle

E, N, YAW, SPD, BG, SCALE, BM1, BM2, BA = range(9)
DIM_X = 9
BIAS_OF_MAG = {1: BM1, 2: BM2}
DEG_PER_H = math.radians(1.0) / 3600.0
MILLI_G = 9.80665e-3
PER_SQRT_H = 1.0 / 60.0  # a coefficient per sqrt(hour) is this times the same per sqrt(second)
CHI2_2DOF_999 = 13.816  # 99.9 % point of chi-square with 2 degrees of freedom


@dataclass(frozen=True)
class InsParams:
    """Noise and behaviour settings. Sensor noises are nominal datasheet values of the sensors
    (a tactical IMU, a 1-2 % tyre scale, fluxgate compasses a few degrees off); process noises of
    constant quantities are small but non-zero so the filter can still follow slow drift."""

    gyro_arw_radps_per_sqrt_hz: float = math.radians(0.2) * PER_SQRT_H
    accel_vrw_mps2_per_sqrt_hz: float = 0.07 * PER_SQRT_H
    gyro_bias_walk_radps_per_sqrt_s: float = 1.0 * DEG_PER_H / math.sqrt(150.0)  # ~1 deg/h over 300 s
    accel_bias_walk_mps2_per_sqrt_s: float = 0.1 * MILLI_G / math.sqrt(150.0)
    speed_scale_walk_per_sqrt_s: float = 1e-6
    mag_bias_walk_rad_per_sqrt_s: float = 1e-6
    position_walk_m_per_sqrt_s: float = 0.01  # what the planar model leaves out (bumps, lever arms)
    speedometer_std_mps: float = 0.05
    initial_gyro_bias_std_radps: float = 10.0 * DEG_PER_H
    initial_accel_bias_std_mps2: float = 2.0 * MILLI_G
    initial_speed_scale_std: float = 0.03
    initial_mag_bias_std_rad: float = math.radians(5.0)
    initial_speed_std_mps: float = 1.0  # from an uncalibrated speedometer
    unknown_speed_std_mps: float = 10.0  # no speedometer reading at initialisation
    gps_gate_chi2: float = CHI2_2DOF_999
    reacquire_after_s: float = 10.0  # longer than the few-second jumps a DGPS makes
    reacquire_min_rejections: int = 20
    reacquire_position_variance_scale: float = 25.0  # 5x the fix's std: the jump may still be settling
    gps_timeout_s: float = 1.0  # without an accepted fix for this long the solution is dead reckoning
    history_s: float = 0.5  # how late a measurement may arrive and still be used


@dataclass(frozen=True)
class ImuInput:
    """One IMU interval: bias-uncorrected rate and specific force held over ``dt_s``."""

    gyro_z_radps: float
    accel_x_mps2: float
    dt_s: float


def propagate(x: np.ndarray, u: ImuInput) -> np.ndarray:
    """The state after ``u``: turn and accelerate, then move along the mid-step heading."""
    dt = u.dt_s
    rate = u.gyro_z_radps - x[BG]
    accel = u.accel_x_mps2 - x[BA]
    mean_speed = x[SPD] + 0.5 * accel * dt
    heading = x[YAW] + 0.5 * rate * dt
    out = x.copy()
    out[E] += mean_speed * dt * math.cos(heading)
    out[N] += mean_speed * dt * math.sin(heading)
    out[YAW] = wrap_angle(x[YAW] + rate * dt)
    out[SPD] += accel * dt
    return out


def process_noise_rate(params: InsParams) -> np.ndarray:
    """Diagonal of the process noise per second, in state order: white noise densities squared."""
    p = params
    return np.array(
        [
            p.position_walk_m_per_sqrt_s**2,
            p.position_walk_m_per_sqrt_s**2,
            p.gyro_arw_radps_per_sqrt_hz**2,
            p.accel_vrw_mps2_per_sqrt_hz**2,
            p.gyro_bias_walk_radps_per_sqrt_s**2,
            p.speed_scale_walk_per_sqrt_s**2,
            p.mag_bias_walk_rad_per_sqrt_s**2,
            p.mag_bias_walk_rad_per_sqrt_s**2,
            p.accel_bias_walk_mps2_per_sqrt_s**2,
        ]
    )


def transition(x: np.ndarray, u: ImuInput, q_rate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobian F of ``propagate`` at ``x`` and the process noise Q of the interval, from the
    per-second noise ``q_rate`` (``process_noise_rate``)."""
    dt = u.dt_s
    accel = u.accel_x_mps2 - x[BA]
    mean_speed = x[SPD] + 0.5 * accel * dt
    heading = x[YAW] + 0.5 * (u.gyro_z_radps - x[BG]) * dt
    c, s = math.cos(heading), math.sin(heading)
    F = np.eye(DIM_X)
    F[E, YAW], F[N, YAW] = -mean_speed * dt * s, mean_speed * dt * c
    F[E, SPD], F[N, SPD] = dt * c, dt * s
    F[E, BG], F[N, BG] = 0.5 * mean_speed * dt * dt * s, -0.5 * mean_speed * dt * dt * c
    F[E, BA], F[N, BA] = -0.5 * dt * dt * c, -0.5 * dt * dt * s
    F[YAW, BG] = -dt
    F[SPD, BA] = -dt
    return F, np.diag(q_rate * dt)


# Measurement models: h(x) and its Jacobian, per sensor.


def gps_h(x: np.ndarray) -> np.ndarray:
    H = np.zeros((2, DIM_X))
    H[0, E] = H[1, N] = 1.0
    return H


def gps_hx(x: np.ndarray) -> np.ndarray:
    return x[[E, N]]


def speed_h(x: np.ndarray) -> np.ndarray:
    H = np.zeros((1, DIM_X))
    H[0, SPD], H[0, SCALE] = x[SCALE], x[SPD]
    return H


def speed_hx(x: np.ndarray) -> np.ndarray:
    return np.array([x[SCALE] * x[SPD]])


def mag_h(x: np.ndarray, bias: int) -> np.ndarray:
    H = np.zeros((1, DIM_X))
    H[0, YAW], H[0, bias] = -1.0, 1.0
    return H


def mag_hx(x: np.ndarray, bias: int) -> np.ndarray:
    return np.array([math.pi / 2 - x[YAW] + x[bias]])


def angle_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([wrap_angle(float(a[0] - b[0]))])
