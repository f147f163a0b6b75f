"""Angles on the circle: one definition of wrapping for every module (headings, yaw errors)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray


def wrap_angle(angle_rad: float) -> float:
    """``angle_rad`` wrapped into [-pi, pi]."""
    return math.remainder(angle_rad, math.tau)


def wrap_angles(angles_rad: ArrayLike) -> NDArray[np.float64]:
    """Element-wise ``wrap_angle`` for arrays, into [-pi, pi)."""
    return np.remainder(np.asarray(angles_rad, dtype=float) + math.pi, math.tau) - math.pi
