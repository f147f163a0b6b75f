"""Sans-IO replay protection, in the manner of MAVLink 2 signing and IPsec's sliding window.

Per stream (source id, channel) a receiver keeps the highest sequence number accepted and a
64-message bitmap behind it. Publishers start their sequence at their wall clock in
microseconds, so a restarted publisher continues above where it left off. A message is accepted
iff it is new to the window *and* its ``t_pub_ns`` lies within the freshness window of the
receiver's shared clock; the second rule stops replays to a receiver that has no state yet, once
that receiver is synchronised (before then, for its first ~0.5 s, it cannot judge freshness).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

from protocol.errors import ProtocolError, Reason
from protocol.fastpath import native

WINDOW = 64
RESTART_JUMP = 1_000_000
_FULL = (1 << WINDOW) - 1


@dataclass
class ReplayLimits:
    max_age_ns: int = 2_000_000_000
    max_future_ns: int = 2_000_000_000
    max_streams: int = 4096


class _Stream:
    __slots__ = ("first", "highest", "seen")

    def __init__(self, seq: int) -> None:
        self.first = seq  # seqs below it were never counted as lost (this receiver joined later)
        self.highest = seq
        self.seen = 1  # bit i set: highest - i was accepted


class PythonReplayGuard:
    """Accepts each (source, channel, seq) once, and only while fresh.

    The reference; :data:`ReplayGuard` is the C twin of it where the fast path is built."""

    def __init__(self, limits: ReplayLimits | None = None) -> None:
        self.limits = limits or ReplayLimits()
        self._streams: OrderedDict[tuple[int, str], _Stream] = OrderedDict()

    def check(self, source_id: int, channel: str, seq: int, t_pub_ns: int, now_ns: int | None) -> int:
        """Accept or raise ProtocolError(REPLAY/STALE/FUTURE).

        ``now_ns=None`` skips the freshness test (the receiver's clock is not yet synchronised).
        Returns how many messages this one shows as lost (a gap ahead of the window), or -1 when
        a late message fills a hole counted as lost before, so callers can keep loss statistics.
        """
        if now_ns is not None:
            if t_pub_ns < now_ns - self.limits.max_age_ns:
                raise ProtocolError(Reason.STALE, f"published {(now_ns - t_pub_ns) / 1e9:.3f} s ago", source_id)
            if t_pub_ns > now_ns + self.limits.max_future_ns:
                raise ProtocolError(Reason.FUTURE, f"published {(t_pub_ns - now_ns) / 1e9:.3f} s ahead", source_id)
        key = (source_id, channel)
        streams = self._streams
        stream = streams.get(key)
        if stream is not None:
            # Least recently used goes first when the table is full, never an active stream.
            streams.move_to_end(key)
        else:
            if len(self._streams) >= self.limits.max_streams:
                self._streams.popitem(last=False)
            self._streams[key] = _Stream(seq)
            return 0
        ahead = seq - stream.highest
        if ahead > 0:
            stream.seen = ((stream.seen << ahead) | 1) & _FULL if ahead < WINDOW else 1
            stream.highest = seq
            # A restarted publisher resumes at its wall clock in microseconds: a jump of a
            # million or more is a new life of the source, not a million lost messages.
            return ahead - 1 if ahead <= RESTART_JUMP else 0
        behind = -ahead
        if behind >= WINDOW:
            raise ProtocolError(Reason.REPLAY, f"seq {seq} is {behind} behind", source_id)
        bit = 1 << behind
        if stream.seen & bit:
            raise ProtocolError(Reason.REPLAY, f"seq {seq} already seen", source_id)
        stream.seen |= bit
        # Only holes above the first seq seen were reported as lost; filling one below it (a
        # message reordered around this receiver's first) must not drive loss counts negative.
        return -1 if seq > stream.first else 0

    def forget(self, source_id: int, channel: str) -> None:
        self._streams.pop((source_id, channel), None)

    def __len__(self) -> int:
        """Streams tracked now (at most ``limits.max_streams``)."""
        return len(self._streams)


ReplayGuard: type[PythonReplayGuard]
if native is not None:

    class _NativeReplayGuard(native.ReplayGuard):  # type: ignore[misc,name-defined]
        """PythonReplayGuard's rules and errors in C (protocol/_fastpath.c)."""

        __slots__ = ()

        def __init__(self, limits: ReplayLimits | None = None) -> None:
            super().__init__(limits or ReplayLimits())

    ReplayGuard = _NativeReplayGuard  # type: ignore[assignment]
else:
    ReplayGuard = PythonReplayGuard
