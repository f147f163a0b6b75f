"""Pose history: interpolation between states, bounded extrapolation, refusals counted."""

from __future__ import annotations

import math

import pytest

from brain.fusion import PoseHistory
from brain.fusion.poses import heading_std_rad
from protocol.messages import NavQuality
from tests.brain.fusion.helpers import MS, state


def test_position_is_linear_and_yaw_takes_the_short_way_round() -> None:
    history = PoseHistory()
    history.add(0, state(10.0, 20.0, math.radians(170)))
    history.add(100 * MS, state(12.0, 16.0, math.radians(-170)))
    pose = history.at(25 * MS)
    assert pose is not None
    assert (pose.east_m, pose.north_m) == pytest.approx((10.5, 19.0))
    # 170 deg -> -170 deg is 20 deg through 180, not 340 deg back through 0.
    assert math.degrees(pose.yaw_rad) % 360 == pytest.approx(175.0)
    middle = history.at(50 * MS)
    assert middle is not None and abs(middle.yaw_rad) == pytest.approx(math.pi)
    exact = history.at(100 * MS)
    assert exact is not None and exact.east_m == 12.0 and history.stats.interpolated == 3


def test_extrapolates_with_velocity_within_the_limit_and_refuses_beyond() -> None:
    history = PoseHistory(max_extrapolation_ns=100 * MS)
    history.add(1_000 * MS, state(0.0, 0.0, math.pi / 2, speed=4.0, yaw_rate=0.5))
    ahead = history.at(1_050 * MS)
    assert ahead is not None
    assert (ahead.east_m, ahead.north_m, ahead.yaw_rad) == pytest.approx((0.0, 0.2, math.pi / 2 + 0.025))
    behind = history.at(950 * MS)
    assert behind is not None and behind.north_m == pytest.approx(-0.2)
    assert history.at(1_101 * MS) is None
    assert history.at(899 * MS) is None
    assert history.stats.extrapolated == 2
    assert (history.stats.too_new, history.stats.too_old) == (1, 1)


def test_empty_history_and_unusable_states_are_counted() -> None:
    history = PoseHistory()
    assert history.at(0) is None and history.stats.empty == 1
    invalid = state(1.0, 1.0, 0.0)._replace(quality=NavQuality.INVALID)
    not_finite = state(math.nan, 1.0, 0.0)
    assert not history.add(0, invalid) and not history.add(0, not_finite)
    assert history.stats.invalid == 2 and len(history) == 0


def test_late_states_are_inserted_in_order_and_old_ones_dropped() -> None:
    history = PoseHistory(span_ns=1_000 * MS)
    history.add(0, state(0.0, 0.0, 0.0))
    history.add(200 * MS, state(2.0, 0.0, 0.0))
    history.add(100 * MS, state(5.0, 0.0, 0.0))  # arrives late, belongs in the middle
    pose = history.at(150 * MS)
    assert pose is not None and pose.east_m == pytest.approx(3.5)
    history.add(100 * MS, state(1.0, 0.0, 0.0))  # same time: replaces
    pose = history.at(150 * MS)
    assert pose is not None and pose.east_m == pytest.approx(1.5)
    history.add(1_150 * MS, state(11.5, 0.0, 0.0))
    assert history.oldest_ns == 200 * MS and history.newest_ns == 1_150 * MS
    assert history.at(50 * MS) is None  # dropped: now before the history by more than the limit
    assert not history.add(100 * MS, state(1.0, 0.0, 0.0))  # too late to keep
    assert history.stats.stale == 1 and history.oldest_ns == 200 * MS


def test_rejects_a_bad_configuration() -> None:
    with pytest.raises(ValueError):
        PoseHistory(span_ns=0)


def test_the_heading_uncertainty_is_read_from_the_covariance_or_taken_as_exact() -> None:
    assert heading_std_rad(state(0.0, 0.0, 0.0, yaw_std=0.03)) == pytest.approx(0.03)
    # Left out or unreadable: exact, so the map treats the state as it did before it was read.
    for covariance in ((), (0.0,) * 24, (math.nan,) * 25):
        assert heading_std_rad(state(0.0, 0.0, 0.0)._replace(covariance=covariance)) == 0.0
