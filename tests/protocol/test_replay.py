"""Replay protection: the per-stream sliding window, loss accounting and freshness."""

from __future__ import annotations

import random
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import channels
from protocol.auth import Keyring
from protocol.errors import ProtocolError, Reason
from protocol.messages import WheelSpeed
from protocol.replay import WINDOW, ReplayGuard, ReplayLimits
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock

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


MS = 1_000_000
STEP_BACK_US = 10_000_000  # the sender's wall clock stepped back 10 s


def old_life(guard: ReplayGuard, messages: int = 300) -> list[tuple[int, int]]:
    """A publisher at 100 Hz, synchronised: (seq, t_pub_ns) of each message, all accepted."""
    sent = [(BASE + i, NOW + 10 * MS * i) for i in range(messages)]
    for seq, t_pub in sent:
        assert check(guard, seq, t_pub_ns=t_pub, now_ns=t_pub + MS) == 0
    return sent


def test_a_publisher_restarted_with_its_clock_stepped_back_is_accepted_at_once() -> None:
    """The sender restarts 0.3 s after its last message with its wall clock (so its seq base)
    10 s back: its first fresh message starts a new life, with no loss counted, and it goes on."""
    guard = ReplayGuard()
    sent = old_life(guard)
    restart_ns = sent[-1][1] + 300 * MS
    restarted = sent[-1][0] + 300_000 - STEP_BACK_US  # its wall clock in us when it opened the bus
    assert check(guard, restarted, t_pub_ns=restart_ns, now_ns=restart_ns) == 0
    for i in range(1, 100):
        t_pub = restart_ns + 10 * MS * i
        assert check(guard, restarted + i, t_pub_ns=t_pub, now_ns=t_pub) == 0
    assert check(guard, restarted + 102, t_pub_ns=restart_ns + 1020 * MS, now_ns=restart_ns + 1020 * MS) == 2


def test_the_previous_life_cannot_be_replayed_into_the_new_one() -> None:
    """Once a source restarted below its old numbers, its old life's messages, whose seqs are now
    far ahead, are replays, however fresh; so are the new life's own, repeated."""
    guard = ReplayGuard()
    sent = old_life(guard)
    restart_ns = sent[-1][1] + 300 * MS
    restarted = sent[0][0] - STEP_BACK_US
    check(guard, restarted, t_pub_ns=restart_ns, now_ns=restart_ns)
    check(guard, restarted + 1, t_pub_ns=restart_ns + 10 * MS, now_ns=restart_ns + 10 * MS)
    now = restart_ns + 20 * MS
    for seq, t_pub in sent[-150:]:  # the old life's last 1.5 s: all still fresh
        assert reason_of(guard, seq, t_pub_ns=t_pub, now_ns=now) is Reason.REPLAY
    assert reason_of(guard, restarted, t_pub_ns=restart_ns, now_ns=now) is Reason.REPLAY
    assert reason_of(guard, restarted + 1, t_pub_ns=restart_ns + 10 * MS, now_ns=now) is Reason.REPLAY
    # Published before the new life's first message seen: old life or new, not accepted.
    assert reason_of(guard, restarted - 1, t_pub_ns=restart_ns - 1, now_ns=now) is Reason.REPLAY
    assert check(guard, restarted + 2, t_pub_ns=now, now_ns=now) == 0


def test_a_refused_message_not_published_after_the_stream_s_newest_is_still_a_replay() -> None:
    """Far behind, or already seen, and published no later than the newest message accepted on
    the stream: REPLAY, fresh or not. An unsynchronised receiver (now_ns=None) cannot judge
    freshness, so it never takes a refused message for a new life."""
    guard = ReplayGuard()
    sent = old_life(guard)
    newest = sent[-1][1]
    now = newest + MS
    far_behind = sent[0][0] - STEP_BACK_US
    for t_pub in (newest, newest - 1, newest - 500 * MS):
        assert reason_of(guard, far_behind, t_pub_ns=t_pub, now_ns=now) is Reason.REPLAY
        assert reason_of(guard, sent[-1][0], t_pub_ns=t_pub, now_ns=now) is Reason.REPLAY
    assert reason_of(guard, sent[-WINDOW][0], t_pub_ns=newest, now_ns=now) is Reason.REPLAY
    assert reason_of(guard, far_behind, t_pub_ns=newest + 1, now_ns=None) is Reason.REPLAY
    assert reason_of(guard, far_behind, t_pub_ns=now + 3_000 * MS, now_ns=now) is Reason.FUTURE
    assert check(guard, sent[-1][0] + 1, t_pub_ns=now, now_ns=now) == 0  # the stream is unharmed


@settings(max_examples=300, deadline=None, derandomize=True)
@given(
    st.lists(
        st.tuples(
            st.sampled_from(("send", "send", "send", "restart", "replay", "replay")),
            st.integers(-(10**8), 10**8),
            st.integers(1, 3_000 * MS),
        ),
        max_size=150,
    )
)
def test_genuine_traffic_across_restarts_is_accepted_and_every_replay_refused(
    events: list[tuple[str, int, int]],
) -> None:
    """A synchronised receiver; a sender publishing in order with rising shared time, restarting
    at any seq base (below or above its last), and an attacker replaying anything it sent: every
    genuine message is accepted, and no message is ever accepted twice."""
    guard = ReplayGuard()
    seq, t_pub = BASE, NOW
    sent: list[tuple[int, int]] = []
    for action, number, elapsed in events:
        if action == "replay" and sent:
            old_seq, old_t_pub = sent[number % len(sent)]
            assert reason_of(guard, old_seq, t_pub_ns=old_t_pub, now_ns=t_pub) in (Reason.REPLAY, Reason.STALE)
            continue
        seq = BASE + number if action == "restart" else seq + 1
        t_pub += elapsed
        check(guard, seq, t_pub_ns=t_pub, now_ns=t_pub)
        sent.append((seq, t_pub))


def receive_seqs(bus: Bus, seqs: list[int], wanted: int, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while wanted not in seqs and time.monotonic() < deadline:
        bus.poll(0.05)


def test_a_bus_publisher_restarted_with_its_clock_stepped_back_is_heard_within_a_second(
    bus_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Over loopback multicast: a publisher restarted while the host's wall clock, from which it
    takes its seq base, is 10 s back (its shared time is right), is heard again at once."""
    keys = Keyring.generate()
    receiver = Bus.open(bus_url, source_id=2, clock=MasterClock(), keyring=keys)
    seqs: list[int] = []
    receiver.subscribe(channels.WHEEL_SPEED, lambda msg, envelope: seqs.append(envelope.seq))
    first = Bus.open(bus_url, source_id=1, clock=MasterClock(), keyring=keys)
    old = [first.publish(channels.WHEEL_SPEED, WheelSpeed(1.0, 0.0)) for _ in range(5)]
    receive_seqs(receiver, seqs, old[-1], 2.0)
    assert seqs == old
    first.close()
    clock = MasterClock()  # synchronised shared time, read before the wall clock steps back
    stepped_back_ns = time.time_ns() - STEP_BACK_US * 1000
    with monkeypatch.context() as patch:
        patch.setattr(time, "time_ns", lambda: stepped_back_ns)
        restarted = Bus.open(bus_url, source_id=1, clock=clock, keyring=keys)
    start = time.monotonic()
    new = [restarted.publish(channels.WHEEL_SPEED, WheelSpeed(2.0, 0.0)) for _ in range(3)]
    receive_seqs(receiver, seqs, new[-1], 1.0)
    elapsed_s = time.monotonic() - start
    assert new[0] < old[0] - STEP_BACK_US // 2  # the restarted publisher numbers below its old life
    assert seqs == old + new and elapsed_s < 1.0
    assert not receiver.rejects
    for bus in (receiver, restarted):
        bus.close()


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
