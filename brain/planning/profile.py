"""Lateral offset profiles d(s) in the corridor frame: quintic blends, holds, and their sequence.

A blend moves the offset from (d0, slope m0, no curvature) to (d1, level, no curvature) over a
length L: the quintic with those six boundary conditions, so a swerve starts and ends without a
kink or a jump in curvature, and a new blend can start from the middle of an old one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def blend(
    x: ArrayLike, length: ArrayLike, d0: ArrayLike, m0: ArrayLike, d1: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Offset and slope at ``x`` metres into a quintic blend (clamped to [0, length]); broadcasts."""
    length = np.asarray(length, dtype=float)
    x = np.asarray(np.clip(np.asarray(x, dtype=float), 0.0, length), dtype=float)
    coefficients = blend_coefficients(length, d0, m0, d1)
    return _poly(coefficients, x), _poly_slope(coefficients, x)


def blend_value(x: ArrayLike, length: ArrayLike, d0: ArrayLike, m0: ArrayLike, d1: ArrayLike) -> FloatArray:
    """Offset only at ``x`` metres into a blend (clamped to [0, length]); broadcasts."""
    length = np.asarray(length, dtype=float)
    x = np.asarray(np.minimum(np.maximum(np.asarray(x, dtype=float), 0.0), length), dtype=float)
    return _poly(blend_coefficients(length, d0, m0, d1), x)


def blend_coefficients(length: ArrayLike, d0: ArrayLike, m0: ArrayLike, d1: ArrayLike) -> FloatArray:
    """Coefficients a0..a5 (last axis) of d(x) = sum a_k x^k for a blend."""
    length, d0, m0, d1 = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (length, d0, m0, d1)))
    if np.any(length <= 0.0):
        raise ValueError("a blend needs a positive length")
    rise = d1 - d0
    a3 = (10.0 * rise - 6.0 * m0 * length) / length**3
    a4 = (-15.0 * rise + 8.0 * m0 * length) / length**4
    a5 = (6.0 * rise - 3.0 * m0 * length) / length**5
    return np.stack([d0, m0, np.zeros_like(d0), a3, a4, a5], axis=-1)


def _poly(c: FloatArray, x: FloatArray) -> FloatArray:
    c = np.asarray(c)
    return c[..., 0] + x * (c[..., 1] + x * (c[..., 2] + x * (c[..., 3] + x * (c[..., 4] + x * c[..., 5]))))


def _poly_slope(c: FloatArray, x: FloatArray) -> FloatArray:
    c = np.asarray(c)
    return c[..., 1] + x * (2 * c[..., 2] + x * (3 * c[..., 3] + x * (4 * c[..., 4] + x * 5 * c[..., 5])))


@dataclass(frozen=True)
class LateralProfile:
    """Piecewise quintic d(s): piece i covers [start_m[i], end_m[i]] with local coordinate
    s - start_m[i]. Pieces are contiguous; before the first and after the last, d stays level
    at the end value."""

    start_m: FloatArray
    end_m: FloatArray
    coefficients: FloatArray  # (pieces, 6)

    def __post_init__(self) -> None:
        if len(self.start_m) == 0 or self.coefficients.shape != (len(self.start_m), 6):
            raise ValueError("a lateral profile needs at least one piece with six coefficients each")
        if np.any(self.end_m < self.start_m) or np.any(np.abs(self.start_m[1:] - self.end_m[:-1]) > 1e-9):
            raise ValueError("profile pieces must be contiguous and ordered")

    @classmethod
    def level(cls, s_m: float, d_m: float) -> LateralProfile:
        """A constant offset (e.g. the centre line, d = 0)."""
        return cls(np.array([s_m]), np.array([s_m]), np.array([[d_m, 0.0, 0.0, 0.0, 0.0, 0.0]]))

    def at(self, s_m: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(d, slope dd/ds) at stations."""
        s = np.asarray(s_m, dtype=float)
        index = np.clip(np.searchsorted(self.start_m, s, side="right") - 1, 0, len(self.start_m) - 1)
        x = np.clip(s - self.start_m[index], 0.0, self.end_m[index] - self.start_m[index])
        coefficients = self.coefficients[index]
        slope = np.where((s < self.start_m[0]) | (s > self.end_m[-1]), 0.0, _poly_slope(coefficients, x))
        return _poly(coefficients, x), slope

    def until(self, s_m: float) -> LateralProfile:
        """This profile ending exactly at ``s_m``: later pieces dropped, the last one cut there, or
        a level piece added when the profile ended before. Before its start the profile is level,
        so ending it there is that level (a vehicle that rolled or backed behind the station its
        path was planned from)."""
        if s_m < self.start_m[0]:
            return LateralProfile.level(s_m, float(self.at(self.start_m[0])[0]))
        keep = self.start_m < s_m
        keep[0] = True
        cut = LateralProfile(self.start_m[keep], np.minimum(self.end_m[keep], s_m), self.coefficients[keep])
        if cut.end_m[-1] < s_m:
            final = float(self.at(cut.end_m[-1])[0])
            return cut.then(float(cut.end_m[-1]), s_m, [final, 0.0, 0.0, 0.0, 0.0, 0.0])
        return cut

    def since(self, s_m: float) -> LateralProfile:
        """Pieces that end before ``s_m`` dropped (the result is unchanged from ``s_m`` on)."""
        keep = self.end_m >= s_m
        if not keep.any():
            keep[-1] = True
        return LateralProfile(self.start_m[keep], self.end_m[keep], self.coefficients[keep])

    def then(self, start_m: float, end_m: float, coefficients: ArrayLike) -> LateralProfile:
        """This profile with one more piece appended at its end (which must be ``start_m``)."""
        if abs(start_m - self.end_m[-1]) > 1e-9:
            raise ValueError(f"a piece starting at {start_m} cannot follow one ending at {self.end_m[-1]}")
        return LateralProfile(
            np.append(self.start_m, start_m),
            np.append(self.end_m, end_m),
            np.vstack([self.coefficients, np.asarray(coefficients, dtype=float).reshape(1, 6)]),
        )


def swerve(
    base: LateralProfile,
    begin_m: float,
    offset_m: float,
    transition_m: float,
    return_m: float,
    back_m: float = 0.0,
) -> LateralProfile:
    """``base`` until ``begin_m``, then a blend to ``offset_m`` over ``transition_m``, level until
    ``return_m``, then a blend of the same length back to ``back_m`` (the centre line)."""
    d0, m0 = (float(v) for v in base.at(begin_m))
    reach = begin_m + transition_m
    return_m = max(return_m, reach)
    level = [offset_m, 0.0, 0.0, 0.0, 0.0, 0.0]
    return (
        base.until(begin_m)
        .then(begin_m, reach, blend_coefficients(transition_m, d0, m0, offset_m))
        .then(reach, return_m, level)
        .then(return_m, return_m + transition_m, blend_coefficients(transition_m, offset_m, 0.0, back_m))
    )
