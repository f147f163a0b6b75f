"""Lateral profiles: quintic blends and the swerves built from them."""

from __future__ import annotations

import numpy as np
import pytest

from brain.planning.profile import LateralProfile, blend, blend_coefficients, swerve


def test_a_blend_meets_its_six_boundary_conditions() -> None:
    length, d0, m0, d1 = 12.0, 0.5, 0.2, -2.0
    c = blend_coefficients(length, d0, m0, d1)
    value = np.polynomial.Polynomial(c)
    slope, bend = value.deriv(), value.deriv(2)
    assert (value(0.0), slope(0.0), bend(0.0)) == pytest.approx((d0, m0, 0.0))
    assert (value(length), slope(length), bend(length)) == pytest.approx((d1, 0.0, 0.0), abs=1e-12)
    d, m = blend([-1.0, 6.0, 20.0], length, d0, m0, d1)
    assert d[0] == pytest.approx(d0) and d[2] == pytest.approx(d1)  # clamped outside [0, L]
    assert d[1] == pytest.approx(value(6.0)) and m[1] == pytest.approx(slope(6.0))


def test_a_swerve_is_smooth_where_its_pieces_join() -> None:
    base = LateralProfile.level(0.0, 0.0)
    path = swerve(base, begin_m=10.0, offset_m=3.0, transition_m=15.0, return_m=40.0)
    s = np.linspace(0.0, 80.0, 8001)
    d, m = path.at(s)
    assert np.max(np.abs(np.diff(d))) < 0.01 and np.max(np.abs(np.diff(m))) < 0.01
    assert d[s <= 10.0] == pytest.approx(0.0)
    assert d[(s >= 25.0) & (s <= 40.0)] == pytest.approx(3.0)
    assert d[s >= 55.0] == pytest.approx(0.0, abs=1e-12)


def test_a_new_swerve_starts_from_the_old_one_mid_blend() -> None:
    first = swerve(LateralProfile.level(0.0, 0.0), 0.0, 3.0, 20.0, 60.0)
    second = swerve(first, 8.0, -2.0, 10.0, 30.0)
    s = np.array([0.0, 4.0, 8.0])
    np.testing.assert_allclose(second.at(s)[0], first.at(s)[0])
    np.testing.assert_allclose(second.at(8.0)[1], first.at(8.0)[1])  # same slope where they part
    assert second.at(25.0)[0] == pytest.approx(-2.0)


def test_cutting_and_pruning_profiles() -> None:
    path = swerve(LateralProfile.level(0.0, 1.0), 5.0, 2.0, 10.0, 20.0)
    assert path.until(12.0).end_m[-1] == 12.0
    longer = path.until(50.0)
    assert longer.end_m[-1] == 50.0 and longer.at(45.0)[0] == pytest.approx(0.0, abs=1e-12)
    s = np.linspace(16.0, 50.0, 50)
    np.testing.assert_allclose(path.since(16.0).at(s)[0], path.at(s)[0])
    with pytest.raises(ValueError, match="follow"):
        path.then(3.0, 4.0, np.zeros(6))
    # Before its start a profile is level, so it can end there (a vehicle that backed up behind it).
    behind = path.until(-1.0)
    assert behind.end_m[-1] == -1.0 and behind.at(-1.0)[0] == pytest.approx(1.0)
    assert swerve(path, -1.0, 3.0, 4.0, 10.0).at(3.0)[0] == pytest.approx(3.0)
