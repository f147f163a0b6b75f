"""The brain's drive modes from live and silent inputs, and their speed caps."""

from __future__ import annotations

import pytest

from brain.health import (
    LIDARS,
    NAVIGATION,
    STEREO,
    SWEEP_LIDAR,
    DriveMode,
    HealthParams,
    SensorHealth,
    stopping_speed_mps,
)
from protocol.messages import NavQuality, VehicleState

S = 1_000_000_000


def nav_state(quality: NavQuality = NavQuality.DGPS, sigma_m: float = 0.05) -> VehicleState:
    cov = [0.0] * 25
    cov[0] = cov[6] = sigma_m**2 / 2
    return VehicleState(0.0, 0.0, 0.0, 0.0, 10.0, 10.0, 0.0, 0.0, tuple(cov), int(quality))


def live(health: SensorHealth, t_ns: int, *sources: str, nav: VehicleState | None = None) -> None:
    for source in sources:
        health.heard(source, t_ns)
    health.heard_navigation(nav or nav_state(), t_ns)


def test_everything_live_is_normal_at_the_course_speed() -> None:
    health = SensorHealth()
    live(health, 10 * S, *LIDARS, STEREO)
    result = health.assess(10 * S + S // 10, course_speed_mps=12.0)
    assert (result.mode, result.speed_cap_mps, result.silent) == (DriveMode.NORMAL, 12.0, ())


def test_the_2005_failure_every_lidar_silent_is_noticed_within_0_3_s() -> None:
    health = SensorHealth()
    live(health, 10 * S, *LIDARS, STEREO)
    # The lidars stop at 10 s; stereo and navigation carry on.
    noticed_at = None
    for step in range(1, 40):
        now = 10 * S + step * S // 100
        live(health, now, STEREO)
        if health.assess(now).mode is DriveMode.STEREO_ONLY:
            noticed_at = now
            break
    assert noticed_at is not None and noticed_at - 10 * S <= 0.3 * S
    result = health.assess(noticed_at, course_speed_mps=15.0)
    params = HealthParams()
    # The cap lets the vehicle stop inside stereo's 35 m, reaction time included.
    v = result.speed_cap_mps
    assert v * params.reaction_s + v**2 / (2 * params.braking_mps2) == pytest.approx(35.0 - params.margin_m)
    assert set(LIDARS) <= set(result.silent)


@pytest.mark.parametrize(
    ("live_sources", "mode", "stops"),
    [
        ((), DriveMode.BLIND, True),
        (("lidar_v_left", "lidar_v_right"), DriveMode.BLIND, True),  # vertical lidars see no obstacles
        (("lidar_h_left", "lidar_h_right", "lidar_v_left", "lidar_v_right"), DriveMode.LIDAR_ONLY, False),
        (("lidar_h_right", STEREO), DriveMode.LIDAR_DEGRADED, False),
    ],
)
def test_modes(live_sources: tuple[str, ...], mode: DriveMode, stops: bool) -> None:
    health = SensorHealth()
    live(health, 5 * S, *live_sources)
    result = health.assess(5 * S, course_speed_mps=10.0)
    assert result.mode is mode
    assert (result.speed_cap_mps == 0.0) is stops


def test_without_the_sweeping_lidar_the_vehicle_can_stop_within_the_vertical_lidars_reach() -> None:
    params = HealthParams()
    health = SensorHealth()
    live(health, 5 * S, *(name for name in LIDARS if name != SWEEP_LIDAR), STEREO)
    result = health.assess(5 * S, course_speed_mps=13.4)
    assert result.mode is DriveMode.LIDAR_DEGRADED and SWEEP_LIDAR in result.silent
    v = result.speed_cap_mps
    assert v * params.reaction_s + v**2 / (2 * params.braking_mps2) == pytest.approx(24.0 - params.margin_m)
    assert "ditches seen only 24 m ahead" in result.reason
    # Another lidar silent, the sweep live: reported, not slowed.
    health = SensorHealth()
    live(health, 5 * S, *(name for name in LIDARS if name != "lidar_v_left"), STEREO)
    result = health.assess(5 * S, course_speed_mps=13.4)
    assert (result.mode, result.speed_cap_mps) == (DriveMode.LIDAR_DEGRADED, 13.4)


def test_stale_or_invalid_navigation_stops() -> None:
    health = SensorHealth()
    assert health.assess(0).mode is DriveMode.NAV_LOST  # nothing heard yet
    live(health, 5 * S, *LIDARS, STEREO)
    assert health.assess(5 * S + S // 2).speed_cap_mps == 0.0  # everything 0.5 s old
    for source in (*LIDARS, STEREO):
        health.heard(source, 6 * S)
    result = health.assess(6 * S)
    assert result.mode is DriveMode.NAV_LOST and NAVIGATION in result.silent
    live(health, 7 * S, *LIDARS, STEREO, nav=nav_state(NavQuality.INVALID))
    assert health.assess(7 * S).mode is DriveMode.NAV_LOST


def test_dead_reckoning_slows_as_the_position_uncertainty_grows() -> None:
    caps = []
    for sigma in (0.1, 1.0, 2.0, 5.0):
        health = SensorHealth()
        live(health, S, *LIDARS, STEREO, nav=nav_state(NavQuality.DEAD_RECKONING, sigma))
        caps.append(health.assess(S, course_speed_mps=15.0).speed_cap_mps)
    assert caps == sorted(caps, reverse=True)
    assert caps[0] < 8.0 and caps[-1] == pytest.approx(1.0)


def test_late_messages_never_roll_the_clock_back() -> None:
    health = SensorHealth(expected=(STEREO,))
    health.heard(STEREO, 10 * S)
    health.heard(STEREO, 9 * S)
    assert health.last_ns[STEREO] == 10 * S
    assert stopping_speed_mps(HealthParams().margin_m, HealthParams()) == 0.0


def test_the_oldest_live_input_is_the_stalest_picture_a_plan_uses() -> None:
    health = SensorHealth()
    ms = S // 1000
    health.heard("lidar_h_left", 10_000 * ms)
    health.heard("lidar_h_right", 10_050 * ms)
    health.heard(STEREO, 9_700 * ms)
    sources = ("lidar_h_left", "lidar_h_right", STEREO)
    assert health.oldest_live_ns(sources, 10_100 * ms) == 9_700 * ms
    # Past their age limits (stereo 0.5 s, lidars 0.2 s) silent inputs are not counted.
    assert health.oldest_live_ns(sources, 10_210 * ms) == 10_050 * ms
    assert health.oldest_live_ns(sources, 60 * S) is None
