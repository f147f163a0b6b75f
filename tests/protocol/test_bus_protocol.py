"""The wire protocol end to end: rascal.runtime.bus.Bus over an in-process MemTransport hub."""

from __future__ import annotations

import itertools
import re
from collections import Counter
from typing import Any

import pytest

from protocol import channels
from protocol import messages as m
from protocol.auth import Keyring
from protocol.codec import Codec, Envelope
from protocol.framing import DEFAULT_MAX_DATAGRAM_BYTES, is_fragment
from protocol.replay import ReplayLimits
from protocol.schema import info_for_class
from protocol.transport import MemTransport, open_transport
from rascal.runtime.bus import Bus, ChannelStats
from rascal.runtime.clock import ManualClock
from rascal.runtime.rtdb import Validity
from tests.protocol.wire_samples import BIG_SAMPLES, CHANNEL_OF, SAMPLES, T0_NS, WRONG_KEY, keyring

IMU = m.ImuSample(0.12, -0.03, 9.806, 0.001, -0.0004, 0.21)
PUBLISHER = 10
SUBSCRIBER = 20
_hub_names = itertools.count()


class Net:
    """One private hub, one manual clock shared by every node, and helpers to build nodes."""

    def __init__(self, test_name: str) -> None:
        safe = re.sub(r"[^A-Za-z0-9_-]", "-", test_name)  # test ids hold brackets, not URL-safe
        self.url = f"mem://bus-protocol-{safe}-{next(_hub_names)}"
        self.clock = ManualClock(T0_NS)

    def bus(self, source_id: int, keys: Keyring | None = None, *, unsigned: bool = False, **options: Any) -> Bus:
        return Bus(open_transport(self.url), source_id, None if unsigned else keys or keyring(), self.clock, **options)

    def tap(self, *names: str) -> MemTransport:
        """A raw member of the hub: captures datagrams and injects arbitrary ones."""
        transport = open_transport(self.url)
        assert isinstance(transport, MemTransport)
        for name in names:
            transport.listen(name)
        if not names:
            transport.listen_all()
        return transport


@pytest.fixture
def net(request: pytest.FixtureRequest) -> Net:
    return Net(request.node.name)


class Inbox:
    def __init__(self) -> None:
        self.items: list[tuple[Any, Envelope]] = []

    def __call__(self, msg: Any, envelope: Envelope) -> None:
        self.items.append((msg, envelope))

    @property
    def messages(self) -> list[Any]:
        return [msg for msg, _ in self.items]


def drain(transport: MemTransport) -> list[bytes]:
    captured: list[bytes] = []
    transport.receive(captured.append, 0.0, 1_000_000)
    return captured


# -- delivery ----------------------------------------------------------------------------------


def test_a_published_message_arrives_typed_with_its_envelope(net: Net) -> None:
    """publish -> poll delivers an equal ImuSample with the header's source, seq and times."""
    pub, sub = net.bus(PUBLISHER), net.bus(SUBSCRIBER)
    inbox = Inbox()
    sub.subscribe(channels.IMU, inbox)
    seq = pub.publish(channels.IMU, IMU, t_meas_ns=T0_NS - 3_000_000)
    assert sub.poll() == 1
    [(msg, envelope)] = inbox.items
    assert msg == IMU and type(msg) is m.ImuSample
    assert envelope.channel == channels.IMU
    assert (envelope.source_id, envelope.seq, envelope.type_id) == (PUBLISHER, seq, info_for_class(m.ImuSample).type_id)
    assert (envelope.t_meas_ns, envelope.t_pub_ns, envelope.recv_ns) == (T0_NS - 3_000_000, T0_NS, T0_NS)
    assert sub.rejects == Counter()
    assert sub.stats[channels.IMU].messages == 1


@pytest.mark.parametrize("sample", SAMPLES + BIG_SAMPLES, ids=lambda s: type(s).__name__)
def test_every_message_type_round_trips_over_the_bus(net: Net, sample: Any) -> None:
    """Every sample, on its declared channel, arrives once, equal and of its declared type."""
    channel = CHANNEL_OF[type(sample)]
    pub, sub = net.bus(PUBLISHER), net.bus(SUBSCRIBER)
    inbox = Inbox()
    sub.subscribe(channel, inbox)
    pub.publish(channel, sample)
    sub.poll()
    assert inbox.messages == [sample]
    assert type(inbox.messages[0]) is channels.CHANNEL_TYPES[channel]


def test_a_fragmented_message_crosses_the_bus(net: Net) -> None:
    """A message over one datagram travels as several fragments of at most max_datagram_bytes
    and is delivered once, equal."""
    big = BIG_SAMPLES[1]
    pub, sub = net.bus(PUBLISHER), net.bus(SUBSCRIBER)
    tap = net.tap(channels.PATH)
    inbox = Inbox()
    sub.subscribe(channels.PATH, inbox)
    pub.publish(channels.PATH, big)
    datagrams = drain(tap)
    assert len(datagrams) > 20
    assert all(is_fragment(d) and len(d) <= DEFAULT_MAX_DATAGRAM_BYTES for d in datagrams)
    sub.poll()
    assert inbox.messages == [big]
    assert sub.rejects == Counter()
    assert sub.reassembler.pending() == 0


# -- rejection ---------------------------------------------------------------------------------


def test_rejects_are_counted_per_source_and_reason_and_never_delivered(net: Net) -> None:
    """Bad messages are counted under (claimed source, reason) and never reach the handler."""
    sub = net.bus(SUBSCRIBER)
    inbox = Inbox()
    sub.subscribe(channels.IMU, inbox)
    unsigned = net.bus(31, unsigned=True)
    forger = net.bus(32, Keyring({1: WRONG_KEY}, 1))
    stranger = net.bus(33, keyring(9))
    for _ in range(3):
        unsigned.publish(channels.IMU, IMU)
        forger.publish(channels.IMU, IMU)
    stranger.publish(channels.IMU, IMU)
    sub.poll()
    assert inbox.items == []
    assert sub.rejects == Counter({(31, "unsigned"): 3, (32, "bad_mac"): 3, (33, "unknown_key"): 1})
    assert sub.rejected_total() == 7
    assert channels.IMU not in sub.stats


def test_a_datagram_too_short_for_its_flags_is_truncated(net: Net) -> None:
    sub = net.bus(SUBSCRIBER)
    sub.subscribe(channels.IMU, Inbox())
    raw = net.tap()
    for stub in (b"", b"R", b"RB\x01"):
        raw.send(channels.IMU, stub)
    sub.poll()
    assert sub.rejects == Counter({(None, "truncated"): 3})


def test_a_bug_in_our_own_handler_is_not_counted_as_a_remote_fault(net: Net) -> None:
    """An IndexError raised by a raw handler is the handler's, and surfaces; it is not a
    truncated datagram from the sender."""
    sub = net.bus(SUBSCRIBER)

    def faulty(*_: object) -> None:
        raise IndexError("ours")

    sub.subscribe_raw(faulty)
    net.bus(PUBLISHER).publish(channels.IMU, IMU)
    with pytest.raises(IndexError, match="ours"):
        sub.poll()
    assert sub.rejected_total() == 0


def test_a_spoofer_with_the_wrong_key_never_gets_a_message_through(net: Net) -> None:
    """Whatever a spoofer sends (any type, any declared channel, fragmented or not, even under the
    victim's source id and key id), no handler or latest-value entry ever sees it: every datagram,
    each fragment included, is rejected on its own tag."""
    sub = net.bus(SUBSCRIBER)
    tap = net.tap()
    inbox = Inbox()
    latest = {}
    for name in channels.CHANNEL_TYPES:
        sub.subscribe(name, inbox)
        latest[name] = sub.latest(name, 10**9)
    spoofers = [net.bus(PUBLISHER, Keyring({1: WRONG_KEY}, 1)), net.bus(PUBLISHER, Keyring({2: WRONG_KEY}, 2))]
    sent = 0
    for _round in range(5):
        for spoofer in spoofers:
            for sample in SAMPLES + BIG_SAMPLES:
                spoofer.publish(CHANNEL_OF[type(sample)], sample)
        sent += len(drain(tap))
        net.clock.advance(1_000_000)
        sub.poll()
    assert inbox.items == []
    assert all(entry.read(net.clock.now_ns()).validity is Validity.NEVER for entry in latest.values())
    assert sub.rejects == Counter({(PUBLISHER, "bad_mac"): sent // 2, (PUBLISHER, "unknown_key"): sent // 2})
    assert sub.reassembler.pending() == 0


def test_a_replayed_genuine_datagram_is_rejected(net: Net) -> None:
    """A captured genuine message sent again (whole or as fragments) is REPLAY, not redelivered."""
    pub, sub = net.bus(PUBLISHER), net.bus(SUBSCRIBER)
    tap = net.tap(channels.IMU, channels.PATH)
    inbox = Inbox()
    sub.subscribe(channels.IMU, inbox)
    sub.subscribe(channels.PATH, inbox)
    pub.publish(channels.IMU, IMU)
    pub.publish(channels.PATH, BIG_SAMPLES[1])
    sub.poll()
    assert len(inbox.items) == 2
    captured = drain(tap)
    for datagram in captured:
        tap.send(channels.IMU, datagram)
    tap.send(channels.IMU, captured[0])
    sub.poll()
    assert len(inbox.items) == 2
    assert sub.rejects == Counter({(PUBLISHER, "replay"): 3})


def test_a_replay_to_a_fresh_receiver_after_the_freshness_window_is_stale(net: Net) -> None:
    """A receiver with no window state yet still refuses a recording older than max_age (STALE)."""
    pub = net.bus(PUBLISHER)
    tap = net.tap(channels.IMU)
    pub.publish(channels.IMU, IMU)
    [recorded] = drain(tap)
    net.clock.advance(ReplayLimits().max_age_ns + 1)
    late = net.bus(SUBSCRIBER)
    inbox = Inbox()
    late.subscribe(channels.IMU, inbox)
    tap.send(channels.IMU, recorded)
    late.poll()
    assert inbox.items == []
    assert late.rejects == Counter({(PUBLISHER, "stale"): 1})


def test_the_wrong_type_on_a_declared_channel_is_wrong_type(net: Net) -> None:
    """A genuinely signed GpsFix on the IMU channel is WRONG_TYPE and not delivered."""
    sub = net.bus(SUBSCRIBER)
    inbox = Inbox()
    sub.subscribe(channels.IMU, inbox)
    tap = net.tap()
    gps = m.GpsFix(35.05, -117.57, 712.4, 0.35, 0.41, 0.9, 3, 11)
    tap.send(channels.IMU, Codec(keyring()).encode(b"IMU", gps, PUBLISHER, 5, T0_NS, T0_NS))
    sub.poll()
    assert inbox.items == []
    assert sub.rejects == Counter({(PUBLISHER, "wrong_type"): 1})


def test_publishing_the_wrong_type_on_a_declared_channel_is_a_local_error(net: Net) -> None:
    """Bus.publish refuses (TypeError) a type other than the channel's declared one."""
    pub = net.bus(PUBLISHER)
    with pytest.raises(TypeError):
        pub.publish(channels.IMU, m.WheelSpeed(1.0, 2.0))


def test_losses_are_counted_from_sequence_gaps(net: Net) -> None:
    """Messages that never arrive show up in the channel's loss count; late ones are taken back."""
    sub = net.bus(SUBSCRIBER)
    sub.subscribe(channels.IMU, Inbox())
    tap = net.tap()
    codec = Codec(keyring())
    for seq in (100, 101, 105, 103):
        tap.send(channels.IMU, codec.encode(b"IMU", IMU, PUBLISHER, seq, T0_NS, T0_NS))
    sub.poll()
    stats = sub.stats[channels.IMU]
    assert (stats.messages, stats.lost) == (4, 2)


# -- latest-value store ------------------------------------------------------------------------


def test_latest_is_never_then_fresh_then_stale_by_measurement_age(net: Net) -> None:
    """A Latest entry reads NEVER before any message, FRESH while now - t_meas <= max_age, and
    STALE (without its value) after that."""
    pub, sub = net.bus(PUBLISHER), net.bus(SUBSCRIBER)
    max_age = 100_000_000
    entry = sub.latest(channels.IMU, max_age)
    assert entry.read(net.clock.now_ns()).validity is Validity.NEVER
    pub.publish(channels.IMU, IMU, t_meas_ns=T0_NS - 40_000_000)
    sub.poll()
    reading = entry.read(net.clock.now_ns())
    assert (reading.validity, reading.value, reading.age_ns) == (Validity.FRESH, IMU, 40_000_000)
    net.clock.advance(60_000_000)
    assert entry.read(net.clock.now_ns()).validity is Validity.FRESH
    net.clock.advance(1)
    reading = entry.read(net.clock.now_ns())
    assert (reading.validity, reading.value, reading.age_ns) == (Validity.STALE, None, max_age + 1)


def test_latest_is_stale_at_once_for_an_old_measurement(net: Net) -> None:
    """A message published now about a measurement older than max_age is STALE on arrival."""
    pub, sub = net.bus(PUBLISHER), net.bus(SUBSCRIBER)
    entry = sub.latest(channels.IMU, 100_000_000)
    pub.publish(channels.IMU, IMU, t_meas_ns=T0_NS - 500_000_000)
    sub.poll()
    assert entry.read(net.clock.now_ns()).validity is Validity.STALE
    assert entry.updates == 1


def test_latest_keeps_the_newest_measurement_despite_reordering(net: Net) -> None:
    """A late message with an older t_meas does not roll the latest value back."""
    sub = net.bus(SUBSCRIBER)
    entry = sub.latest(channels.IMU, 10**9)
    tap = net.tap()
    codec = Codec(keyring())
    newer = IMU._replace(accel_x_mps2=1.0)
    tap.send(channels.IMU, codec.encode(b"IMU", newer, PUBLISHER, 2, T0_NS - 1_000, T0_NS))
    tap.send(channels.IMU, codec.encode(b"IMU", IMU, PUBLISHER, 1, T0_NS - 2_000, T0_NS))
    sub.poll()
    assert entry.fresh(net.clock.now_ns()) == newer
    assert entry.updates == 2


@pytest.mark.parametrize("true_hz", [10.0, 20.0, 100.0])
def test_a_steady_channels_rate_reads_within_1_percent(true_hz: float) -> None:
    stats = ChannelStats()
    period_ns = round(1e9 / true_hz)
    stats.arrivals_ns.extend(range(0, 5_000_000_000, period_ns))
    # Read just before the next message: the wait since the last one must not count against it.
    now_ns = stats.arrivals_ns[-1] + period_ns - 1
    assert stats.rate_hz(now_ns, 1_000_000_000) == pytest.approx(true_hz, rel=0.01)


def test_a_channel_that_stops_reads_ever_lower_then_zero() -> None:
    stats = ChannelStats()
    stats.arrivals_ns.extend(range(0, 2_000_000_000, 50_000_000))  # 20 Hz for 2 s
    last = stats.arrivals_ns[-1]
    readings = [stats.rate_hz(last + gap_ns, 2_000_000_000) for gap_ns in (200_000_000, 1_000_000_000, 3_000_000_000)]
    assert readings[0] < 20.0 and readings == sorted(readings, reverse=True) and readings[-1] == 0.0
