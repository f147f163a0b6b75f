"""PI speed control with anti-windup, and the throttle/brake split with its deadband."""

from __future__ import annotations

import pytest

from modules.control.speed import PiSpeedController, SpeedGains, split_effort

GAINS = SpeedGains(kp=0.5, ki=0.2, integral_min=-0.5, integral_max=1.0, deadband=0.03)


def test_proportional_and_integral_parts() -> None:
    pi = PiSpeedController(GAINS)
    assert pi.update(10.0, 9.0, 0.02) == pytest.approx(0.5 + 0.2 * 1.0 * 0.02)
    for _ in range(49):
        pi.update(10.0, 9.0, 0.02)
    assert pi.integral == pytest.approx(0.2)  # 1 m/s for 1 s


def test_the_integrator_holds_while_the_output_is_saturated_by_the_error() -> None:
    pi = PiSpeedController(GAINS)
    pi.integral = 0.4
    for _ in range(5000):  # 100 s asking for a speed the vehicle cannot reach
        assert pi.update(18.0, 15.0, 0.02) == 1.0
    assert pi.integral == pytest.approx(0.4)
    # Once the target drops below the speed, the effort turns to braking at once.
    assert pi.update(14.0, 15.0, 0.02) < 0.0


def test_the_integrator_integrates_again_as_soon_as_the_error_pulls_out_of_saturation() -> None:
    pi = PiSpeedController(GAINS)
    pi.integral = 0.8
    assert pi.update(12.0, 10.0, 0.02) == 1.0  # 0.5 * 2 + 0.8: saturated, integrator held
    assert pi.integral == pytest.approx(0.8)
    pi.update(10.0, 10.5, 0.02)  # overshoot: the error now unwinds the integrator
    assert pi.integral == pytest.approx(0.8 - 0.2 * 0.5 * 0.02)


def test_the_integrator_is_clamped() -> None:
    pi = PiSpeedController(SpeedGains(kp=0.0, ki=1.0, integral_min=-0.2, integral_max=0.6))
    for _ in range(1000):
        pi.update(10.0, 9.9, 0.02)
    assert pi.integral == pytest.approx(0.6)
    for _ in range(1000):
        pi.update(9.8, 9.9, 0.02)
    assert pi.integral == pytest.approx(-0.2)


def test_reset_empties_the_integrator() -> None:
    pi = PiSpeedController(GAINS)
    for _ in range(100):
        pi.update(10.0, 9.0, 0.02)
    pi.reset()
    assert pi.integral == 0.0
    assert pi.update(10.0, 10.0, 0.02) == 0.0


def test_split_drives_brakes_or_coasts_never_both() -> None:
    assert split_effort(1.0, 0.03) == (1.0, 0.0)
    assert split_effort(-1.0, 0.03) == (0.0, 1.0)
    assert split_effort(0.02, 0.03) == (0.0, 0.0)
    assert split_effort(-0.02, 0.03) == (0.0, 0.0)
    for effort in [i / 100 for i in range(-100, 101)]:
        throttle, brake = split_effort(effort, 0.03)
        assert 0.0 <= throttle <= 1.0 and 0.0 <= brake <= 1.0
        assert throttle == 0.0 or brake == 0.0


def test_split_is_continuous_at_the_deadband_edge() -> None:
    throttle, _ = split_effort(0.0301, 0.03)
    assert throttle == pytest.approx(0.0, abs=1e-3)
    _, brake = split_effort(-0.0301, 0.03)
    assert brake == pytest.approx(0.0, abs=1e-3)
    assert split_effort(0.515, 0.03)[0] == pytest.approx(0.5)


def test_split_clamps_efforts_out_of_range() -> None:
    assert split_effort(3.0, 0.0) == (1.0, 0.0)
    assert split_effort(-3.0, 0.0) == (0.0, 1.0)


@pytest.mark.parametrize(
    "kwargs",
    [{"kp": -0.1}, {"kp": 0.0, "ki": 0.0}, {"integral_min": 0.2}, {"integral_max": 1.5}, {"deadband": 1.0}],
)
def test_bad_speed_gains_are_refused(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        SpeedGains(**kwargs)


def test_bad_time_steps_and_deadbands_are_refused() -> None:
    with pytest.raises(ValueError):
        PiSpeedController(GAINS).update(1.0, 0.0, 0.0)
    with pytest.raises(ValueError):
        split_effort(0.5, -0.1)
