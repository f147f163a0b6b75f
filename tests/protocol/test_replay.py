"""Replay protection: the per-stream sliding window, loss accounting and freshness."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.errors import ProtocolError, Reason
from protocol.replay import WINDOW, ReplayGuard, ReplayLimits

NOW = 1_700_000_000_000_000_000
BASE = 1_700_000_000_000_000  # a publisher's first seq: wall-clock microseconds at start
SOURCE = 3
CHANNEL = "IMU"


def check(
    guard: ReplayGuard,
    seq: int,
    *,
    t_pub_ns: int = NOW,
    now_ns: int | None = NOW,
    source_id: int = SOURCE,
    channel: str = CHANNEL,
) -> int:
    return guard.check(source_id, channel, seq, t_pub_ns, now_ns)


def reason_of(guard: ReplayGuard, seq: int, **kwargs: int | str | None) -> Reason:
    with pytest.raises(ProtocolError) as caught:
        check(guard, seq, **kwargs)  # type: ignore[arg-type]
    return caught.value.reason


def test_in_order_messages_are_accepted_with_no_loss() -> None:
    """Consecutive sequence numbers are all accepted and report no loss."""
    guard = ReplayGuard()
    assert [check(guard, BASE + i) for i in range(1000)] == [0] * 1000


def test_an_exact_duplicate_is_a_replay() -> None:
    """The same (source, channel, seq) a second time is REPLAY, right away or later in the window."""
    guard = ReplayGuard()
    check(guard, BASE)
    assert reason_of(guard, BASE) is Reason.REPLAY
    for i in range(1, 10):
        check(guard, BASE + i)
    for i in range(10):
        assert reason_of(guard, BASE + i) is Reason.REPLAY


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.permutations(range(WINDOW)), st.lists(st.integers(0, WINDOW - 1), max_size=40))
def test_reordering_within_the_window_accepts_each_message_once(order: list[int], repeats: list[int]) -> None:
    """Any arrival order of 64 consecutive messages accepts each exactly once, every repeat is
    REPLAY, and once all have arrived the reported losses net to zero."""
    guard = ReplayGuard()
    losses = [check(guard, BASE + offset) for offset in order]
    assert sum(losses) == 0
    for offset in repeats:
        assert reason_of(guard, BASE + offset) is Reason.REPLAY


def test_a_message_older_than_the_window_is_a_replay() -> None:
    """A never-seen seq 64 or more behind the highest accepted is REPLAY; 63 behind is accepted."""
    guard = ReplayGuard()
    check(guard, BASE)
    check(guard, BASE + 100)
    assert reason_of(guard, BASE + 100 - WINDOW) is Reason.REPLAY
    assert reason_of(guard, BASE + 1) is Reason.REPLAY
    assert check(guard, BASE + 100 - WINDOW + 1) == -1


def test_a_gap_is_reported_as_loss_and_a_late_fill_returns_minus_one() -> None:
    """Jumping ahead reports the skipped count; a skipped one arriving late returns -1, once."""
    guard = ReplayGuard()
    assert check(guard, BASE) == 0
    assert check(guard, BASE + 5) == 4
    assert check(guard, BASE + 3) == -1
    assert reason_of(guard, BASE + 3) is Reason.REPLAY
    assert check(guard, BASE + 6) == 0
    assert check(guard, BASE + 6 + 200) == 199  # a gap wider than the window
    assert check(guard, BASE + 6 + 200 - 1) == -1


def test_messages_before_the_first_seen_are_not_negative_loss() -> None:
    """A late message older than the first one a receiver saw was never counted as lost, so it
    is accepted with loss 0 (not -1): loss statistics never go negative."""
    guard = ReplayGuard()
    assert check(guard, BASE + 10) == 0
    assert [check(guard, BASE + i) for i in range(10)] == [0] * 10
    assert check(guard, BASE + 12) == 1
    assert check(guard, BASE + 11) == -1


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.lists(st.integers(0, 300), min_size=1, max_size=120))
def test_net_loss_is_the_true_loss(arrivals: list[int]) -> None:
    """For any arrival pattern, the running net loss equals the number of seqs between the first
    one seen and the highest accepted that are still missing (so it is never negative)."""
    guard = ReplayGuard()
    accepted: set[int] = set()
    first = arrivals[0]
    net = 0
    for offset in arrivals:
        try:
            net += check(guard, BASE + offset)
        except ProtocolError as error:
            assert error.reason is Reason.REPLAY
            continue
        accepted.add(offset)
        missing = sum(1 for s in range(first, max(accepted)) if s not in accepted)
        assert net == missing >= 0


@pytest.mark.parametrize("offset_ns,expected", [(-2_000_000_001, Reason.STALE), (2_000_000_001, Reason.FUTURE)])
def test_stale_and_future_messages_are_rejected(offset_ns: int, expected: Reason) -> None:
    """t_pub more than max_age before now is STALE, more than max_future after now is FUTURE."""
    guard = ReplayGuard(ReplayLimits(max_age_ns=2_000_000_000, max_future_ns=2_000_000_000))
    assert reason_of(guard, BASE, t_pub_ns=NOW + offset_ns) is expected


def test_freshness_bounds_are_inclusive() -> None:
    """Exactly max_age old or max_future ahead is still fresh."""
    guard = ReplayGuard(ReplayLimits(max_age_ns=1000, max_future_ns=500))
    assert check(guard, BASE, t_pub_ns=NOW - 1000) == 0
    assert check(guard, BASE + 1, t_pub_ns=NOW + 500) == 0
    assert reason_of(guard, BASE + 2, t_pub_ns=NOW - 1001) is Reason.STALE
    assert reason_of(guard, BASE + 3, t_pub_ns=NOW + 501) is Reason.FUTURE


def test_a_rejected_stale_message_does_not_use_up_its_seq() -> None:
    """STALE/FUTURE rejections leave the window untouched: the same seq, fresh, is accepted."""
    guard = ReplayGuard()
    assert reason_of(guard, BASE, t_pub_ns=NOW - 10**12) is Reason.STALE
    assert reason_of(guard, BASE, t_pub_ns=NOW + 10**12) is Reason.FUTURE
    assert check(guard, BASE) == 0


def test_no_clock_skips_the_freshness_test() -> None:
    """now_ns=None accepts any t_pub (a receiver not yet synchronised), but still stops replays."""
    guard = ReplayGuard()
    assert check(guard, BASE, t_pub_ns=0, now_ns=None) == 0
    assert check(guard, BASE + 1, t_pub_ns=2**63 - 1, now_ns=None) == 0
    assert reason_of(guard, BASE, t_pub_ns=0, now_ns=None) is Reason.REPLAY


def test_a_restarted_publisher_with_a_higher_seq_base_is_accepted() -> None:
    """A publisher restarting with a later wall-clock seq base is accepted at once, and its
    previous life's messages are then replays."""
    guard = ReplayGuard()
    for i in range(500):
        check(guard, BASE + i)
    restarted = BASE + 7_000_000  # 7 s later, in microseconds
    assert check(guard, restarted) == 0  # a new life, not seven million lost messages
    for i in range(1, 100):
        check(guard, restarted + i)
    for i in (0, 250, 499):
        assert reason_of(guard, BASE + i) is Reason.REPLAY


def test_streams_are_independent_per_source_and_channel() -> None:
    """The same seq on another channel or from another source is a different message."""
    guard = ReplayGuard()
    check(guard, BASE)
    assert check(guard, BASE, channel="GPS") == 0
    assert check(guard, BASE, source_id=SOURCE + 1) == 0
    assert reason_of(guard, BASE, channel="GPS") is Reason.REPLAY


def test_the_number_of_streams_is_bounded() -> None:
    """At most max_streams streams are tracked, however many (source, channel) pairs appear."""
    limits = ReplayLimits(max_streams=16)
    guard = ReplayGuard(limits)
    rng = random.Random(1)
    for _ in range(2000):
        check(guard, rng.randrange(2**40), source_id=rng.randrange(1, 0x10000), channel=f"C{rng.randrange(50)}")
        assert len(guard) <= limits.max_streams


def test_forget_drops_a_stream() -> None:
    """After forget(), a stream starts afresh (the next seq seen is accepted)."""
    guard = ReplayGuard()
    check(guard, BASE)
    guard.forget(SOURCE, CHANNEL)
    assert check(guard, BASE) == 0
    guard.forget(SOURCE, "never-seen")


def test_replay_errors_name_the_source() -> None:
    """REPLAY/STALE/FUTURE errors carry the source id, for per-source statistics."""
    guard = ReplayGuard()
    check(guard, BASE, source_id=99)
    for kwargs in ({}, {"t_pub_ns": 0}, {"t_pub_ns": 2**62}):
        with pytest.raises(ProtocolError) as caught:
            guard.check(99, CHANNEL, BASE, kwargs.get("t_pub_ns", NOW), NOW)
        assert caught.value.source_id == 99
