"""Sans-IO fragmentation and reassembly of messages larger than one datagram.

Fragment datagram (little-endian; SPEC.md section 8 is normative)::

    magic "RB" | version u8 | flags u8 (FRAGMENT, + SIGNED) | source_id u16 | index u16 |
    count u16 | key_id u16 | message_id u32 | total_len u32 | data | tag (8 B, if SIGNED)

Each signed fragment carries its own keyed BLAKE2b-64 tag over header and data, checked before
the fragment may take any reassembly state: a forger without the key can neither start, evict
nor poison a partial message. The reassembled message still carries its own MAC and replay
checks. The bounds (per source and overall) remain against key holders gone mad, and in the
unsigned mode, where fragments carry no tag, as messages carry none: with them, incomplete
messages hold at most ``max_total_bytes`` (4 MiB) however many sources send, and each is freed
at its timeout by the receiver's next poll (rascal.runtime.bus.Bus.poll wakes for it), whether or not
another fragment comes.
"""

from __future__ import annotations

import secrets
import struct
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import NamedTuple

from protocol.auth import FRAGMENT_TAG_BYTES, Keyring
from protocol.codec import FLAG_FRAGMENT, FLAG_SIGNED, MAGIC, VERSION
from protocol.errors import ProtocolError, Reason

FRAGMENT_HEADER = struct.Struct("<2sBBHHHHII")
FRAGMENT_HEADER_BYTES = FRAGMENT_HEADER.size  # 20
FRAGMENT_FLAGS = (FLAG_FRAGMENT, FLAG_FRAGMENT | FLAG_SIGNED)
DEFAULT_MAX_DATAGRAM_BYTES = 1400


def new_message_id() -> int:
    """A message id nobody can predict, so none can be claimed before the sender uses it."""
    return secrets.randbits(32)


def fragment(
    message: bytes,
    source_id: int,
    message_id: int,
    max_datagram: int = DEFAULT_MAX_DATAGRAM_BYTES,
    keyring: Keyring | None = None,
) -> list[bytes]:
    """Split ``message`` into fragment datagrams of at most ``max_datagram`` bytes each, each
    tagged with ``keyring``'s active key (unsigned without one).

    A message that fits in one datagram is returned unchanged, as the only element.
    """
    if len(message) <= max_datagram:
        return [message]
    tag_bytes = FRAGMENT_TAG_BYTES if keyring is not None else 0
    chunk = max_datagram - FRAGMENT_HEADER_BYTES - tag_bytes
    if chunk < 1:
        raise ValueError(f"a datagram of {max_datagram} B has no room for fragment data")
    count = -(-len(message) // chunk)
    if count > 0xFFFF:
        raise ValueError(f"message of {len(message)} B needs {count} fragments, over 65535")
    flags, key_id = (FLAG_FRAGMENT | FLAG_SIGNED, keyring.active) if keyring is not None else (FLAG_FRAGMENT, 0)
    head = (MAGIC, VERSION, flags, source_id)
    tail = (count, key_id, message_id & 0xFFFFFFFF, len(message))
    parts = [
        FRAGMENT_HEADER.pack(*head, index, *tail) + message[index * chunk : (index + 1) * chunk]
        for index in range(count)
    ]
    if keyring is not None:
        parts = [part + keyring.sign_fragment(part) for part in parts]
    return parts


def is_fragment(datagram: bytes) -> bool:
    return len(datagram) > 3 and datagram[3] & FLAG_FRAGMENT != 0


@dataclass
class _Partial:
    total_len: int
    count: int
    first_ns: int
    parts: dict[int, bytes] = field(default_factory=dict)
    received: int = 0


@dataclass
class ReassemblyLimits:
    timeout_ns: int = 500_000_000
    max_message_bytes: int = 256 * 1024
    max_partials_per_source: int = 8
    max_bytes_per_source: int = 1024 * 1024
    max_sources: int = 64
    # All sources together: the per-source bounds alone would let 64 sources pin 64 MiB.
    max_total_bytes: int = 4 * 1024 * 1024


class _Fragment(NamedTuple):
    """One fragment that passed every check that needs no reassembly state."""

    source_id: int
    part: int  # this fragment's index
    part_count: int
    message_id: int
    total_len: int
    data: bytes


class Reassembler:
    """Collects fragments into messages. Duplicates and reordering are fine; a message with a
    lost fragment is dropped whole once ``timeout_ns`` has passed since its first fragment.

    ``keyring=None`` is the unsigned mode: fragments need no tag (a tag is stripped unverified).
    With a keyring, each fragment's tag is verified before it touches any state.
    """

    def __init__(self, limits: ReassemblyLimits | None = None, keyring: Keyring | None = None) -> None:
        self.limits = limits or ReassemblyLimits()
        self.keyring = keyring
        # source -> message_id -> partial; both ordered oldest first for eviction.
        self._sources: OrderedDict[int, OrderedDict[int, _Partial]] = OrderedDict()
        self._bytes: dict[int, int] = {}
        self._total = 0  # sum of self._bytes
        # Every partial by arrival of its first fragment, which is deadline order: expiry pops
        # from the front and costs nothing per source or partial that has not expired.
        self._ages: OrderedDict[tuple[int, int], _Partial] = OrderedDict()
        self.dropped: list[ProtocolError] = []

    def feed(self, datagram: bytes, now_ns: int) -> bytes | None:
        """Add one fragment; return the whole message when it completes, else None.

        Raises ProtocolError for a malformed or unauthentic fragment, before it changes
        anything. Messages dropped for timeout or memory bounds are appended to
        :attr:`dropped` for the caller to count.
        """
        frag = self._check(datagram)
        self.expire(now_ns)
        source_id, message_id, total_len = frag.source_id, frag.message_id, frag.total_len
        partials = self._partials_of(source_id)
        partial = partials.get(message_id)
        if partial is None:
            partial = _Partial(total_len, frag.part_count, now_ns)
            partials[message_id] = partial
            self._ages[(source_id, message_id)] = partial
            self._enforce_source_bounds(source_id, partials, total_len)
            self._enforce_total_bound(source_id)
        elif partial.total_len != total_len or partial.count != frag.part_count:
            raise ProtocolError(Reason.BAD_FRAGMENT, "fragment disagrees with earlier ones", source_id)
        if frag.part in partial.parts:
            return None  # duplicate
        if partial.received + len(frag.data) > total_len:
            self._discard(source_id, message_id)
            raise ProtocolError(Reason.BAD_FRAGMENT, f"fragments exceed the declared {total_len} B", source_id)
        partial.parts[frag.part] = frag.data
        partial.received += len(frag.data)
        if len(partial.parts) < partial.count:
            return None
        self._discard(source_id, message_id)
        if partial.received != total_len:
            raise ProtocolError(Reason.BAD_FRAGMENT, f"reassembled {partial.received} B of {total_len}", source_id)
        return b"".join(partial.parts[i] for i in range(partial.count))

    def _check(self, datagram: bytes) -> _Fragment:
        """Framing, then bounds, then the tag: everything decidable from this datagram alone."""
        size = len(datagram)
        if size <= FRAGMENT_HEADER_BYTES:
            raise ProtocolError(Reason.TRUNCATED, "fragment shorter than its header")
        magic, version, flags, source_id, index, count, key_id, message_id, total_len = FRAGMENT_HEADER.unpack_from(
            datagram
        )
        if magic != MAGIC:
            raise ProtocolError(Reason.BAD_MAGIC)
        if version != VERSION:
            raise ProtocolError(Reason.BAD_VERSION, f"version {version}", source_id)
        if flags not in FRAGMENT_FLAGS or count < 2 or index >= count:
            raise ProtocolError(Reason.BAD_FRAGMENT, f"flags {flags:#x}, index {index} of {count}", source_id)
        # A message over the per-source or total bound could never be held within it (eviction
        # keeps the newest partial), so it is refused like one over the message limit.
        limits = self.limits
        if total_len > min(limits.max_message_bytes, limits.max_bytes_per_source, limits.max_total_bytes):
            raise ProtocolError(Reason.OVERSIZED, f"fragmented message of {total_len} B", source_id)
        if count > total_len:
            raise ProtocolError(Reason.BAD_FRAGMENT, f"{count} fragments for {total_len} B", source_id)
        end = self._authenticate(datagram, flags, key_id, source_id)
        return _Fragment(source_id, index, count, message_id, total_len, datagram[FRAGMENT_HEADER_BYTES:end])

    def _authenticate(self, datagram: bytes, flags: int, key_id: int, source_id: int) -> int:
        """Verify the tag as the mode asks; return where the fragment's data ends."""
        size = len(datagram)
        if not flags & FLAG_SIGNED:
            if self.keyring is not None:
                raise ProtocolError(Reason.UNSIGNED, "fragment", source_id)
            return size
        end = size - FRAGMENT_TAG_BYTES
        if end <= FRAGMENT_HEADER_BYTES:
            raise ProtocolError(Reason.TRUNCATED, "fragment without room for its tag", source_id)
        if self.keyring is not None:
            if key_id not in self.keyring.keys:
                raise ProtocolError(Reason.UNKNOWN_KEY, f"fragment key id {key_id}", source_id)
            view = memoryview(datagram)
            if not self.keyring.verify_fragment(key_id, view[:end], view[end:]):
                raise ProtocolError(Reason.BAD_MAC, "fragment", source_id)
        return end

    def _discard(self, source_id: int, message_id: int) -> None:
        partials = self._sources[source_id]
        partial = partials.pop(message_id)
        del self._ages[(source_id, message_id)]
        self._bytes[source_id] -= partial.total_len
        self._total -= partial.total_len
        if not partials:
            del self._sources[source_id]
            del self._bytes[source_id]

    def expire(self, now_ns: int) -> None:
        """Drop partial messages older than the timeout (recorded in :attr:`dropped`)."""
        deadline = now_ns - self.limits.timeout_ns
        ages = self._ages
        while ages:
            (source_id, message_id), oldest = next(iter(ages.items()))
            if oldest.first_ns > deadline:
                break
            self._discard(source_id, message_id)
            self.dropped.append(ProtocolError(Reason.FRAGMENT_TIMEOUT, f"message {message_id}", source_id))

    def next_expiry_ns(self) -> int | None:
        """When the oldest incomplete message times out (the clock of ``feed``'s ``now_ns``);
        None when nothing is pending."""
        if not self._ages:
            return None
        return next(iter(self._ages.values())).first_ns + self.limits.timeout_ns

    def pending(self) -> int:
        return len(self._ages)

    def held_bytes(self) -> int:
        """Bytes reserved for incomplete messages: their declared ``total_len``, summed."""
        return self._total

    def _partials_of(self, source_id: int) -> OrderedDict[int, _Partial]:
        partials = self._sources.get(source_id)
        if partials is None:
            if len(self._sources) >= self.limits.max_sources:
                evicted_source = next(iter(self._sources))
                for message_id in list(self._sources[evicted_source]):
                    self._evict(evicted_source, message_id)
            partials = self._sources[source_id] = OrderedDict()
            self._bytes[source_id] = 0
        else:
            self._sources.move_to_end(source_id)
        return partials

    def _enforce_source_bounds(self, source_id: int, partials: OrderedDict[int, _Partial], new_bytes: int) -> None:
        # Memory is reserved for the declared total up front so a source can't exceed its bound.
        self._bytes[source_id] += new_bytes
        self._total += new_bytes
        limits = self.limits
        while len(partials) > 1 and (
            len(partials) > limits.max_partials_per_source or self._bytes[source_id] > limits.max_bytes_per_source
        ):
            self._evict(source_id, next(iter(partials)))

    def _enforce_total_bound(self, new_source: int) -> None:
        """Over the total, evict the oldest partial of the source holding the most (of equals,
        the least recently active), so one busy source cannot push out a light one's message.
        The partial just started (the newest of ``new_source``) is never the one evicted; it
        fits the total alone (``_check``), so the loop ends."""
        sources = self._sources
        while self._total > self.limits.max_total_bytes:
            # max() returns the first of equals, and sources are kept least recently active first.
            candidates = (s for s in sources if s != new_source or len(sources[s]) > 1)
            heaviest = max(candidates, key=self._bytes.__getitem__)
            self._evict(heaviest, next(iter(sources[heaviest])))

    def _evict(self, source_id: int, message_id: int) -> None:
        self._discard(source_id, message_id)
        self.dropped.append(ProtocolError(Reason.FRAGMENT_EVICTED, f"message {message_id}", source_id))
