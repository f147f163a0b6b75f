"""A planar navigation EKF: IMU-driven prediction, DGPS, speedometer and magnetometer updates.

Sans-IO: messages and their measurement times go in, ``VehicleState`` comes out; no clock, no bus.

State (``x``, 9 entries; indices below)::

    east_m, north_m     rear-axle reference point in the deployment's ENU frame
    yaw_rad             counter-clockwise from east
    speed_mps           along the body x axis
    gyro_bias_radps     z-gyro bias
    speed_scale         speedometer reading / true speed (tyre radius error)
    mag1_bias_rad       magnetometer 1's heading bias (clockwise from north, as it reports)
    mag2_bias_rad       magnetometer 2's heading bias
    accel_bias_mps2     x-accelerometer bias

Filter: filterpy's ``ExtendedKalmanFilter``; its ``predict`` (``P = F P F' + Q``) and its Joseph
form ``update`` run with our own Jacobians F and H and noises Q and R. ``predict_x`` is overridden
by the nonlinear motion model.

Motion model: yaw integrates the bias-corrected gyro, speed the bias-corrected accelerometer, and
the position moves *along the yaw* over the mid-step heading. That is the no-sideslip constraint,
built into the model rather than applied as a pseudo-measurement: the vehicle is a kinematic
bicycle about the rear axle (modules/sim/vehicle.py), so its velocity has no lateral component
and the lateral accelerometer (centripetal, v * yaw rate) carries no new information.

Measurement time: every IMU step is kept for ``history_s`` with its posterior and the
measurements applied inside it. A measurement older than the newest state rewinds to the step
that contains its time, is applied there, and every later IMU sample and measurement is
replayed; one older than the history is rejected and counted. One newer than the newest IMU
sample waits until the IMU catches up (up to ``history_s`` ahead; further is rejected and counted).

GPS gating: a fix whose innovation's Mahalanobis distance exceeds a chi-square bound (2 dof) is
rejected and counted. If fixes keep being rejected for ``reacquire_after_s`` (at least
``reacquire_min_rejections`` of them in a row), the filter believes the GPS: position is reset to
the fix with an inflated covariance, the history is cleared, and a re-acquisition is counted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pymap3d
from filterpy.kalman import ExtendedKalmanFilter

from brain.corridor import GeodeticOrigin
from protocol.messages import GpsFix, ImuSample, MagHeading, NavQuality, VehicleState, WheelSpeed

E, N, YAW, SPD, BG, SCALE, BM1, BM2, BA = range(9)
DIM_X = 9
_BIAS_OF_MAG = {1: BM1, 2: BM2}
DEG_PER_H = math.radians(1.0) / 3600.0
MILLI_G = 9.80665e-3
PER_SQRT_H = 1.0 / 60.0  # a coefficient per sqrt(hour) is this times the same per sqrt(second)
CHI2_2DOF_999 = 13.816  # 99.9 % point of chi-square with 2 degrees of freedom
UNINITIALISED_VARIANCE = 1e12  # what state() reports before the filter has a solution


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
class _ImuInput:
    """One IMU interval: bias-uncorrected rate and specific force held over ``dt_s``."""

    gyro_z_radps: float
    accel_x_mps2: float
    dt_s: float


@dataclass
class _Measurement:
    """A measurement waiting to be applied or kept for replay. ``kind`` is gps, speed or mag."""

    t_ns: int
    kind: str
    z: np.ndarray
    R: np.ndarray
    mag_index: int = 0
    quality: int = int(NavQuality.DGPS)


@dataclass
class _Step:
    """The posterior after the IMU interval ending at ``t_ns`` and the measurements inside it."""

    t_ns: int
    imu: ImuSample | None
    x: np.ndarray
    P: np.ndarray
    measurements: list[_Measurement] = field(default_factory=list)


def wrap(angle_rad: float) -> float:
    """``angle_rad`` wrapped into [-pi, pi]."""
    return math.remainder(angle_rad, math.tau)


def propagate(x: np.ndarray, u: _ImuInput) -> np.ndarray:
    """The state after ``u``: turn and accelerate, then move along the mid-step heading."""
    dt = u.dt_s
    rate = u.gyro_z_radps - x[BG]
    accel = u.accel_x_mps2 - x[BA]
    mean_speed = x[SPD] + 0.5 * accel * dt
    heading = x[YAW] + 0.5 * rate * dt
    out = x.copy()
    out[E] += mean_speed * dt * math.cos(heading)
    out[N] += mean_speed * dt * math.sin(heading)
    out[YAW] = wrap(x[YAW] + rate * dt)
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


def transition(x: np.ndarray, u: _ImuInput, q_rate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


class _PlanarEkf(ExtendedKalmanFilter):
    """filterpy's EKF with the nonlinear motion model as its state prediction."""

    def predict_x(self, u: _ImuInput) -> None:  # type: ignore[override]
        self.x = propagate(self.x, u)


def _gps_h(x: np.ndarray) -> np.ndarray:
    H = np.zeros((2, DIM_X))
    H[0, E] = H[1, N] = 1.0
    return H


def _gps_hx(x: np.ndarray) -> np.ndarray:
    return x[[E, N]]


def _speed_h(x: np.ndarray) -> np.ndarray:
    H = np.zeros((1, DIM_X))
    H[0, SPD], H[0, SCALE] = x[SCALE], x[SPD]
    return H


def _speed_hx(x: np.ndarray) -> np.ndarray:
    return np.array([x[SCALE] * x[SPD]])


def _mag_h(x: np.ndarray, bias: int) -> np.ndarray:
    H = np.zeros((1, DIM_X))
    H[0, YAW], H[0, bias] = -1.0, 1.0
    return H


def _mag_hx(x: np.ndarray, bias: int) -> np.ndarray:
    return np.array([math.pi / 2 - x[YAW] + x[bias]])


def _angle_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([wrap(float(a[0] - b[0]))])


class InsEkf:
    """The navigation filter. Feed every message with its measurement time; read ``state``.

    It initialises at the first GPS fix once a magnetometer heading is known (yaw comes from the
    compass, position from the fix, speed from the speedometer if heard). Counters:
    ``gps_rejected`` (fixes failing the gate), ``reacquisitions``, ``late_rejected`` (measurements
    older than the history), ``replayed`` (measurements applied by rewinding), ``imu_dropped``
    (IMU samples not newer than the newest state: the state cannot be predicted backwards),
    ``ahead_rejected`` (measurements more than the history ahead of the newest IMU sample).
    """

    def __init__(self, origin: GeodeticOrigin, params: InsParams | None = None) -> None:
        self.origin = origin
        self.params = params or InsParams()
        self._q_rate = process_noise_rate(self.params)
        self._ekf = _PlanarEkf(dim_x=DIM_X, dim_z=1)
        self._history: list[_Step] = []
        self._pending: list[_Measurement] = []
        # The latest speed and headings with their times, for initialisation.
        self._last_speed: tuple[int, float] | None = None
        self._last_mag: dict[int, tuple[int, MagHeading]] = {}
        self._last_gps_ns: int | None = None
        self._gps_quality = int(NavQuality.DGPS)
        self._rejections = 0
        self._first_rejection_ns: int | None = None
        self._reacquired = False
        self.gps_rejected = 0
        self.reacquisitions = 0
        self.late_rejected = 0
        self.imu_dropped = 0
        self.ahead_rejected = 0
        self.replayed = 0

    @property
    def initialised(self) -> bool:
        return bool(self._history)

    @property
    def t_ns(self) -> int | None:
        """Time of the newest state (None before initialisation)."""
        return self._history[-1].t_ns if self._history else None

    @property
    def x(self) -> np.ndarray:
        """The newest state estimate (a copy)."""
        return self._ekf.x.copy()

    @property
    def P(self) -> np.ndarray:
        """The newest state covariance (a copy)."""
        return self._ekf.P.copy()

    # ----- inputs

    def on_imu(self, msg: ImuSample, t_ns: int) -> None:
        """Predict to ``t_ns`` with the sample that covers the interval ending there."""
        if not self._history:
            return
        last = self._history[-1]
        if t_ns <= last.t_ns:
            self.imu_dropped += 1
            return
        self._history.append(_Step(t_ns, msg, last.x, last.P))
        self._run_step(len(self._history) - 1)
        self._trim_history()
        due = [m for m in self._pending if m.t_ns <= t_ns]
        if due:
            self._pending = [m for m in self._pending if m.t_ns > t_ns]
            for m in due:
                self._insert(m)

    def on_gps(self, msg: GpsFix, t_ns: int) -> None:
        """A fix, converted to the origin's ENU frame at the origin's height (the course is flat),
        gated; before initialisation, the fix that starts the filter."""
        east, north, _ = pymap3d.geodetic2enu(
            msg.lat_deg, msg.lon_deg, self.origin.alt_m, self.origin.lat_deg, self.origin.lon_deg, self.origin.alt_m
        )
        z = np.array([float(east), float(north)])
        R = np.diag([msg.std_east_m**2, msg.std_north_m**2])
        m = _Measurement(t_ns, "gps", z, R, quality=msg.quality)
        if self._history:
            self._insert(m)
        else:
            self._initialise(m)

    def on_speed(self, msg: WheelSpeed, t_ns: int) -> None:
        """A speedometer reading: scale times speed."""
        self._last_speed = (t_ns, msg.speed_mps)
        if self._history:
            R = np.array([[self.params.speedometer_std_mps**2]])
            self._insert(_Measurement(t_ns, "speed", np.array([msg.speed_mps]), R))

    def on_mag(self, msg: MagHeading, t_ns: int) -> None:
        """A compass heading: pi/2 - yaw + that unit's bias, compared on the circle."""
        if msg.magnetometer not in _BIAS_OF_MAG:
            return
        self._last_mag[msg.magnetometer] = (t_ns, msg)
        if self._history:
            R = np.array([[msg.std_rad**2]])
            z = np.array([msg.heading_from_north_rad])
            self._insert(_Measurement(t_ns, "mag", z, R, mag_index=msg.magnetometer))

    # ----- output

    def quality(self, t_ns: int) -> NavQuality:
        """INVALID before initialisation, DEAD_RECKONING once no fix was accepted for
        ``gps_timeout_s``, otherwise the quality the last accepted fix reported."""
        if not self._history:
            return NavQuality.INVALID
        if self._last_gps_ns is None or t_ns - self._last_gps_ns > self.params.gps_timeout_s * 1e9:
            return NavQuality.DEAD_RECKONING
        return NavQuality(self._gps_quality)

    def state(self, t_ns: int) -> VehicleState:
        """The solution at ``t_ns``: the newest state at or before it, predicted forward with the
        IMU sample that follows it (or the newest). Before initialisation: zeros, INVALID."""
        if not self._history:
            cov = tuple(float(v) for v in np.eye(5).ravel() * UNINITIALISED_VARIANCE)
            return VehicleState(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, cov, int(NavQuality.INVALID))
        index = self._index_at_or_before(t_ns)
        if index < 0:
            raise ValueError(f"state: {t_ns} is older than the history")
        step = self._history[index]
        imu = self._history[min(index + 1, len(self._history) - 1)].imu or step.imu
        x, P = step.x, step.P
        if imu is not None and t_ns > step.t_ns:
            u = _ImuInput(imu.gyro_z_radps, imu.accel_x_mps2, (t_ns - step.t_ns) / 1e9)
            F, Q = transition(x, u, self._q_rate)
            P = F @ P @ F.T + Q
            x, P = propagate(x, u), 0.5 * (P + P.T)
        return self._vehicle_state(x, P, imu, t_ns)

    def _vehicle_state(self, x: np.ndarray, P: np.ndarray, imu: ImuSample | None, t_ns: int) -> VehicleState:
        rate = (imu.gyro_z_radps if imu is not None else 0.0) - x[BG]
        # Yaw rate = gyro - bias: its variance is the bias's plus one sample's noise.
        cov = np.zeros((5, 5))
        cov[:4, :4] = P[np.ix_([E, N, YAW, SPD], [E, N, YAW, SPD])]
        cov[4, :4] = cov[:4, 4] = -P[BG, [E, N, YAW, SPD]]
        sample_rate_hz = 1e9 / self._typical_dt_ns()
        cov[4, 4] = P[BG, BG] + self.params.gyro_arw_radps_per_sqrt_hz**2 * sample_rate_hz
        yaw, speed = float(x[YAW]), float(x[SPD])
        return VehicleState(
            float(x[E]),
            float(x[N]),
            0.0,
            yaw,
            speed,
            speed * math.cos(yaw),
            speed * math.sin(yaw),
            float(rate),
            tuple(float(v) for v in cov.ravel()),
            int(self.quality(t_ns)),
        )

    def _typical_dt_ns(self) -> int:
        if len(self._history) < 2:
            return 10_000_000
        return max(1, self._history[-1].t_ns - self._history[-2].t_ns)

    # ----- initialisation

    def _initialise(self, fix: _Measurement) -> None:
        """First solution at the fix's time, if a compass heading close to it in time is known:
        position from the fix, yaw from the compass (whose unknown bias becomes the yaw's error,
        hence their correlation), speed from the speedometer (or at rest, very uncertain)."""
        p = self.params
        window_ns = p.history_s * 1e9
        headings = [msg for t_ns, msg in self._last_mag.values() if abs(t_ns - fix.t_ns) <= window_ns]
        if not headings:
            return
        mag = min(headings, key=lambda h: h.magnetometer)
        speed = self._last_speed if self._last_speed and abs(self._last_speed[0] - fix.t_ns) <= window_ns else None
        x = np.zeros(DIM_X)
        x[E], x[N] = fix.z
        x[YAW] = wrap(math.pi / 2 - mag.heading_from_north_rad)
        x[SPD] = speed[1] if speed else 0.0
        x[SCALE] = 1.0
        speed_std = p.initial_speed_std_mps if speed else p.unknown_speed_std_mps
        bias_var = p.initial_mag_bias_std_rad**2
        P = np.diag(
            [
                fix.R[0, 0],
                fix.R[1, 1],
                bias_var + mag.std_rad**2,
                speed_std**2,
                p.initial_gyro_bias_std_radps**2,
                p.initial_speed_scale_std**2,
                bias_var,
                bias_var,
                p.initial_accel_bias_std_mps2**2,
            ]
        )
        b = _BIAS_OF_MAG[mag.magnetometer]
        P[YAW, b] = P[b, YAW] = -bias_var  # yaw0 = yaw - bias + noise: its error is minus the bias
        self._ekf.x, self._ekf.P = x, P
        self._history = [_Step(fix.t_ns, None, x.copy(), P.copy())]
        self._accept_gps(fix)

    # ----- time handling

    def _index_at_or_before(self, t_ns: int) -> int:
        """Index of the newest step not after ``t_ns`` (-1 if none); scans from the newest, as
        late measurements are recent."""
        for i in range(len(self._history) - 1, -1, -1):
            if self._history[i].t_ns <= t_ns:
                return i
        return -1

    def _insert(self, m: _Measurement) -> None:
        """Apply ``m`` at its time: wait if it is ahead of the IMU, reject it if it is older than
        the history, otherwise re-run the step containing it and replay everything after."""
        history = self._history
        if m.t_ns > history[-1].t_ns:
            if m.t_ns - history[-1].t_ns > self.params.history_s * 1e9:
                self.ahead_rejected += 1  # the IMU is stalled or the stamp is wrong: do not hoard
            else:
                self._pending.append(m)
            return
        index = self._index_at_or_before(m.t_ns - 1) + 1  # first step ending at or after m.t_ns
        step = history[index]
        if step.t_ns == m.t_ns:
            # At a step's own time the measurement goes after everything in it: no re-run of the
            # step is needed, only of the later ones (none in the common, in-order case).
            self._ekf.x, self._ekf.P = step.x.copy(), step.P.copy()
            if self._apply(m, gate=True):
                step.measurements.append(m)
            step.x, step.P = self._ekf.x.copy(), self._ekf.P.copy()
        elif index == 0:
            self.late_rejected += 1  # older than the history: nothing to rewind to
            return
        else:
            self._run_step(index, new=m)
        if index < len(history) - 1:
            self.replayed += 1
            for later in range(index + 1, len(history)):
                self._run_step(later)
        if self._reacquired:
            # The re-acquired position invalidates every older state: no rewinding past it.
            self._reacquired = False
            self._history = [self._history[-1]]

    def _run_step(self, index: int, new: _Measurement | None = None) -> None:
        """Recompute step ``index`` from the previous posterior: predict to each measurement in
        time order, apply it, predict to the step's end. ``new`` is gated; kept ones are not."""
        prev, step = self._history[index - 1], self._history[index]
        assert step.imu is not None
        self._ekf.x, self._ekf.P = prev.x.copy(), prev.P.copy()
        measurements = sorted([*step.measurements, *([new] if new else [])], key=lambda o: o.t_ns)
        kept: list[_Measurement] = []
        t_ns = prev.t_ns
        for m in measurements:
            self._predict(step.imu, m.t_ns - t_ns)
            t_ns = m.t_ns
            if self._apply(m, gate=m is new):
                kept.append(m)
        self._predict(step.imu, step.t_ns - t_ns)
        step.measurements = kept
        step.x, step.P = self._ekf.x.copy(), self._ekf.P.copy()

    def _trim_history(self) -> None:
        horizon_ns = self._history[-1].t_ns - self.params.history_s * 1e9
        drop = 0
        while drop < len(self._history) - 1 and self._history[drop + 1].t_ns <= horizon_ns:
            drop += 1
        if drop:
            del self._history[:drop]

    # ----- filter steps

    def _predict(self, imu: ImuSample, dt_ns: int) -> None:
        if dt_ns <= 0:
            return
        u = _ImuInput(imu.gyro_z_radps, imu.accel_x_mps2, dt_ns / 1e9)
        self._ekf.F, self._ekf.Q = transition(self._ekf.x, u, self._q_rate)
        self._ekf.predict(u)
        self._normalise()

    def _apply(self, m: _Measurement, gate: bool) -> bool:
        """Update with ``m``; False if the GPS gate rejected it."""
        ekf = self._ekf
        if m.kind == "gps":
            return self._gps(m, gate)
        if m.kind == "speed":
            ekf.update(m.z, _speed_h, _speed_hx, R=m.R)
        else:
            bias = _BIAS_OF_MAG[m.mag_index]
            ekf.update(m.z, _mag_h, _mag_hx, R=m.R, args=(bias,), hx_args=(bias,), residual=_angle_residual)
        self._normalise()
        return True

    def _gps(self, m: _Measurement, gate: bool) -> bool:
        """Gate a new fix (and keep the books on it); a replayed one was accepted already."""
        ekf = self._ekf
        if gate:
            innovation = m.z - ekf.x[[E, N]]
            S = ekf.P[np.ix_([E, N], [E, N])] + m.R
            if float(innovation @ np.linalg.solve(S, innovation)) > self.params.gps_gate_chi2:
                self._reject_gps(m)
                return False
            self._accept_gps(m)
        ekf.update(m.z, _gps_h, _gps_hx, R=m.R)
        self._normalise()
        return True

    def _accept_gps(self, m: _Measurement) -> None:
        self._rejections = 0
        self._first_rejection_ns = None
        if self._last_gps_ns is None or m.t_ns >= self._last_gps_ns:
            self._last_gps_ns = m.t_ns
            self._gps_quality = m.quality

    def _reject_gps(self, m: _Measurement) -> None:
        """Count the rejection; if the GPS has disagreed long and often enough, believe it."""
        p = self.params
        self.gps_rejected += 1
        self._rejections += 1
        if self._first_rejection_ns is None:
            self._first_rejection_ns = m.t_ns
        persisted_s = (m.t_ns - self._first_rejection_ns) / 1e9
        if self._rejections >= p.reacquire_min_rejections and persisted_s >= p.reacquire_after_s:
            self._reacquire(m)

    def _reacquire(self, m: _Measurement) -> None:
        """Reset the position to the fix, uncorrelated, with its covariance inflated."""
        ekf = self._ekf
        ekf.x[[E, N]] = m.z
        for i in (E, N):
            ekf.P[i, :] = 0.0
            ekf.P[:, i] = 0.0
        ekf.P[np.ix_([E, N], [E, N])] = m.R * self.params.reacquire_position_variance_scale
        self.reacquisitions += 1
        self._reacquired = True
        self._accept_gps(m)

    def _normalise(self) -> None:
        """Yaw back into [-pi, pi] (an update can push it over) and P exactly symmetric (round-off
        in F P F' and the Joseph form leaves it asymmetric in the last bits, which accumulates)."""
        ekf = self._ekf
        ekf.x[YAW] = wrap(ekf.x[YAW])
        ekf.P = 0.5 * (ekf.P + ekf.P.T)
