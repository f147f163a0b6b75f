"""Closed-loop runs of the controller against the simulated vehicle dynamics, in process.

The controller reads the true state here on purpose: these runs test the control laws, not the
navigation. The cross-track error is measured independently of the controller's own path
interface, at the rear axle (the vehicle's position), against the path polyline.
"""

from __future__ import annotations

import math
from collections import deque
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from modules.control.controller import ControllerSettings, Mode, Motion, VehicleController
from modules.control.corridor_guard import CorridorGuard
from modules.control.path_tracking import TrackedPath
from modules.sim.vehicle import VehicleParams, VehicleState, step
from protocol.messages import ActuatorCommand

SIM_DT_S = 0.01  # the simulator's 100 Hz
CONTROL_EVERY = 2  # control at 50 Hz


class Run(NamedTuple):
    t_s: NDArray[np.float64]
    cross_track_m: NDArray[np.float64]  # signed, left positive, rear axle vs the path
    speed_mps: NDArray[np.float64]
    yaw_rad: NDArray[np.float64]
    steering_rad: NDArray[np.float64]  # commands, one per control step
    modes: list[Mode]
    progress_m: float

    @property
    def rms_cross_track_m(self) -> float:
        return float(np.sqrt(np.mean(self.cross_track_m**2)))

    def after(self, t_s: float) -> NDArray[np.bool_]:
        return self.t_s >= t_s


def signed_distance(east: NDArray[np.float64], north: NDArray[np.float64], x: float, y: float, hint: int) -> tuple:
    """(signed distance, segment) to the polyline near segment ``hint``: a plain reference search."""
    lo, hi = max(0, hint - 40), min(len(east) - 1, hint + 40)
    ax, ay = east[lo:hi], north[lo:hi]
    dx, dy = east[lo + 1 : hi + 1] - ax, north[lo + 1 : hi + 1] - ay
    t = np.clip(((x - ax) * dx + (y - ay) * dy) / (dx * dx + dy * dy), 0.0, 1.0)
    d = np.hypot(x - ax - t * dx, y - ay - t * dy)
    k = int(np.argmin(d))
    side = dx[k] * (y - ay[k]) - dy[k] * (x - ax[k])
    return math.copysign(float(d[k]), side), lo + k


def drive(
    settings: ControllerSettings,
    east: NDArray[np.float64],
    north: NDArray[np.float64],
    speed: NDArray[np.float64],
    start: tuple[float, float, float, float],
    duration_s: float,
    delay_steps: int = 0,
    guard: CorridorGuard | None = None,
) -> Run:
    """Drive the path from ``start`` (east, north, yaw, speed) for ``duration_s`` or until the
    controller has brought the vehicle to rest at the end of the path. ``delay_steps``: the
    controller sees the pose that many control periods (20 ms) late; ``guard``: the controller's
    corridor guard."""
    params = VehicleParams()
    controller = VehicleController(settings)
    controller.guard = guard
    controller.set_path(TrackedPath(east, north, speed))
    state = VehicleState(east_m=start[0], north_m=start[1], yaw_rad=start[2], speed_mps=start[3])
    command = ActuatorCommand(0.0, 0.0, 0.0)
    s_path = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(east), np.diff(north)))])
    times, errors, speeds, yaws, steering, modes = [], [], [], [], [], []
    hint = 0
    seen: deque[Motion] = deque()
    steps = round(duration_s / SIM_DT_S)
    for k in range(steps):
        if k % CONTROL_EVERY == 0:
            seen.append(Motion.of(state))
            motion = seen.popleft() if len(seen) > delay_steps else seen[0]
            out = controller.drive(motion, SIM_DT_S * CONTROL_EVERY)
            command = ActuatorCommand(out.throttle, out.brake, out.steering_rad)
            steering.append(out.steering_rad)
            modes.append(out.mode)
            if out.mode in (Mode.END, Mode.HOLD) and state.speed_mps == 0.0 and k > 100:
                break
        step(state, command, SIM_DT_S, params)
        error, hint = signed_distance(east, north, state.east_m, state.north_m, hint)
        times.append((k + 1) * SIM_DT_S)
        errors.append(error)
        speeds.append(state.speed_mps)
        yaws.append(state.yaw_rad)
    return Run(
        np.array(times),
        np.array(errors),
        np.array(speeds),
        np.array(yaws),
        np.array(steering),
        modes,
        float(s_path[hint]),
    )


def sign_changes(values: NDArray[np.float64], ignore_below: float = 1e-4) -> int:
    """How often ``values`` change sign, ignoring values within ``ignore_below`` of zero."""
    signs = np.sign(values[np.abs(values) > ignore_below])
    return int(np.count_nonzero(np.diff(signs)))


def s_curve(radius_m: float, speed_mps: float) -> tuple[NDArray[np.float64], ...]:
    """30 m east, a left quarter circle, a right quarter circle, 60 m straight; 0.5 m spacing.
    The speed tapers to a stop at the end at 1.5 m/s^2, as the course interpolation plans it."""
    points = [(x, 0.0) for x in np.arange(0.0, 30.0, 0.5)]
    n = int(radius_m * math.pi / 2 / 0.5)
    for a in np.linspace(0.0, math.pi / 2, n, endpoint=False):
        points.append((30.0 + radius_m * math.sin(a), radius_m * (1 - math.cos(a))))
    cx, cy = 30.0 + radius_m, radius_m  # end of the left arc, heading north
    for a in np.linspace(0.0, math.pi / 2, n, endpoint=False):
        points.append((cx + radius_m - radius_m * math.cos(a), cy + radius_m * math.sin(a)))
    ex, ey = cx + radius_m, cy + radius_m  # heading east again
    points += [(ex + x, ey) for x in np.arange(0.0, 60.01, 0.5)]
    east = np.array([p[0] for p in points])
    north = np.array([p[1] for p in points])
    to_go = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(east), np.diff(north)))])
    to_go = to_go[-1] - to_go
    return east, north, np.minimum(speed_mps, np.sqrt(2.0 * 1.5 * to_go))
