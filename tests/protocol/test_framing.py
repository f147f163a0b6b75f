"""Fragmentation and reassembly: exactness, reordering, loss, and the memory bounds."""

from __future__ import annotations

import itertools
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.auth import FRAGMENT_TAG_BYTES, Keyring
from protocol.codec import FLAG_FRAGMENT, FLAG_SIGNED, MAGIC, VERSION
from protocol.errors import ProtocolError, Reason
from protocol.framing import (
    DEFAULT_MAX_DATAGRAM_BYTES,
    FRAGMENT_HEADER,
    FRAGMENT_HEADER_BYTES,
    Reassembler,
    ReassemblyLimits,
    fragment,
    is_fragment,
    new_message_id,
)
from tests.protocol.wire_samples import WRONG_KEY, keyring

T0 = 1_000_000_000_000
SOURCE = 7


def payload(size: int, seed: int = 0) -> bytes:
    return random.Random(seed).randbytes(size)


def header(
    index: int,
    count: int,
    total: int,
    *,
    message_id: int = 1,
    source_id: int = SOURCE,
    flags: int = FLAG_FRAGMENT,
    version: int = VERSION,
    magic: bytes = MAGIC,
) -> bytes:
    return FRAGMENT_HEADER.pack(magic, version, flags, source_id, index, count, 0, message_id, total)


def feed_all(reassembler: Reassembler, datagrams: list[bytes], now_ns: int = T0) -> list[bytes]:
    """Feed every datagram; return the messages that completed, in order."""
    return [whole for d in datagrams if (whole := reassembler.feed(d, now_ns)) is not None]


def reason_of(reassembler: Reassembler, datagram: bytes, now_ns: int = T0) -> Reason:
    with pytest.raises(ProtocolError) as caught:
        reassembler.feed(datagram, now_ns)
    return caught.value.reason


def retained_bytes(reassembler: Reassembler, source_id: int) -> int:
    """Fragment data actually held for a source."""
    partials = reassembler._sources.get(source_id, {})
    return sum(len(part) for partial in partials.values() for part in partial.parts.values())


# -- exact reassembly --------------------------------------------------------------------------


@pytest.mark.parametrize("size", [1536, 64 * 1024, 200_000], ids=["1.5KB", "64KiB", "200KB"])
def test_a_message_fragments_and_reassembles_exactly(size: int) -> None:
    """A message over one datagram splits into fragments of at most max_datagram bytes that
    reassemble, in order, into exactly the original, once, on the last fragment."""
    message = payload(size, size)
    datagrams = fragment(message, SOURCE, 99)
    chunk = DEFAULT_MAX_DATAGRAM_BYTES - FRAGMENT_HEADER_BYTES
    assert len(datagrams) == -(-size // chunk)
    assert all(len(d) <= DEFAULT_MAX_DATAGRAM_BYTES and is_fragment(d) for d in datagrams)
    reassembler = Reassembler()
    results = [reassembler.feed(d, T0) for d in datagrams]
    assert results[:-1] == [None] * (len(datagrams) - 1)
    assert results[-1] == message
    assert reassembler.pending() == 0
    assert reassembler.dropped == []


@pytest.mark.parametrize("size", [1536, 64 * 1024, 200_000], ids=["1.5KB", "64KiB", "200KB"])
@pytest.mark.parametrize("seed", range(3))
def test_shuffled_and_duplicated_fragments_reassemble_exactly_once(size: int, seed: int) -> None:
    """Fragments in any order, some of them sent two or three times (also after completion),
    give the original message exactly once."""
    rng = random.Random(seed)
    message = payload(size, seed)
    parts = fragment(message, SOURCE, seed)
    again = rng.sample(parts, rng.randint(1, len(parts) - 1))  # never a whole second copy
    datagrams = parts + again + rng.sample(again, len(again) // 2)
    rng.shuffle(datagrams)
    reassembler = Reassembler()
    assert feed_all(reassembler, datagrams) == [message]


@settings(max_examples=150, deadline=None, derandomize=True)
@given(
    size=st.integers(1401, 30_000),
    max_datagram=st.integers(200, 4000),
    order=st.randoms(use_true_random=False),
)
def test_any_order_of_fragments_of_any_size_reassembles_exactly(
    size: int, max_datagram: int, order: random.Random
) -> None:
    """For any message size, datagram size and arrival order, reassembly is exact and single."""
    message = payload(size)
    datagrams = fragment(message, SOURCE, 5, max_datagram)
    if len(datagrams) == 1:  # fits in one datagram: sent whole, not as a fragment
        assert datagrams == [message]
        return
    datagrams += order.sample(datagrams, order.randint(0, len(datagrams) - 1))
    order.shuffle(datagrams)
    assert feed_all(Reassembler(), datagrams) == [message]


def test_a_complete_resend_after_completion_is_a_new_message() -> None:
    """The reassembler forgets completed messages: a full second copy reassembles again (the
    replay guard, not reassembly, drops it as a duplicate message)."""
    message = payload(5000)
    parts = fragment(message, SOURCE, 1)
    assert feed_all(Reassembler(), parts + parts[::-1]) == [message, message]


def test_a_message_that_fits_is_sent_whole() -> None:
    """A message no longer than one datagram is returned unchanged as the only datagram."""
    for size in (4, 100, DEFAULT_MAX_DATAGRAM_BYTES):
        message = MAGIC + bytes([VERSION, FLAG_SIGNED]) + payload(size - 4)
        assert fragment(message, SOURCE, 1) == [message]
        assert not is_fragment(message)


def test_interleaved_messages_from_several_sources_reassemble_separately() -> None:
    """Fragments of several messages and sources, interleaved, each reassemble to their own
    message even when message ids collide across sources."""
    rng = random.Random(3)
    messages = {
        (source, mid): payload(rng.randint(1500, 20_000), source * 10 + mid) for source in (1, 2, 3) for mid in (1, 2)
    }
    datagrams = [d for (source, mid), msg in messages.items() for d in fragment(msg, source, mid)]
    rng.shuffle(datagrams)
    assert sorted(feed_all(Reassembler(), datagrams)) == sorted(messages.values())


def test_a_message_needing_more_than_65535_fragments_is_refused() -> None:
    """fragment() refuses (ValueError) a message whose fragment count would not fit in 16 bits."""
    with pytest.raises(ValueError, match="65535"):
        fragment(b"x" * 65536, SOURCE, 1, max_datagram=FRAGMENT_HEADER_BYTES + 1)


# -- loss and timeout --------------------------------------------------------------------------


def test_a_lost_fragment_delivers_nothing_and_times_out() -> None:
    """Without one fragment nothing is delivered; once the timeout passes the partial message is
    dropped and reported as FRAGMENT_TIMEOUT for its source."""
    limits = ReassemblyLimits(timeout_ns=500_000_000)
    reassembler = Reassembler(limits)
    datagrams = fragment(payload(64 * 1024), SOURCE, 42)
    del datagrams[17]
    assert feed_all(reassembler, datagrams) == []
    assert reassembler.pending() == 1
    reassembler.expire(T0 + limits.timeout_ns - 1)
    assert reassembler.dropped == []
    reassembler.expire(T0 + limits.timeout_ns + 1)
    assert [(e.reason, e.source_id) for e in reassembler.dropped] == [(Reason.FRAGMENT_TIMEOUT, SOURCE)]
    assert reassembler.pending() == 0


def test_timeouts_are_noticed_by_the_next_fragment() -> None:
    """A stale partial is dropped as FRAGMENT_TIMEOUT when any later fragment arrives, and the
    missing fragment arriving after that does not complete anything."""
    limits = ReassemblyLimits(timeout_ns=100)
    reassembler = Reassembler(limits)
    datagrams = fragment(payload(5000), SOURCE, 1)
    assert feed_all(reassembler, datagrams[:-1], T0) == []
    other = fragment(payload(3000, 1), SOURCE + 1, 2)
    assert reassembler.feed(other[0], T0 + 101) is None
    assert [e.reason for e in reassembler.dropped] == [Reason.FRAGMENT_TIMEOUT]
    assert reassembler.feed(datagrams[-1], T0 + 102) is None


def test_the_timeout_counts_from_the_first_fragment() -> None:
    """A slow trickle of fragments does not keep a partial message alive past the timeout."""
    limits = ReassemblyLimits(timeout_ns=1000)
    reassembler = Reassembler(limits)
    datagrams = fragment(payload(10_000), SOURCE, 1)
    results = [reassembler.feed(d, T0 + 300 * i) for i, d in enumerate(datagrams)]
    assert all(result is None for result in results)
    assert Reason.FRAGMENT_TIMEOUT in [e.reason for e in reassembler.dropped]


# -- memory bounds -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "limits",
    [
        ReassemblyLimits(),
        ReassemblyLimits(max_message_bytes=50_000, max_partials_per_source=3, max_bytes_per_source=80_000),
        ReassemblyLimits(max_message_bytes=200_000, max_partials_per_source=100, max_bytes_per_source=64 * 1024),
    ],
    ids=["defaults", "few-partials", "few-bytes"],
)
def test_one_source_never_holds_more_than_its_bounds(limits: ReassemblyLimits) -> None:
    """However many partial messages one source starts, at most max_partials_per_source are
    kept and at most max_bytes_per_source are reserved and held; the rest are FRAGMENT_EVICTED
    or refused as OVERSIZED."""
    rng = random.Random(11)
    reassembler = Reassembler(limits)
    started = 0
    for message_id in range(300):
        message = payload(rng.randint(2000, limits.max_message_bytes), message_id)
        parts = fragment(message, SOURCE, message_id)
        try:
            for part in parts[: rng.randint(1, len(parts) - 1)]:  # never the whole message
                assert reassembler.feed(part, T0) is None
            started += 1
        except ProtocolError as error:
            assert error.reason is Reason.OVERSIZED  # one message alone exceeds the byte bound
            assert len(message) > limits.max_bytes_per_source
        assert len(reassembler._sources.get(SOURCE, {})) <= limits.max_partials_per_source
        assert reassembler._bytes.get(SOURCE, 0) <= limits.max_bytes_per_source
        assert retained_bytes(reassembler, SOURCE) <= limits.max_bytes_per_source
    evicted = [e for e in reassembler.dropped if e.reason is Reason.FRAGMENT_EVICTED]
    assert evicted and all(e.source_id == SOURCE for e in evicted)
    assert len(evicted) + reassembler.pending() == started


def test_a_message_larger_than_the_per_source_byte_bound_is_oversized() -> None:
    """A single fragmented message over max_bytes_per_source is refused (OVERSIZED) up front,
    so no limits can let one source hold more than its bound."""
    limits = ReassemblyLimits(max_message_bytes=256 * 1024, max_bytes_per_source=100_000)
    reassembler = Reassembler(limits)
    assert reason_of(reassembler, fragment(payload(150_000), SOURCE, 1)[0]) is Reason.OVERSIZED
    assert reassembler.pending() == 0
    assert feed_all(reassembler, fragment(payload(100_000), SOURCE, 2)) == [payload(100_000)]


def test_many_sources_are_bounded_by_max_sources() -> None:
    """Partial messages from many sources keep at most max_sources sources; the least recently
    heard source is evicted and its partials reported as FRAGMENT_EVICTED."""
    limits = ReassemblyLimits(max_sources=8)
    reassembler = Reassembler(limits)
    for source_id in range(1, 201):
        reassembler.feed(fragment(payload(3000), source_id, source_id)[0], T0)
        assert len(reassembler._sources) <= limits.max_sources
        assert reassembler.pending() <= limits.max_sources * limits.max_partials_per_source
    evicted = {e.source_id for e in reassembler.dropped if e.reason is Reason.FRAGMENT_EVICTED}
    assert evicted == set(range(1, 193))
    assert set(reassembler._sources) == set(range(193, 201))


def test_an_active_source_is_not_evicted_by_newcomers() -> None:
    """A source heard from recently survives a crowd of new sources, and its message completes."""
    limits = ReassemblyLimits(max_sources=4)
    reassembler = Reassembler(limits)
    message = payload(20_000)
    mine = fragment(message, SOURCE, 1)
    results = []
    for i, part in enumerate(mine):
        results.append(reassembler.feed(part, T0))
        reassembler.feed(fragment(payload(3000), 1000 + i, 1)[0], T0)  # a stranger each time
    assert results[-1] == message


def test_an_evicted_message_cannot_complete() -> None:
    """The remaining fragments of an evicted message start a new partial; nothing is delivered."""
    limits = ReassemblyLimits(max_partials_per_source=1)
    reassembler = Reassembler(limits)
    first = fragment(payload(5000), SOURCE, 1)
    reassembler.feed(first[0], T0)
    reassembler.feed(fragment(payload(5000, 1), SOURCE, 2)[0], T0)
    assert [e.reason for e in reassembler.dropped] == [Reason.FRAGMENT_EVICTED]
    assert feed_all(reassembler, first[1:]) == []


# -- malformed fragments -----------------------------------------------------------------------


def test_fragments_disagreeing_on_total_length_are_bad_fragment() -> None:
    """A fragment whose total length differs from the earlier fragments of its message is BAD_FRAGMENT."""
    reassembler = Reassembler()
    reassembler.feed(header(0, 3, 3000) + b"a" * 1000, T0)
    assert reason_of(reassembler, header(1, 3, 3001) + b"b" * 1000) is Reason.BAD_FRAGMENT


def test_fragments_disagreeing_on_count_are_bad_fragment() -> None:
    """A fragment whose count differs from the earlier fragments of its message is BAD_FRAGMENT."""
    reassembler = Reassembler()
    reassembler.feed(header(0, 3, 3000) + b"a" * 1000, T0)
    assert reason_of(reassembler, header(1, 4, 3000) + b"b" * 1000) is Reason.BAD_FRAGMENT


def test_fragments_overflowing_the_declared_total_are_bad_fragment_and_freed() -> None:
    """Fragment data beyond the declared total is BAD_FRAGMENT, and the partial is released."""
    reassembler = Reassembler()
    assert reason_of(reassembler, header(0, 2, 100) + b"a" * 101) is Reason.BAD_FRAGMENT
    assert reassembler.pending() == 0
    reassembler.feed(header(0, 3, 3000, message_id=2) + b"a" * 2000, T0)
    assert reason_of(reassembler, header(1, 3, 3000, message_id=2) + b"b" * 1001) is Reason.BAD_FRAGMENT
    assert reassembler.pending() == 0


def test_fragments_short_of_the_declared_total_are_bad_fragment() -> None:
    """All fragments present but fewer bytes than declared is BAD_FRAGMENT, not a short message."""
    reassembler = Reassembler()
    reassembler.feed(header(0, 2, 3000) + b"a" * 1000, T0)
    assert reason_of(reassembler, header(1, 2, 3000) + b"b" * 1000) is Reason.BAD_FRAGMENT
    assert reassembler.pending() == 0


@pytest.mark.parametrize(
    "index,count,total,flags",
    [
        (0, 1, 100, FLAG_FRAGMENT),  # one fragment is not fragmentation
        (0, 0, 100, FLAG_FRAGMENT),
        (2, 2, 100, FLAG_FRAGMENT),  # index out of range
        (65535, 3, 100, FLAG_FRAGMENT),
        (0, 5, 4, FLAG_FRAGMENT),  # more fragments than bytes
        (0, 2, 100, FLAG_FRAGMENT | 0x04),  # fragments carry no flag but SIGNED
        (0, 2, 100, 0x06),
    ],
)
def test_inconsistent_fragment_headers_are_bad_fragment(index: int, count: int, total: int, flags: int) -> None:
    """Impossible index/count/total combinations or extra flags are BAD_FRAGMENT and keep nothing."""
    reassembler = Reassembler()
    assert reason_of(reassembler, header(index, count, total, flags=flags) + b"x") is Reason.BAD_FRAGMENT
    assert reassembler.pending() == 0


def test_malformed_fragment_framing_is_rejected_with_its_reason() -> None:
    """Short, wrongly tagged, wrong-version or too-large fragments are TRUNCATED, BAD_MAGIC,
    BAD_VERSION or OVERSIZED."""
    reassembler = Reassembler(ReassemblyLimits(max_message_bytes=10_000))
    assert reason_of(reassembler, header(0, 2, 100)) is Reason.TRUNCATED  # no data
    assert reason_of(reassembler, header(0, 2, 100)[:-1]) is Reason.TRUNCATED
    assert reason_of(reassembler, b"") is Reason.TRUNCATED
    assert reason_of(reassembler, header(0, 2, 100, magic=b"XX") + b"x") is Reason.BAD_MAGIC
    assert reason_of(reassembler, header(0, 2, 100, version=2) + b"x") is Reason.BAD_VERSION
    assert reason_of(reassembler, header(0, 2, 10_001) + b"x") is Reason.OVERSIZED
    assert reassembler.pending() == 0


# -- authenticated fragments -------------------------------------------------------------------


def test_signed_fragments_carry_a_tag_and_reassemble_exactly() -> None:
    """With a keyring every fragment has flags FRAGMENT|SIGNED, the active key id, and an 8-byte
    tag after its data, still within max_datagram; a keyed reassembler rebuilds the message."""
    keys = keyring(1, 2, active=2)
    message = payload(10_000)
    datagrams = fragment(message, SOURCE, 3, keyring=keys)
    chunk = DEFAULT_MAX_DATAGRAM_BYTES - FRAGMENT_HEADER_BYTES - FRAGMENT_TAG_BYTES
    assert len(datagrams) == -(-len(message) // chunk)
    for datagram in datagrams:
        fields = FRAGMENT_HEADER.unpack_from(datagram)
        assert fields[2] == FLAG_FRAGMENT | FLAG_SIGNED and fields[6] == 2
        assert len(datagram) <= DEFAULT_MAX_DATAGRAM_BYTES
    assert feed_all(Reassembler(keyring=keyring(1, 2)), datagrams[::-1]) == [message]


def test_any_change_to_a_signed_fragment_is_bad_mac_and_changes_nothing() -> None:
    """Flipping any bit of header (after the flags), data or tag fails the tag, before the
    fragment touches the partial message it names; the genuine message still completes."""
    keys = keyring()
    message = payload(5000)
    first, *rest = fragment(message, SOURCE, 9, keyring=keys)
    reassembler = Reassembler(keyring=keys)
    assert reassembler.feed(first, T0) is None
    for position in [4, 6, 8, 10, 12, 16, FRAGMENT_HEADER_BYTES, len(rest[0]) - 1]:
        for bit in (0x01, 0x80):
            forged = bytearray(rest[0])
            forged[position] ^= bit
            assert reason_of(reassembler, bytes(forged)) in (Reason.BAD_MAC, Reason.UNKNOWN_KEY, Reason.BAD_FRAGMENT)
    assert reassembler.pending() == 1
    assert feed_all(reassembler, rest) == [message]


def test_a_signed_receiver_refuses_unsigned_wrong_key_and_unknown_key_fragments() -> None:
    """Untagged fragments are UNSIGNED, tags under another key BAD_MAC, an unlisted key id
    UNKNOWN_KEY, a fragment too short for its tag TRUNCATED; none is held."""
    reassembler = Reassembler(keyring=keyring())
    message = payload(3000)
    assert reason_of(reassembler, fragment(message, SOURCE, 1)[0]) is Reason.UNSIGNED
    wrong = Keyring({1: WRONG_KEY}, 1)
    assert reason_of(reassembler, fragment(message, SOURCE, 1, keyring=wrong)[0]) is Reason.BAD_MAC
    assert reason_of(reassembler, fragment(message, SOURCE, 1, keyring=keyring(7))[0]) is Reason.UNKNOWN_KEY
    short = header(0, 2, 100, flags=FLAG_FRAGMENT | FLAG_SIGNED) + b"x" * FRAGMENT_TAG_BYTES
    assert reason_of(reassembler, short) is Reason.TRUNCATED
    assert reassembler.pending() == 0


def test_an_unsigned_receiver_strips_fragment_tags_unverified() -> None:
    """The unsigned mode takes tagged fragments as it takes signed messages: tag stripped."""
    message = payload(4000)
    assert feed_all(Reassembler(), fragment(message, SOURCE, 1, keyring=keyring())) == [message]


def test_message_ids_are_random() -> None:
    """Message ids cannot be predicted from earlier ones: 200 draws (a repeat has odds of 5 in a
    million), no repeats, no common step."""
    ids = [new_message_id() for _ in range(200)]
    assert len(set(ids)) == 200 and all(0 <= i < 2**32 for i in ids)
    assert len({b - a for a, b in itertools.pairwise(ids)}) > 190
