"""The two selectable estimators behind the navigation filter, on filterpy, with one interface.

``ekf``: filterpy's ExtendedKalmanFilter with our Jacobians (``predict`` is ``P = F P F' + Q``,
``update`` the Joseph form). ``ukf``: filterpy's UnscentedKalmanFilter with Van der Merwe's scaled
sigma points, the sigma-point family Kratos used (it ran a square-root central-difference
filter); it needs no Jacobians and captures the heading nonlinearity to second order. Both see
the same model (modules/ins/model.py); the navigator above them owns time, gating and books.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter

from modules.ins.model import (
    BA,
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
    angle_residual,
    gps_h,
    gps_hx,
    mag_h,
    mag_hx,
    process_noise_rate,
    propagate,
    speed_h,
    speed_hx,
    transition,
)
from rascal.runtime.angles import wrap_angle, wrap_angles

FILTERS = ("ekf", "ukf")


class FilterCore(Protocol):
    """What the navigator needs of an estimator: the state, and predict/update in place."""

    x: np.ndarray
    P: np.ndarray

    def predict(self, u: ImuInput) -> None: ...

    def update_gps(self, z: np.ndarray, R: np.ndarray) -> None: ...

    def update_speed(self, z: np.ndarray, R: np.ndarray) -> None: ...

    def update_mag(self, z: np.ndarray, R: np.ndarray, bias_index: int) -> None: ...


def make_core(kind: str, params: InsParams) -> FilterCore:
    if kind == "ekf":
        return EkfCore(params)
    if kind == "ukf":
        return UkfCore(params)
    raise ValueError(f"ins: filter must be one of {FILTERS}, not {kind!r}")


class _PlanarEkf(ExtendedKalmanFilter):
    """filterpy's EKF with the nonlinear motion model as its state prediction."""

    def predict_x(self, u: ImuInput) -> None:  # type: ignore[override]
        self.x = propagate(self.x, u)


class EkfCore:
    def __init__(self, params: InsParams) -> None:
        self._q_rate = process_noise_rate(params)
        self._ekf = _PlanarEkf(dim_x=DIM_X, dim_z=1)

    @property
    def x(self) -> np.ndarray:
        return self._ekf.x

    @x.setter
    def x(self, value: np.ndarray) -> None:
        self._ekf.x = value

    @property
    def P(self) -> np.ndarray:
        return self._ekf.P

    @P.setter
    def P(self, value: np.ndarray) -> None:
        self._ekf.P = value

    def predict(self, u: ImuInput) -> None:
        self._ekf.F, self._ekf.Q = transition(self._ekf.x, u, self._q_rate)
        self._ekf.predict(u)

    def update_gps(self, z: np.ndarray, R: np.ndarray) -> None:
        self._ekf.update(z, gps_h, gps_hx, R=R)

    def update_speed(self, z: np.ndarray, R: np.ndarray) -> None:
        self._ekf.update(z, speed_h, speed_hx, R=R)

    def update_mag(self, z: np.ndarray, R: np.ndarray, bias_index: int) -> None:
        self._ekf.update(z, mag_h, mag_hx, R=R, args=(bias_index,), hx_args=(bias_index,), residual=angle_residual)


def _propagate_sigmas(sigmas: np.ndarray, u: ImuInput) -> np.ndarray:
    """``propagate`` for every sigma point at once (rows), yaw left unwrapped: the points stay
    continuous around their mean."""
    dt = u.dt_s
    rate = u.gyro_z_radps - sigmas[:, BG]
    accel = u.accel_x_mps2 - sigmas[:, BA]
    mean_speed = sigmas[:, SPD] + 0.5 * accel * dt
    heading = sigmas[:, YAW] + 0.5 * rate * dt
    out = sigmas.copy()
    out[:, E] += mean_speed * dt * np.cos(heading)
    out[:, N] += mean_speed * dt * np.sin(heading)
    out[:, YAW] += rate * dt
    out[:, SPD] += accel * dt
    return out


def _state_mean(sigmas: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted mean with yaw averaged on the circle (as offsets from the first point)."""
    offsets = sigmas - sigmas[0]
    offsets[:, YAW] = wrap_angles(offsets[:, YAW])
    return sigmas[0] + weights @ offsets


def _state_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = np.subtract(a, b)
    d[..., YAW] = wrap_angles(d[..., YAW])
    return d


def _angle_mean(sigmas: np.ndarray, weights: np.ndarray) -> np.ndarray:
    offsets = wrap_angles(sigmas - sigmas[0])
    return sigmas[0] + weights @ offsets


def _angle_residuals(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return wrap_angles(np.subtract(a, b))


def _unscented_transform(
    sigmas: np.ndarray,
    Wm: np.ndarray,
    Wc: np.ndarray,
    noise_cov: np.ndarray,
    mean_fn: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    residual_fn: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """filterpy's unscented transform with the residual taken over all points at once (its own
    loops over the points in Python when the residual is not a plain subtraction)."""
    mean = Wm @ sigmas if mean_fn is None else mean_fn(sigmas, Wm)
    residuals = (residual_fn or np.subtract)(sigmas, mean[np.newaxis, :])
    return mean, (residuals * Wc[:, None]).T @ residuals + noise_cov


class _CholeskySigmaPoints(MerweScaledSigmaPoints):
    """Van der Merwe's points from one numpy Cholesky factor, all at once (filterpy builds them
    point by point behind SciPy's checked factorisation). Same points, same order, same weights."""

    def sigma_points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        lambda_ = self.alpha**2 * (self.n + self.kappa) - self.n
        # filterpy spreads by the rows of the upper factor U (U'U = M): the columns of numpy's L.
        offsets = np.linalg.cholesky((lambda_ + self.n) * P).T
        return np.vstack([x, x + offsets, x - offsets])


class _VectorisedUkf(UnscentedKalmanFilter):
    """filterpy's UKF with its per-sigma-point Python loops done as array operations: the motion
    model on all points at once, and an update whose measurement model takes all points too."""

    def compute_process_sigmas(self, dt: float, fx: object = None, **fx_args: object) -> None:
        sigmas = self.points_fn.sigma_points(self.x, self.P)
        self.sigmas_f = _propagate_sigmas(sigmas, fx_args["u"])  # type: ignore[arg-type]

    def update_points(
        self,
        z: np.ndarray,
        R: np.ndarray,
        hx_points: Callable[[np.ndarray], np.ndarray],
        residual: Callable[[np.ndarray, np.ndarray], np.ndarray],
        mean: Callable[[np.ndarray, np.ndarray], np.ndarray] | None,
    ) -> None:
        """The UKF update (filterpy's ``update``) with ``hx_points`` mapping every sigma point
        (rows) to its predicted measurement at once. Points are redrawn at the current estimate:
        several measurements may arrive between two predictions, each after the one before."""
        sigmas = self.points_fn.sigma_points(self.x, self.P)
        sigmas_h = hx_points(sigmas)
        z_mean, S = _unscented_transform(sigmas_h, self.Wm, self.Wc, R, mean, residual)
        dx = _state_residual(sigmas, self.x)
        dz = residual(sigmas_h, z_mean)
        cross = (dx * self.Wc[:, None]).T @ dz
        gain = cross @ np.linalg.inv(S)
        self.x = self.x + gain @ residual(z, z_mean)
        self.P = self.P - gain @ S @ gain.T


def _gps_points(sigmas: np.ndarray) -> np.ndarray:
    return sigmas[:, [E, N]]


def _speed_points(sigmas: np.ndarray) -> np.ndarray:
    return (sigmas[:, SCALE] * sigmas[:, SPD])[:, np.newaxis]


def _mag_points(bias_index: int) -> Callable[[np.ndarray], np.ndarray]:
    return lambda sigmas: (math.pi / 2 - sigmas[:, YAW] + sigmas[:, bias_index])[:, np.newaxis]


class UkfCore:
    # Van der Merwe's scaling: alpha 0.5 puts the points 1.5 sigma out in 9 dimensions, wide
    # enough to see the heading nonlinearity, close enough to stay where the model is valid.
    ALPHA, BETA, KAPPA = 0.5, 2.0, 0.0

    def __init__(self, params: InsParams) -> None:
        self._q_rate = process_noise_rate(params)
        # Plain addition spreads the points: a yaw just past +-pi is harmless, since means and
        # residuals are taken on the circle.
        points = _CholeskySigmaPoints(DIM_X, self.ALPHA, self.BETA, self.KAPPA)
        self._ukf = _VectorisedUkf(
            dim_x=DIM_X,
            dim_z=1,
            dt=0.01,
            hx=gps_hx,
            fx=propagate,
            points=points,
            x_mean_fn=_state_mean,
            residual_x=_state_residual,
        )
        self._mag_points = {index: _mag_points(index) for index in BIAS_OF_MAG.values()}

    @property
    def x(self) -> np.ndarray:
        return self._ukf.x

    @x.setter
    def x(self, value: np.ndarray) -> None:
        self._ukf.x = value

    @property
    def P(self) -> np.ndarray:
        return self._ukf.P

    @P.setter
    def P(self, value: np.ndarray) -> None:
        self._ukf.P = value

    def predict(self, u: ImuInput) -> None:
        ukf = self._ukf
        ukf.Q = np.diag(self._q_rate * u.dt_s)
        ukf.predict(dt=u.dt_s, UT=_unscented_transform, u=u)
        ukf.x[YAW] = wrap_angle(float(ukf.x[YAW]))

    def update_gps(self, z: np.ndarray, R: np.ndarray) -> None:
        self._ukf.update_points(z, R, _gps_points, np.subtract, None)

    def update_speed(self, z: np.ndarray, R: np.ndarray) -> None:
        self._ukf.update_points(z, R, _speed_points, np.subtract, None)

    def update_mag(self, z: np.ndarray, R: np.ndarray, bias_index: int) -> None:
        self._ukf.update_points(z, R, self._mag_points[bias_index], _angle_residuals, _angle_mean)
        self._ukf.x[YAW] = wrap_angle(float(self._ukf.x[YAW]))
