"""Sans-IO replay protection, in the manner of MAVLink 2 signing and IPsec's sliding window.

Per stream (source id, channel) a receiver keeps the highest sequence number accepted and a
64-message bitmap behind it. Publishers start their sequence at their wall clock in
microseconds, so a restarted publisher continues above where it left off. A message is accepted
iff it is new to the window *and* its ``t_pub_ns`` lies within the freshness window of the
receiver's shared clock; the second rule stops replays to a receiver that has no state yet, once
that receiver is synchronised (before then, for its first ~0.5 s, it cannot judge freshness).

A publisher restarted after its wall clock stepped back numbers below its previous life, which
the window alone would refuse for good. So a stream also keeps the latest ``t_pub_ns`` it
accepted. A message the window refuses, found fresh by a synchronised receiver and published
after every message accepted so far, cannot be any of them: it starts the source's new life (the
stream restarts at it), and messages published before it are refused from then on, so the old
life's higher numbers cannot be replayed into the new one. Soundness needs no margin on "after",
and none is taken, so a quick restart is followed at once.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

from protocol.errors import ProtocolError, Reason
from protocol.fastpath import native

WINDOW = 64
RESTART_JUMP = 1_000_000
_FULL = (1 << WINDOW) - 1
NO_FLOOR = -(1 << 63)  # t_pub_ns is an int64 on the wire: nothing is published before this


@dataclass
class ReplayLimits:
    max_age_ns: int = 2_000_000_000
    max_future_ns: int = 2_000_000_000
    max_streams: int = 4096


class _Stream:
    __slots__ = ("first", "floor", "highest", "newest", "seen")

    def __init__(self, seq: int, t_pub_ns: int, floor: int = NO_FLOOR) -> None:
        self.first = seq  # seqs below it were never counted as lost (this receiver joined later)
        self.highest = seq
        self.seen = 1  # bit i set: highest - i was accepted
        self.newest = t_pub_ns  # the latest t_pub_ns accepted: no replay is published after it
        self.floor = floor  # t_pub_ns of the source's current life's first message seen


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
            self._streams[key] = _Stream(seq, t_pub_ns)
            return 0
        if t_pub_ns < stream.floor:
            raise ProtocolError(Reason.REPLAY, f"seq {seq} was published before its source restarted", source_id)
        ahead = seq - stream.highest
        if ahead > 0:
            stream.seen = ((stream.seen << ahead) | 1) & _FULL if ahead < WINDOW else 1
            stream.highest = seq
            stream.newest = max(stream.newest, t_pub_ns)
            # A restarted publisher resumes at its wall clock in microseconds: a jump of a
            # million or more is a new life of the source, not a million lost messages.
            return ahead - 1 if ahead <= RESTART_JUMP else 0
        behind = -ahead
        if behind >= WINDOW or stream.seen >> behind & 1:
            if now_ns is None or t_pub_ns <= stream.newest:
                detail = f"seq {seq} is {behind} behind" if behind >= WINDOW else f"seq {seq} already seen"
                raise ProtocolError(Reason.REPLAY, detail, source_id)
            # Fresh, and published after everything accepted here, so none of it: the source
            # restarted below its old numbers (its wall clock stepped back). Follow the new life.
            streams[key] = _Stream(seq, t_pub_ns, floor=t_pub_ns)
            return 0
        stream.seen |= 1 << behind
        stream.newest = max(stream.newest, t_pub_ns)
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

    ReplayGuard = _NativeReplayGuard
else:
    ReplayGuard = PythonReplayGuard
