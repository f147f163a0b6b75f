"""Sans-IO fragmentation and reassembly of messages larger than one datagram.

Fragment datagram (little-endian; SPEC.md is normative)::

    magic "RB" | version u8 | flags u8 (FRAGMENT) | source_id u16 | index u16 | count u16 |
    reserved u16 | message_id u32 | total_len u32 | data

Fragments are not authenticated one by one: the reassembled message carries the MAC and is
verified as a whole. Because of that, everything here is bounded (per source and overall), so
unauthenticated fragments can waste at most a fixed amount of memory.
"""

from __future__ import annotations

import struct
from collections import OrderedDict
from dataclasses import dataclass, field

from protocol.codec import FLAG_FRAGMENT, MAGIC, VERSION
from protocol.errors import ProtocolError, Reason

FRAGMENT_HEADER = struct.Struct("<2sBBHHHHII")
FRAGMENT_HEADER_BYTES = FRAGMENT_HEADER.size  # 20
DEFAULT_MAX_DATAGRAM_BYTES = 1400


def fragment(
    message: bytes, source_id: int, message_id: int, max_datagram: int = DEFAULT_MAX_DATAGRAM_BYTES
) -> list[bytes]:
    """Split ``message`` into fragment datagrams of at most ``max_datagram`` bytes each.

    A message that fits in one datagram is returned unchanged, as the only element.
    """
    if len(message) <= max_datagram:
        return [message]
    chunk = max_datagram - FRAGMENT_HEADER_BYTES
    count = -(-len(message) // chunk)
    if count > 0xFFFF:
        raise ValueError(f"message of {len(message)} B needs {count} fragments, over 65535")
    total = len(message)
    message_id &= 0xFFFFFFFF
    return [
        FRAGMENT_HEADER.pack(MAGIC, VERSION, FLAG_FRAGMENT, source_id, index, count, 0, message_id, total)
        + message[index * chunk : (index + 1) * chunk]
        for index in range(count)
    ]


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


class Reassembler:
    """Collects fragments into messages. Duplicates and reordering are fine; a message with a
    lost fragment is dropped whole once ``timeout_ns`` has passed since its first fragment."""

    def __init__(self, limits: ReassemblyLimits | None = None) -> None:
        self.limits = limits or ReassemblyLimits()
        # source -> message_id -> partial; both ordered oldest first for eviction.
        self._sources: OrderedDict[int, OrderedDict[int, _Partial]] = OrderedDict()
        self._bytes: dict[int, int] = {}
        self.dropped: list[ProtocolError] = []

    def feed(self, datagram: bytes, now_ns: int) -> bytes | None:
        """Add one fragment; return the whole message when it completes, else None.

        Raises ProtocolError for a malformed fragment. Messages dropped for timeout or memory
        bounds are appended to :attr:`dropped` for the caller to count.
        """
        if len(datagram) <= FRAGMENT_HEADER_BYTES:
            raise ProtocolError(Reason.TRUNCATED, "fragment shorter than its header")
        magic, version, flags, source_id, index, count, _reserved, message_id, total_len = FRAGMENT_HEADER.unpack_from(
            datagram
        )
        if magic != MAGIC:
            raise ProtocolError(Reason.BAD_MAGIC)
        if version != VERSION:
            raise ProtocolError(Reason.BAD_VERSION, f"version {version}", source_id)
        if flags != FLAG_FRAGMENT or count < 2 or index >= count:
            raise ProtocolError(Reason.BAD_FRAGMENT, f"index {index} of {count}", source_id)
        # A message over the per-source bound could never be held within it (eviction keeps at
        # least the newest partial), so it is refused like one over the message limit.
        if total_len > min(self.limits.max_message_bytes, self.limits.max_bytes_per_source):
            raise ProtocolError(Reason.OVERSIZED, f"fragmented message of {total_len} B", source_id)
        if count > total_len:
            raise ProtocolError(Reason.BAD_FRAGMENT, f"{count} fragments for {total_len} B", source_id)
        data = datagram[FRAGMENT_HEADER_BYTES:]

        self.expire(now_ns)
        partials = self._partials_of(source_id)
        partial = partials.get(message_id)
        if partial is None:
            partial = _Partial(total_len, count, now_ns)
            partials[message_id] = partial
            self._enforce_source_bounds(source_id, partials, total_len)
        elif partial.total_len != total_len or partial.count != count:
            raise ProtocolError(Reason.BAD_FRAGMENT, "fragment disagrees with earlier ones", source_id)
        if index in partial.parts:
            return None  # duplicate
        if partial.received + len(data) > total_len:
            self._discard(source_id, message_id)
            raise ProtocolError(Reason.BAD_FRAGMENT, f"fragments exceed the declared {total_len} B", source_id)
        partial.parts[index] = data
        partial.received += len(data)
        if len(partial.parts) < count:
            return None
        self._discard(source_id, message_id)
        if partial.received != total_len:
            raise ProtocolError(Reason.BAD_FRAGMENT, f"reassembled {partial.received} B of {total_len}", source_id)
        return b"".join(partial.parts[i] for i in range(count))

    def _discard(self, source_id: int, message_id: int) -> None:
        partial = self._sources[source_id].pop(message_id)
        self._bytes[source_id] -= partial.total_len

    def expire(self, now_ns: int) -> None:
        """Drop partial messages older than the timeout (recorded in :attr:`dropped`)."""
        deadline = now_ns - self.limits.timeout_ns
        for source_id in list(self._sources):
            partials = self._sources[source_id]
            while partials:
                message_id, oldest = next(iter(partials.items()))
                if oldest.first_ns > deadline:
                    break
                del partials[message_id]
                self._bytes[source_id] -= oldest.total_len
                self.dropped.append(ProtocolError(Reason.FRAGMENT_TIMEOUT, f"message {message_id}", source_id))
            if not partials:
                del self._sources[source_id]
                del self._bytes[source_id]

    def pending(self) -> int:
        return sum(len(partials) for partials in self._sources.values())

    def _partials_of(self, source_id: int) -> OrderedDict[int, _Partial]:
        partials = self._sources.get(source_id)
        if partials is None:
            if len(self._sources) >= self.limits.max_sources:
                evicted_source, evicted = self._sources.popitem(last=False)
                del self._bytes[evicted_source]
                self.dropped.extend(
                    ProtocolError(Reason.FRAGMENT_EVICTED, f"message {mid}", evicted_source) for mid in evicted
                )
            partials = self._sources[source_id] = OrderedDict()
            self._bytes[source_id] = 0
        else:
            self._sources.move_to_end(source_id)
        return partials

    def _enforce_source_bounds(self, source_id: int, partials: OrderedDict[int, _Partial], new_bytes: int) -> None:
        # Memory is reserved for the declared total up front so a source can't exceed its bound.
        self._bytes[source_id] += new_bytes
        limits = self.limits
        while len(partials) > 1 and (
            len(partials) > limits.max_partials_per_source or self._bytes[source_id] > limits.max_bytes_per_source
        ):
            message_id, oldest = partials.popitem(last=False)
            self._bytes[source_id] -= oldest.total_len
            self.dropped.append(ProtocolError(Reason.FRAGMENT_EVICTED, f"message {message_id}", source_id))
