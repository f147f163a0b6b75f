"""Fuzzing the receive path: nothing a peer sends may raise anything but ProtocolError.

Two receivers see the same traffic, in signed and in unsigned mode:

* sans-IO: Reassembler.feed -> Codec.open -> decode_body (no replay guard, so every body that
  opens reaches the msgpack decoder and the validator, whatever its type id);
* the Bus, fed through a MemTransport hub: it must never raise, and must account for every
  datagram (delivered, or counted as a reject).

Traffic is genuine messages and fragments mutated every way we could think of, random bytes,
and hand-made msgpack bodies of random structure sealed with the right key, so that signed mode
exercises the body decoder too. The main loop is seeded (deterministic); a smaller hypothesis
test adds shrinking generators.
"""

from __future__ import annotations

import math
import random
import struct
from collections.abc import Callable
from typing import Any

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol import channels
from protocol.auth import TAG_BYTES, Keyring
from protocol.codec import FLAG_FRAGMENT, FLAG_SIGNED, HEADER, HEADER_BYTES, MAGIC, VERSION, Codec, decode_body
from protocol.errors import ProtocolError, Reason
from protocol.framing import FRAGMENT_HEADER, FRAGMENT_HEADER_BYTES, Reassembler, fragment, is_fragment
from protocol.schema import info_for_class, registered
from protocol.transport import MemTransport
from rascal.runtime.bus import MAX_REJECT_SOURCES, Bus
from rascal.runtime.clock import ManualClock
from tests.protocol.wire_samples import BIG_SAMPLES, CHANNEL_OF, SAMPLES, T0_NS, assert_well_formed, keyring, seal

SEED = 0x5EED_2005
DATAGRAMS_PER_MODE = 100_000
SENDER = 42
RECEIVER = 1000
TYPE_IDS = [info.type_id for info in registered()]
# Reasons the Bus counts at poll time for partial messages it gave up on, not for a datagram.
DEFERRED = {Reason.FRAGMENT_TIMEOUT.value, Reason.FRAGMENT_EVICTED.value}

# (offset, struct format) of each header field a mutation may rewrite.
MESSAGE_FIELDS = [
    (0, "2s"),
    (2, "B"),
    (3, "B"),
    (4, "<H"),
    (6, "<H"),
    (8, "<H"),
    (10, "B"),
    (11, "B"),
    (12, "<Q"),
    (20, "<q"),
    (28, "<q"),
]
FRAGMENT_FIELDS = [(0, "2s"), (2, "B"), (3, "B"), (4, "<H"), (6, "<H"), (8, "<H"), (10, "<H"), (12, "<I"), (16, "<I")]
INTERESTING_INTS = [
    0,
    1,
    2,
    3,
    7,
    0x7F,
    0x80,
    0xFF,
    0x100,
    0x7FFF,
    0x8000,
    0xFFFF,
    0x10000,
    2**31 - 1,
    2**31,
    2**32 - 1,
    2**32,
    2**53,
    2**63 - 1,
    2**64 - 1,
    -1,
    -2,
    -128,
    -(2**31),
    -(2**63),
]
INTERESTING_FLOATS = [
    0.0,
    -0.0,
    1.0,
    -1.5,
    math.nan,
    -math.nan,
    math.inf,
    -math.inf,
    1e308,
    -1e308,
    1.7976931348623157e308,
    5e-324,
    2.0**63,
    1e-300,
]
RAW_BODIES = [
    b"",
    b"\xc0",
    b"\xc1",
    b"\x90",
    b"\x80",
    b"\xdc\xff\xff",
    b"\xdd\xff\xff\xff\xff",
    b"\xdf\xff\xff\xff\xff",
    b"\xde\x00\x02\xa1a\x01\xa1a\x02",
    b"\xa2\xff\xfe",
    b"\xd9\x05abc",
    b"\xc6\xff\xff\xff\xff\x00",
    b"\xc9\xff\xff\xff\xff\x05",
    b"\xd7\xff" + b"\xff" * 8,
    b"\xd6\xff\x00\x00\x00\x01",
    b"\xc7\x03\xff\x00\x00\x00",
    b"\x92\x01",
    b"\x92\x01\x02\x03",
    b"\x81\x01\x02",
    b"\x81\x91\x01\x02",
    b"\x81\x80\x01",
    b"\xcf" + b"\xff" * 8,
    b"\xd3\x80" + b"\x00" * 7,
    b"\xd4\x80\x00",
    b"\x91\xd4\xfe\x01",
    b"\xcb\x7f\xf8" + b"\x00" * 6,
    b"\xca\x7f\x80\x00\x00",
]


def max_of(fmt: str) -> int:
    return (1 << (8 * struct.calcsize(fmt))) - 1


class Traffic:
    """Generates batches of datagrams (usually one; a fragmented message gives several)."""

    def __init__(self, rng: random.Random, keys: Keyring | None, clock: ManualClock) -> None:
        self.rng = rng
        self.keys = keys
        self.codec = Codec(keys)
        self.clock = clock
        self.seq = 1_700_000_000_000_000
        self.message_id = 0
        self.sender = SENDER
        self.history: list[bytes] = []
        self.archive: list[bytes] = []
        self.templates = [(CHANNEL_OF[type(s)].encode(), s) for s in SAMPLES]
        self.big = [(CHANNEL_OF[type(s)].encode(), s) for s in BIG_SAMPLES]
        self.strategies: list[tuple[Callable[[], list[bytes]], int]] = [
            (self.genuine, 4),
            (self.replayed, 4),
            (self.skewed_clock, 2),
            (self.bit_flips, 12),
            (self.byte_writes, 8),
            (self.truncated, 6),
            (self.extended, 5),
            (self.header_rewrite, 12),
            (self.random_bytes, 7),
            (self.spliced, 3),
            (self.fragments, 12),
            (self.crafted_body, 20),
            (self.mutated_body, 7),
        ]
        self._choose = [s for s, _ in self.strategies]
        self._weights = [w for _, w in self.strategies]

    def batch(self) -> list[bytes]:
        self.clock.advance(self.rng.randrange(2_000_000))
        # Many senders: in unsigned mode a rewritten seq poisons one stream's window, not all.
        self.sender = self.rng.randrange(1, 500)
        datagrams = self.rng.choices(self._choose, self._weights)[0]()
        self.history.extend(datagrams[:4])
        del self.history[:-64]
        if self.rng.random() < 0.01:  # recordings old enough to be stale
            self.archive.append(datagrams[0])
        return datagrams

    # -- building blocks -----------------------------------------------------------------------

    def encoded(self, big: bool = False) -> tuple[bytes, Any]:
        """A genuine message with a fresh sequence number, published now."""
        channel, msg = self.rng.choice(self.big if big else self.templates)
        self.seq += 1
        now = self.clock.now_ns()
        return self.codec.encode(channel, msg, self.sender, self.seq, now - self.rng.randrange(10**8), now), msg

    def flip_bits(self, data: bytes, count: int, start: int = 0) -> bytes:
        buf = bytearray(data)
        if len(buf) > start:
            for _ in range(count):
                buf[self.rng.randrange(start, len(buf))] ^= 1 << self.rng.randrange(8)
        return bytes(buf)

    def rewrite(self, data: bytes, fields: list[tuple[int, str]]) -> bytes:
        buf = bytearray(data)
        for _ in range(self.rng.choice((1, 1, 1, 2, 3))):
            offset, fmt = self.rng.choice(fields)
            if offset + struct.calcsize(fmt) > len(buf):
                continue
            if fmt == "2s":
                value: Any = self.rng.choice([b"RB", b"BR", b"\x00\x00", self.rng.randbytes(2)])
            else:
                (old,) = struct.unpack_from(fmt, buf, offset)
                top = max_of(fmt)
                signed = fmt.endswith("q")
                choices = [
                    0,
                    1,
                    top,
                    top - 1,
                    old + 1,
                    old - 1,
                    self.rng.randint(0, top),
                    old ^ (1 << self.rng.randrange(8)),
                ]
                if signed:
                    choices += [-1, -(2**63), 2**63 - 1]
                value = self.rng.choice(choices)
                low, high = (-(2**63), 2**63 - 1) if signed else (0, top)
                value = min(max(value, low), high)
            struct.pack_into(fmt, buf, offset, value)
        return bytes(buf)

    def reseal(self, head_and_body: bytes) -> bytes:
        """Re-sign mutated bytes with the right key, so only the body decoder can catch them."""
        return head_and_body + self.keys.sign(head_and_body) if self.keys else head_and_body

    def unsealed(self, data: bytes) -> bytes:
        return data[:-TAG_BYTES] if self.keys else data

    # -- strategies ----------------------------------------------------------------------------

    def genuine(self) -> list[bytes]:
        data, _ = self.encoded(big=self.rng.random() < 0.3)
        if len(data) <= 1400:
            return [data]
        self.message_id += 1
        return fragment(data, self.sender, self.message_id, keyring=self.keys)

    def replayed(self) -> list[bytes]:
        recordings = self.archive if self.archive and self.rng.random() < 0.3 else self.history
        return [self.rng.choice(recordings)] if recordings else self.genuine()

    def skewed_clock(self) -> list[bytes]:
        """A genuine sender whose clock is far off (or a recording's timestamps): stale or future."""
        channel, msg = self.rng.choice(self.templates)
        self.seq += 1
        t_pub = self.clock.now_ns() + self.rng.choice((-1, 1)) * self.rng.choice((2 * 10**9, 10**12, 2**62))
        return [self.codec.encode(channel, msg, self.sender, self.seq, t_pub, t_pub)]

    def bit_flips(self) -> list[bytes]:
        data, _ = self.encoded()
        return [self.flip_bits(data, self.rng.choice((1, 1, 2, 3, 8)))]

    def byte_writes(self) -> list[bytes]:
        buf = bytearray(self.encoded()[0])
        for _ in range(self.rng.randint(1, 4)):
            buf[self.rng.randrange(len(buf))] = self.rng.choice((0, 0xFF, 0x7F, 0x80, 0xC1, self.rng.randrange(256)))
        return [bytes(buf)]

    def truncated(self) -> list[bytes]:
        data, _ = self.encoded(big=self.rng.random() < 0.1)
        return [data[: self.rng.randrange(len(data))]]

    def extended(self) -> list[bytes]:
        data, _ = self.encoded()
        extra = self.rng.choice([self.rng.randbytes(self.rng.randint(1, 64)), data[-16:], b"\x00", data])
        return [data + extra]

    def header_rewrite(self) -> list[bytes]:
        data, _ = self.encoded()
        return [self.rewrite(data, MESSAGE_FIELDS)]

    def random_bytes(self) -> list[bytes]:
        prefix = self.rng.choice(
            [
                b"",
                b"",
                b"RB",
                MAGIC + bytes([VERSION]),
                MAGIC + bytes([VERSION, FLAG_SIGNED]),
                MAGIC + bytes([VERSION, 0]),
                MAGIC + bytes([VERSION, FLAG_FRAGMENT]),
                MAGIC + bytes([VERSION, FLAG_FRAGMENT | FLAG_SIGNED]),
            ]
        )
        return [prefix + self.rng.randbytes(self.rng.choice((0, 1, 3, 19, 20, 35, 36, 37, self.rng.randrange(1500))))]

    def spliced(self) -> list[bytes]:
        first, second = self.encoded()[0], self.encoded()[0]
        cut = self.rng.randrange(len(first))
        return [first[:cut] + second[self.rng.randrange(len(second)) :]]

    def fragments(self) -> list[bytes]:
        data, _ = self.encoded(big=self.rng.random() < 0.5)
        self.message_id += 1
        if self.rng.random() < 0.3:  # mutate the whole message, then fragment it
            data = self.flip_bits(data, 1)
        parts = fragment(data, self.sender, self.message_id, self.rng.choice((1400, 1400, 1000, 600)), self.keys)
        if len(parts) == 1:
            return parts
        for _ in range(self.rng.randint(0, 3)):
            if len(parts) < 2:
                break
            index = self.rng.randrange(len(parts))
            action = self.rng.randrange(6)
            if action == 0:
                parts[index] = self.flip_bits(parts[index], 1)
            elif action == 1:
                parts[index] = self.rewrite(parts[index], FRAGMENT_FIELDS)
            elif action == 2:
                parts[index] = parts[index][: self.rng.randrange(len(parts[index]))]
            elif action == 3:
                parts[index] += self.rng.randbytes(self.rng.randint(1, 40))
            elif action == 4:
                del parts[index]
            else:
                parts.append(parts[index])
        if self.rng.random() < 0.5:
            self.rng.shuffle(parts)
        return parts

    def crafted_body(self) -> list[bytes]:
        """A well-framed, correctly sealed message around a hostile body."""
        channel, msg = self.rng.choice(self.templates)
        roll = self.rng.random()
        type_id = (
            info_for_class(type(msg)).type_id
            if roll < 0.85
            else self.rng.choice(TYPE_IDS)
            if roll < 0.95
            else self.rng.choice((0, 4, 99, 0xFFFF))
        )
        self.seq += 1
        now = self.clock.now_ns()
        data = seal(
            self.hostile_body(msg),
            keys=self.keys,
            channel=channel,
            type_id=type_id,
            source_id=self.sender,
            seq=self.seq,
            t_meas_ns=now,
            t_pub_ns=now,
        )
        if len(data) <= 1400:
            return [data]
        self.message_id += 1
        return fragment(data, self.sender, self.message_id, keyring=self.keys)

    def mutated_body(self) -> list[bytes]:
        """A genuine message whose body bytes are mutated, then sealed again."""
        data, _ = self.encoded(big=self.rng.random() < 0.1)
        head_and_body = self.unsealed(data)
        body_start = HEADER_BYTES + data[10]
        body = bytearray(head_and_body[body_start:])
        for _ in range(self.rng.randint(1, 3)):
            action = self.rng.randrange(4)
            at = self.rng.randrange(len(body) + 1)
            if action == 0 and body:
                body[min(at, len(body) - 1)] ^= 1 << self.rng.randrange(8)
            elif action == 1:
                body[at:at] = self.rng.randbytes(self.rng.randint(1, 9))
            elif action == 2:
                del body[at : at + self.rng.randint(1, 9)]
            else:
                body[at:at] = self.rng.choice(RAW_BODIES)
        return [self.reseal(head_and_body[:body_start] + bytes(body))]

    # -- hostile msgpack -----------------------------------------------------------------------

    def hostile_body(self, msg: Any) -> bytes:
        rng = self.rng
        roll = rng.random()
        if roll < 0.15:
            return rng.choice(RAW_BODIES)
        if roll < 0.22:
            depth = rng.choice((10, 500, 1023, 1024, 1025, 5000))  # msgpack's own limit is 1024
            return rng.choice((b"\x91", b"\x81\xa1k", b"\xdc\x00\x01")) * depth + rng.choice((b"\xc0", b"\x01", b""))
        if roll < 0.3:
            return msgpack.packb(self.random_value(4), use_bin_type=rng.random() < 0.8)
        body = self.structured_mutation(msg)
        packed = msgpack.packb(body, use_bin_type=rng.random() < 0.9)
        if rng.random() < 0.05:
            packed += rng.choice((b"\x00", packed, rng.randbytes(3)))  # trailing data
        return packed

    def structured_mutation(self, msg: Any) -> Any:
        """The message as nested lists with one to three nodes replaced, dropped or added."""
        body = _as_lists(msg)
        for _ in range(self.rng.randint(1, 3)):
            container, index = self.random_node(body)
            action = self.rng.randrange(5)
            if action == 0 or not container:
                container.insert(index, self.random_value(2))
            elif action == 1:
                del container[index % len(container)]
            elif action == 2:
                container.append(self.random_value(1))
            else:
                container[index % len(container)] = self.random_value(3)
        return body

    def random_node(self, body: list) -> tuple[list, int]:
        node = body
        while True:
            if not node:
                return node, 0
            index = self.rng.randrange(len(node))
            child = node[index]
            if isinstance(child, list) and self.rng.random() < 0.6:
                node = child
                continue
            return node, index

    def random_value(self, depth: int) -> Any:
        rng = self.rng
        kind = rng.randrange(14 if depth > 0 else 10)
        if kind == 0:
            return None
        if kind == 1:
            return rng.random() < 0.5
        if kind == 2:
            return rng.choice(INTERESTING_INTS)
        if kind == 3:
            return rng.choice(INTERESTING_FLOATS)
        if kind == 4:
            return rng.uniform(-1e6, 1e6)
        if kind == 5:
            planes = ((32, 127), (0x80, 0xD800), (0x10000, 0x110000))  # ASCII, BMP, astral (no surrogates)
            return "".join(chr(rng.randrange(*rng.choice(planes))) for _ in range(rng.randrange(12)))
        if kind == 6:
            return rng.randbytes(rng.randrange(20))
        if kind == 7:
            return msgpack.ExtType(rng.choice((0, 1, 5, 127)), rng.randbytes(rng.choice((0, 1, 4, 8, 12, 30))))
        if kind == 8:
            return msgpack.Timestamp(rng.randrange(2**34), rng.randrange(10**9))
        if kind == 9:
            return [rng.choice(INTERESTING_FLOATS) for _ in range(rng.randrange(10))]
        if kind == 10:
            return [self.random_value(depth - 1) for _ in range(rng.randrange(6))]
        if kind == 11:
            keys = ("a", "b", "speed_mps", "")
            return {rng.choice(keys): self.random_value(depth - 1) for _ in range(rng.randrange(4))}
        if kind == 12:  # records of plausible widths
            width = rng.choice((2, 3, 6, 7, 8, 9))
            return [[rng.choice(INTERESTING_FLOATS) for _ in range(width)] for _ in range(rng.randrange(5))]
        return [
            [rng.uniform(-100, 100) for _ in range(8)] + ([self.random_value(0)] if rng.random() < 0.5 else [])
            for _ in range(rng.randrange(1, 4))
        ]


def _as_lists(value: Any) -> Any:
    if isinstance(value, tuple):
        return [_as_lists(item) for item in value]
    return value


# -- receivers ---------------------------------------------------------------------------------


class SansIoReceiver:
    """Reassembler -> Codec.open -> decode_body; returns how each datagram ended."""

    def __init__(self, keys: Keyring | None) -> None:
        self.codec = Codec(keys)
        self.reassembler = Reassembler(keyring=keys)
        self.outcomes: dict[str, int] = {}

    def receive(self, datagram: bytes, now_ns: int) -> None:
        try:
            if is_fragment(datagram):
                whole = self.reassembler.feed(datagram, now_ns)
                if whole is None:
                    self._count("absorbed")
                    return
                datagram = whole
            opened = self.codec.open(datagram)
            msg = decode_body(opened.type_id, opened.body, opened.source_id)
        except ProtocolError as error:
            assert isinstance(error.reason, Reason)
            self._count(error.reason.value)
            return
        assert type(msg) is next(info.cls for info in registered() if info.type_id == opened.type_id)
        assert_well_formed(msg)
        self._count("accepted")

    def _count(self, outcome: str) -> None:
        self.outcomes[outcome] = self.outcomes.get(outcome, 0) + 1


class CountingBus(Bus):
    """A Bus that also tells rejects of one datagram from those of abandoned partial messages."""

    direct_rejects = 0

    def _count_reject(self, error: ProtocolError) -> None:
        super()._count_reject(error)
        if error.reason.value not in DEFERRED:
            self.direct_rejects += 1


class BusReceiver:
    """A Bus subscribed to every declared channel (typed) and to everything (raw)."""

    def __init__(self, hub: str, keys: Keyring | None, clock: ManualClock) -> None:
        self.bus = CountingBus(MemTransport(hub), RECEIVER, keys, clock)
        self.tap = MemTransport(hub)
        self.raw_accepted = 0
        self.typed_accepted = 0
        for name, cls in channels.CHANNEL_TYPES.items():
            self.bus.subscribe(name, self._typed(cls))
            self.bus.latest(name, 10**9)
        self.bus.subscribe_raw(self._raw)

    def _typed(self, cls: type) -> Callable[[Any, Any], None]:
        def handler(msg: Any, envelope: Any) -> None:
            assert type(msg) is cls
            assert_well_formed(msg)
            self.typed_accepted += 1

        return handler

    def _raw(self, opened: Any, data: bytes, recv_ns: int) -> None:
        self.raw_accepted += 1

    def receive(self, datagram: bytes) -> None:
        """Send one datagram through the hub and poll: exactly one outcome for a whole message,
        at most one for a fragment (it may just be held, or be a duplicate)."""
        before = self.raw_accepted + self.bus.direct_rejects
        self.tap.send(channels.IMU, datagram)
        assert self.bus.poll() == 1
        outcomes = self.raw_accepted + self.bus.direct_rejects - before
        if is_fragment(datagram):
            assert outcomes <= 1
        else:
            assert outcomes == 1, "a whole datagram was neither delivered nor counted"

    def finish(self, clock: ManualClock) -> None:
        """Give up on held fragments: they are counted, and nothing stays pending."""
        self.bus.reassembler.expire(clock.now_ns() + self.bus.reassembler.limits.timeout_ns + 1)
        self.bus.poll()
        assert self.bus.reassembler.pending() == 0
        assert not self.bus.reassembler.dropped
        assert len(self.bus.rejects) <= MAX_REJECT_SOURCES + len(Reason)
        assert len(self.bus.replay) <= self.bus.replay.limits.max_streams
        direct = sum(n for (_source, reason), n in self.bus.rejects.items() if reason not in DEFERRED)
        assert direct == self.bus.direct_rejects
        self.bus.close()
        self.tap.close()


def _describe(datagram: bytes) -> str:
    return f"{len(datagram)} B: {datagram[:80].hex()}{'...' if len(datagram) > 80 else ''}"


def fuzz(signed: bool, datagrams: int, seed: int) -> tuple[SansIoReceiver, BusReceiver]:
    """Feed ``datagrams`` generated datagrams to both receivers; raise AssertionError naming the
    datagram, mode and seed on the first that raises anything but ProtocolError or is unaccounted."""
    rng = random.Random(seed + signed)
    keys = keyring() if signed else None
    clock = ManualClock(T0_NS)
    traffic = Traffic(rng, keys, clock)
    sans_io = SansIoReceiver(keys)
    bus = BusReceiver(f"fuzz-{'signed' if signed else 'unsigned'}-{seed}", keys, clock)
    sent = 0
    while sent < datagrams:
        for datagram in traffic.batch():
            sent += 1
            try:
                sans_io.receive(datagram, clock.local_ns())
                bus.receive(datagram)
            except Exception as exc:
                raise AssertionError(
                    f"datagram #{sent} ({'signed' if signed else 'unsigned'}, seed {seed:#x}) "
                    f"raised {type(exc).__name__}: {exc}\n{_describe(datagram)}"
                ) from exc
    bus.finish(clock)
    return sans_io, bus


@pytest.mark.parametrize("signed", [True, False], ids=["signed", "unsigned"])
def test_random_and_mutated_datagrams_only_ever_raise_protocol_error(signed: bool) -> None:
    """100,000 random and mutated datagrams per mode: the sans-IO path raises only ProtocolError
    and only delivers well-formed messages; the Bus never raises and accounts for every datagram.
    (``make fuzz`` runs the same generators over a million more, tests/protocol/fuzz_campaign.py.)"""
    sans_io, bus = fuzz(signed, DATAGRAMS_PER_MODE, SEED)
    outcomes = sans_io.outcomes
    # The traffic really exercised the deep paths, not just the cheap early rejections.
    assert outcomes["accepted"] > 1000 and bus.typed_accepted > 1000
    assert outcomes["bad_body"] > 5000
    for reason in ("truncated", "bad_magic", "bad_version", "bad_header", "bad_fragment", "unknown_type"):
        assert outcomes.get(reason, 0) > 50, (reason, outcomes)
    if signed:
        assert outcomes["bad_mac"] > 5000 and outcomes["unsigned"] > 50 and outcomes["unknown_key"] > 50
    else:
        assert "bad_mac" not in outcomes
    bus_reasons = {reason for _source, reason in bus.bus.rejects}
    assert {"replay", "wrong_type", "bad_body", "stale", "future"} <= bus_reasons, bus_reasons


# -- hypothesis --------------------------------------------------------------------------------

MSGPACK_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=20)
    | st.binary(max_size=20)
    | st.builds(msgpack.ExtType, st.integers(0, 127), st.binary(max_size=16)),
    lambda inner: st.lists(inner, max_size=8) | st.dictionaries(st.text(max_size=5), inner, max_size=4),
    max_leaves=25,
)
PREFIXES = [
    b"",
    *(MAGIC + bytes([VERSION, flags]) for flags in (0, FLAG_SIGNED, FLAG_FRAGMENT, FLAG_FRAGMENT | FLAG_SIGNED)),
]


def _receive_everywhere(datagram: bytes) -> None:
    """Both codecs and a reassembler: only ProtocolError may come out; decoded messages are well formed."""
    for keys in (keyring(), None):
        reassembler = Reassembler(keyring=keys)
        try:
            if is_fragment(datagram):
                datagram = reassembler.feed(datagram, T0_NS) or b""
            opened = Codec(keys).open(datagram)
            assert_well_formed(decode_body(opened.type_id, opened.body))
        except ProtocolError:
            pass


@settings(max_examples=600, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(prefix=st.sampled_from(PREFIXES), rest=st.binary(max_size=1600))
def test_arbitrary_bytes_only_raise_protocol_error(prefix: bytes, rest: bytes) -> None:
    """Any byte string (optionally behind a valid-looking prefix) raises at most ProtocolError."""
    _receive_everywhere(prefix + rest)


@settings(max_examples=300, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(type_id=st.sampled_from(TYPE_IDS), body=MSGPACK_VALUES, fields=st.lists(MSGPACK_VALUES, max_size=14))
def test_signed_bodies_of_any_msgpack_structure_only_raise_protocol_error(
    type_id: int, body: Any, fields: list[Any]
) -> None:
    """Correctly signed messages whose body is any msgpack value, or an array of any values,
    decode to a well-formed message or raise ProtocolError(BAD_BODY)."""
    keys = keyring()
    for value in (body, fields):
        data = seal(msgpack.packb(value, use_bin_type=True), keys=keys, type_id=type_id)
        opened = Codec(keys).open(data)
        try:
            assert_well_formed(decode_body(opened.type_id, opened.body))
        except ProtocolError as error:
            assert error.reason is Reason.BAD_BODY


@settings(max_examples=300, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(
    sample=st.sampled_from(SAMPLES + BIG_SAMPLES),
    edits=st.lists(st.tuples(st.integers(0, 2**20), st.integers(0, 255)), min_size=1, max_size=4),
    cut=st.none() | st.integers(0, 2**20),
    fragmented=st.booleans(),
)
def test_edited_genuine_messages_and_fragments_only_raise_protocol_error(
    sample: Any, edits: list[tuple[int, int]], cut: int | None, fragmented: bool
) -> None:
    """A genuine message or one of its fragments, with bytes overwritten and maybe truncated,
    raises at most ProtocolError in both modes."""
    for keys in (keyring(), None):
        data = Codec(keys).encode(CHANNEL_OF[type(sample)].encode(), sample, SENDER, 1, T0_NS, T0_NS)
        parts = fragment(data, SENDER, 1, 600, keys) if fragmented else [data]
        target = edits[0][0] % len(parts)
        buf = bytearray(parts[target])
        for offset, value in edits:
            buf[offset % len(buf)] = value
        parts[target] = bytes(buf[: None if cut is None else cut % (len(buf) + 1)])
        reassembler = Reassembler(keyring=keys)
        for part in parts:
            try:
                whole = reassembler.feed(part, T0_NS) if is_fragment(part) else part
                if whole is not None:
                    opened = Codec(keys).open(whole)
                    assert_well_formed(decode_body(opened.type_id, opened.body))
            except ProtocolError:
                pass


def test_headers_of_every_field_value_class_are_handled() -> None:
    """Every header field set to each boundary value, in a sealed message and a fragment, is
    handled (accepted or ProtocolError) by both codecs and the reassembler."""
    base_body = msgpack.packb([1.0, 2.0])
    for keys in (keyring(), None):
        data = seal(base_body, keys=keys, channel=b"WHEEL_SPEED", type_id=12)
        frag = fragment(data + b"\x00" * 1500, SENDER, 1, keyring=keys)[0]
        for template, fields in ((data, MESSAGE_FIELDS), (frag, FRAGMENT_FIELDS)):
            for offset, fmt in fields:
                if fmt == "2s":
                    continue
                for value in (0, 1, max_of(fmt)):
                    buf = bytearray(template)
                    struct.pack_into(fmt.replace("q", "Q"), buf, offset, value)
                    _receive_everywhere(bytes(buf))
    assert HEADER.size == HEADER_BYTES and FRAGMENT_HEADER.size == FRAGMENT_HEADER_BYTES
