"""The navigation filter: IMU-driven prediction, DGPS, speedometer and magnetometer updates,
applied at their measurement times, gated, with the books kept.

Sans-IO: messages and their measurement times go in, ``VehicleState`` comes out; no clock, no bus.
The model is modules/ins/model.py; the estimator (EKF or UKF, both filterpy) is modules/ins/cores.py.

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

from brain.corridor import GeodeticOrigin
from modules.ins.cores import make_core
from modules.ins.model import (
    BG,
    BIAS_OF_MAG,
    DIM_X,
    SCALE,
    SPD,
    YAW,
    E,
    ImuInput,
    InsParams,
    N,
    process_noise_rate,
    propagate,
    transition,
)
from protocol.messages import GpsFix, ImuSample, MagHeading, NavQuality, VehicleState, WheelSpeed
from rascal.runtime.angles import wrap_angle

UNINITIALISED_VARIANCE = 1e12  # what state() reports before the filter has a solution


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


class InsFilter:
    """The navigation filter. Feed every message with its measurement time; read ``state``.

    It initialises at the first GPS fix once a magnetometer heading is known (yaw comes from the
    compass, position from the fix, speed from the speedometer if heard). Counters:
    ``gps_rejected`` (fixes failing the gate), ``reacquisitions``, ``late_rejected`` (measurements
    older than the history), ``replayed`` (measurements applied by rewinding), ``imu_dropped``
    (IMU samples not newer than the newest state: the state cannot be predicted backwards),
    ``ahead_rejected`` (measurements more than the history ahead of the newest IMU sample).
    """

    def __init__(self, origin: GeodeticOrigin, params: InsParams | None = None, kind: str = "ekf") -> None:
        self.origin = origin
        self.params = params or InsParams()
        self.kind = kind
        self._q_rate = process_noise_rate(self.params)
        self._core = make_core(kind, self.params)
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
        return self._core.x.copy()

    @property
    def P(self) -> np.ndarray:
        """The newest state covariance (a copy)."""
        return self._core.P.copy()

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
        if msg.magnetometer not in BIAS_OF_MAG:
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
            u = ImuInput(imu.gyro_z_radps, imu.accel_x_mps2, (t_ns - step.t_ns) / 1e9)
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
        x[YAW] = wrap_angle(math.pi / 2 - mag.heading_from_north_rad)
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
        b = BIAS_OF_MAG[mag.magnetometer]
        # yaw0 = yaw - bias - noise: its error and the bias estimate's (0 - bias) are both minus the
        # bias, so they move together. The wrong sign made the compass look like it pinned the yaw.
        P[YAW, b] = P[b, YAW] = bias_var
        self._core.x, self._core.P = x, P
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
            self._core.x, self._core.P = step.x.copy(), step.P.copy()
            if self._apply(m, gate=True):
                step.measurements.append(m)
            step.x, step.P = self._core.x.copy(), self._core.P.copy()
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
        self._core.x, self._core.P = prev.x.copy(), prev.P.copy()
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
        step.x, step.P = self._core.x.copy(), self._core.P.copy()

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
        self._core.predict(ImuInput(imu.gyro_z_radps, imu.accel_x_mps2, dt_ns / 1e9))
        self._normalise()

    def _apply(self, m: _Measurement, gate: bool) -> bool:
        """Update with ``m``; False if the GPS gate rejected it."""
        core = self._core
        if m.kind == "gps":
            return self._gps(m, gate)
        if m.kind == "speed":
            core.update_speed(m.z, m.R)
        else:
            core.update_mag(m.z, m.R, BIAS_OF_MAG[m.mag_index])
        self._normalise()
        return True

    def _gps(self, m: _Measurement, gate: bool) -> bool:
        """Gate a new fix (and keep the books on it); a replayed one was accepted already."""
        core = self._core
        if gate:
            innovation = m.z - core.x[[E, N]]
            S = core.P[np.ix_([E, N], [E, N])] + m.R
            if float(innovation @ np.linalg.solve(S, innovation)) > self.params.gps_gate_chi2:
                self._reject_gps(m)
                return False
            self._accept_gps(m)
        core.update_gps(m.z, m.R)
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
        core = self._core
        core.x[[E, N]] = m.z
        for i in (E, N):
            core.P[i, :] = 0.0
            core.P[:, i] = 0.0
        core.P[np.ix_([E, N], [E, N])] = m.R * self.params.reacquire_position_variance_scale
        self.reacquisitions += 1
        self._reacquired = True
        self._accept_gps(m)

    def _normalise(self) -> None:
        """Yaw back into [-pi, pi] (an update can push it over) and P exactly symmetric (round-off
        in F P F' and the Joseph form leaves it asymmetric in the last bits, which accumulates)."""
        core = self._core
        core.x[YAW] = wrap_angle(core.x[YAW])
        core.P = 0.5 * (core.P + core.P.T)
