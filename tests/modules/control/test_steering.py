"""Steering laws: Stanley/Hoffmann signs and values, RASCAL's PD heading controller."""

from __future__ import annotations

import math

import pytest

from modules.control.steering import PdGains, PdHeadingController, StanleyGains, heading_gain, stanley_steering

GAINS = StanleyGains(gain=2.5, softening_mps=1.0)


def test_stanley_on_the_path_and_aligned_steers_straight() -> None:
    assert stanley_steering(0.0, 0.0, 10.0, GAINS) == 0.0


def test_stanley_steers_back_towards_the_path() -> None:
    assert stanley_steering(0.0, 1.0, 10.0, GAINS) < 0.0  # left of the path: steer right
    assert stanley_steering(0.0, -1.0, 10.0, GAINS) > 0.0  # right of it: steer left
    assert stanley_steering(0.2, 0.0, 10.0, GAINS) == pytest.approx(0.2)  # path turns left of us: steer left


def test_stanley_is_hoffmann_s_law() -> None:
    expected = 0.1 - math.atan(2.5 * 0.8 / (1.0 + 6.0))
    assert stanley_steering(0.1, 0.8, 6.0, GAINS) == pytest.approx(expected)


def test_stanley_cross_track_term_is_bounded_and_finite_at_standstill() -> None:
    assert stanley_steering(0.0, 1e6, 0.0, GAINS) == pytest.approx(-math.pi / 2)
    assert math.isfinite(stanley_steering(0.0, 0.5, 0.0, GAINS))
    # The same error asks for less steering the faster the vehicle goes.
    assert abs(stanley_steering(0.0, 0.5, 15.0, GAINS)) < abs(stanley_steering(0.0, 0.5, 3.0, GAINS))


def test_stanley_yaw_damping_opposes_yaw_rate_the_path_does_not_ask_for() -> None:
    damped = StanleyGains(yaw_damping_s=0.1)
    # On a straight path, turning left at 0.3 rad/s: steer right against it.
    assert stanley_steering(0.0, 0.0, 10.0, damped, yaw_rate_radps=0.3) == pytest.approx(-0.03)
    # On a left curve of 20 m radius at 10 m/s the path asks for 0.5 rad/s: no correction then.
    assert stanley_steering(0.0, 0.0, 10.0, damped, 0.5, path_curvature_1pm=1 / 20) == pytest.approx(0.0)


def test_heading_gain_caps_the_heading_loop_bandwidth_at_high_speed() -> None:
    # Below bandwidth * wheelbase (6 rad/s * 1.25 m = 7.5 m/s) Hoffmann's law is unchanged ...
    assert heading_gain(0.0, 1.25, 6.0) == 1.0
    assert heading_gain(7.5, 1.25, 6.0) == 1.0
    # ... above it the loop gain v / L * g stays at the bandwidth.
    for speed in (10.0, 15.0, 17.8):
        assert speed / 1.25 * heading_gain(speed, 1.25, 6.0) == pytest.approx(6.0)
    assert stanley_steering(0.2, 0.0, 15.0, GAINS, heading_gain=0.5) == pytest.approx(0.1)


def test_pd_is_proportional_on_the_first_step_without_a_derivative_kick() -> None:
    pd = PdHeadingController(PdGains(kp=1.5, kd_s=0.5))
    assert pd.steer(0.2, 0.02) == pytest.approx(0.3)


def test_pd_derivative_follows_the_error_rate() -> None:
    pd = PdHeadingController(PdGains(kp=1.0, kd_s=0.5, derivative_tau_s=0.0))
    pd.steer(0.10, 0.02)
    assert pd.steer(0.12, 0.02) == pytest.approx(0.12 + 0.5 * 1.0)  # error rising at 1 rad/s
    assert pd.steer(0.12, 0.02) == pytest.approx(0.12)


def test_pd_derivative_is_low_pass_filtered() -> None:
    pd = PdHeadingController(PdGains(kp=1.0, kd_s=1.0, derivative_tau_s=0.08))
    pd.steer(0.0, 0.02)
    first = pd.steer(0.02, 0.02) - 0.02  # raw rate 1 rad/s, filtered by 0.02 / (0.08 + 0.02)
    assert first == pytest.approx(0.2)


def test_pd_difference_wraps_through_pi() -> None:
    pd = PdHeadingController(PdGains(kp=1.0, kd_s=0.1, derivative_tau_s=0.0))
    pd.steer(math.pi - 0.01, 0.02)
    out = pd.steer(-math.pi + 0.01, 0.02)  # 0.02 rad further, not -2 pi
    assert out == pytest.approx(-math.pi + 0.01 + 0.1)


def test_pd_reset_forgets_the_history() -> None:
    pd = PdHeadingController(PdGains(kp=1.0, kd_s=1.0, derivative_tau_s=0.0))
    pd.steer(0.5, 0.02)
    pd.reset()
    assert pd.steer(-0.5, 0.02) == pytest.approx(-0.5)


def test_pd_look_ahead_grows_with_speed_from_a_minimum() -> None:
    gains = PdGains(lookahead_min_m=3.0, lookahead_time_s=0.8)
    assert gains.lookahead_m(0.0) == 3.0
    assert gains.lookahead_m(10.0) == pytest.approx(8.0)


@pytest.mark.parametrize(
    "make",
    [
        lambda: StanleyGains(gain=0.0),
        lambda: StanleyGains(softening_mps=-1.0),
        lambda: StanleyGains(yaw_damping_s=-0.1),
        lambda: PdGains(kp=0.0),
        lambda: PdGains(kd_s=-1.0),
        lambda: PdGains(lookahead_min_m=0.0),
    ],
)
def test_bad_gains_are_refused(make) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError):
        make()
