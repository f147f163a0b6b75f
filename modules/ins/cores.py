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
    DIM_X,
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
    wrap,
)

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
    offsets[:, YAW] = np.remainder(offsets[:, YAW] + math.pi, math.tau) - math.pi
    return sigmas[0] + weights @ offsets


def _state_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = np.subtract(a, b)
    d[..., YAW] = np.remainder(d[..., YAW] + math.pi, math.tau) - math.pi
    return d


def _angle_mean(sigmas: np.ndarray, weights: np.ndarray) -> np.ndarray:
    offsets = np.remainder(sigmas - sigmas[0] + math.pi, math.tau) - math.pi
    return sigmas[0] + weights @ offsets


def _angle_residuals(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.remainder(np.subtract(a, b) + math.pi, math.tau) - math.pi


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


class _VectorisedUkf(UnscentedKalmanFilter):
    """filterpy's UKF with its two per-sigma-point Python loops done as array operations: the
    motion model on all points at once, and the cross covariance as one weighted product."""

    def compute_process_sigmas(self, dt: float, fx: object = None, **fx_args: object) -> None:
        sigmas = self.points_fn.sigma_points(self.x, self.P)
        self.sigmas_f = _propagate_sigmas(sigmas, fx_args["u"])  # type: ignore[arg-type]

    def cross_variance(self, x: np.ndarray, z: np.ndarray, sigmas_f: np.ndarray, sigmas_h: np.ndarray) -> np.ndarray:
        dx = _state_residual(sigmas_f, x)
        dz = self.residual_z(sigmas_h, z)
        return (dx * self.Wc[:, None]).T @ dz


class UkfCore:
    # Van der Merwe's scaling: alpha 0.5 puts the points 1.5 sigma out in 9 dimensions, wide
    # enough to see the heading nonlinearity, close enough to stay where the model is valid.
    ALPHA, BETA, KAPPA = 0.5, 2.0, 0.0

    def __init__(self, params: InsParams) -> None:
        self._q_rate = process_noise_rate(params)
        # Plain subtraction to spread the points: a yaw just past +-pi is harmless, since means
        # and residuals are taken on the circle.
        points = MerweScaledSigmaPoints(DIM_X, self.ALPHA, self.BETA, self.KAPPA)
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
        ukf.x[YAW] = wrap(float(ukf.x[YAW]))

    def update_gps(self, z: np.ndarray, R: np.ndarray) -> None:
        self._update(z, R, gps_hx, np.subtract, None)

    def update_speed(self, z: np.ndarray, R: np.ndarray) -> None:
        self._update(z, R, speed_hx, np.subtract, None)

    def update_mag(self, z: np.ndarray, R: np.ndarray, bias_index: int) -> None:
        self._update(z, R, lambda x: mag_hx(x, bias_index), _angle_residuals, _angle_mean)

    def _update(
        self,
        z: np.ndarray,
        R: np.ndarray,
        hx: Callable[[np.ndarray], np.ndarray],
        residual: Callable[[np.ndarray, np.ndarray], np.ndarray],
        mean: Callable[[np.ndarray, np.ndarray], np.ndarray] | None,
    ) -> None:
        """One update from sigma points drawn at the current estimate: several measurements may
        arrive between two predictions, and each must see the posterior of the one before."""
        ukf = self._ukf
        ukf.sigmas_f = ukf.points_fn.sigma_points(ukf.x, ukf.P)
        ukf.residual_z, ukf.z_mean = residual, mean
        ukf.update(z, R=R, UT=_unscented_transform, hx=hx)
        ukf.x[YAW] = wrap(float(ukf.x[YAW]))
