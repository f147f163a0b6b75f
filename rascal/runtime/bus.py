"""Publish/subscribe over a transport: typed messages, signing, replay protection, command
authority, statistics.

A Bus is what a module holds. It owns the codec, the reassembler and the replay guard (all
sans-IO, in ``protocol``) and drives the transport. Everything a peer can get wrong raises
ProtocolError inside :meth:`Bus.poll`, which counts it per source and reason and drops the
datagram; the module never sees it.

Command authority (protocol/authority.py): a bus whose keyring holds this source's signing key
signs what it publishes on a governed channel; a bus whose keyring holds an authority table (a
module key file) accepts a governed message only with a valid signature by a source with
authority on its channel. Nodes with the master file (operator tools, tests) sign as whichever
source they are and, trusted, enforce nothing unless given the deployment's authority
(:meth:`Bus.enforce`: the supervisor does, an operator tool told the deployment does).
"""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from protocol import channels
from protocol.auth import Keyring, default_keyring
from protocol.authority import GOVERNED, VERIFIED_ON_RECEIPT, Authority, needs_signature
from protocol.codec import (
    FLAG_FRAGMENT,
    FLAG_SIGNATURE,
    FLAGS_AT,
    Codec,
    Envelope,
    Opened,
    check_channel,
    signed_part,
    unpack_body,
)
from protocol.errors import ProtocolError, Reason
from protocol.fastpath import native
from protocol.framing import DEFAULT_MAX_DATAGRAM_BYTES, Reassembler, ReassemblyLimits, fragment, new_message_id
from protocol.replay import ReplayGuard, ReplayLimits
from protocol.schema import info_for_class, info_for_id
from protocol.transport import Transport, open_transport
from rascal.runtime.clock import Clock, SharedClock
from rascal.runtime.rtdb import Latest

M = TypeVar("M")
_new = tuple.__new__
Handler = Callable[[Any, Envelope], None]
RawHandler = Callable[[Opened, bytes, int], None]

MAX_REJECT_SOURCES = 256
MAX_CHANNELS = 1024
LATENCY_SAMPLES = 1024
ARRIVAL_SAMPLES = 2048
# A poll that waits for an incomplete message's timeout waits this much longer, so the expiry
# after the wait finds it due even if the wait's rounding ends it a little early.
EXPIRY_SLACK_S = 0.001
# Channels whose freshness and uniqueness the time protocol judges itself (a reply counts only
# if it echoes an outstanding request's nonce, once): an unsynchronised client must be able to
# talk to the master, and the master to it, also after a restart with its wall clock stepped
# back, which puts its sequence numbers behind the master's replay window for good.
REPLAY_EXEMPT = frozenset({channels.TIME_SYNC})
# Channels stamped on arrival by the kernel: time sync, whose accuracy the asymmetric wake-up
# latency of the two ends (~50-100 us on loopback) would otherwise limit.
KERNEL_TIMESTAMPED = frozenset({channels.TIME_SYNC})


@dataclass
class ChannelStats:
    """Receive statistics of one channel on this node."""

    messages: int = 0
    bytes: int = 0
    lost: int = 0
    sources: set[int] = field(default_factory=set)
    arrivals_ns: deque[int] = field(default_factory=lambda: deque(maxlen=ARRIVAL_SAMPLES))
    latencies_ns: deque[int] = field(default_factory=lambda: deque(maxlen=LATENCY_SAMPLES))
    type_id: int = 0
    last_source: int = -1

    def rate_hz(self, now_ns: int, window_ns: int = 2_000_000_000) -> float:
        """Messages per second over the last ``window_ns``: one over the mean interval between
        them (unbiased for a steady stream, as `ros2 topic hz` measures), falling once the
        channel has been silent for over two of its intervals (0 when silent that long)."""
        recent = [t for t in self.arrivals_ns if t >= now_ns - window_ns]
        if len(recent) < 2:
            return 0.0
        intervals = len(recent) - 1
        span = recent[-1] - recent[0]
        if now_ns - recent[-1] > 2 * span / intervals:
            span = now_ns - recent[0]
        return intervals * 1e9 / span if span > 0 else 0.0

    def loss_fraction(self) -> float:
        expected = self.messages + self.lost
        return self.lost / expected if expected else 0.0


class _Route:
    """Everything the receive path needs for one subscribed channel, found with one lookup."""

    __slots__ = ("channel", "decode", "governed", "handlers", "latest", "plan", "replay_exempt", "type_id", "wake")

    def __init__(self, channel: str, type_id: int, governed: bool) -> None:
        self.channel = channel
        self.type_id = type_id
        self.replay_exempt = channel in REPLAY_EXEMPT
        self.governed = governed  # its messages' signatures are checked on receipt (in Python)
        info = info_for_id(type_id)
        self.decode = info.decode
        self.plan = info.plan
        self.handlers: list[Handler] = []
        self.latest: list[Latest[Any]] = []
        self.wake = False  # a handler wants each message as it comes; latest values wait for a poll's end


class Bus:
    """One node's connection to the bus.

    ``keyring=None`` is the unsigned mode and must be asked for explicitly with
    ``signing=False`` in :meth:`open`; the default signs and verifies with the deployment key.
    """

    def __init__(
        self,
        transport: Transport,
        source_id: int,
        keyring: Keyring | None,
        clock: Clock,
        *,
        max_datagram_bytes: int = DEFAULT_MAX_DATAGRAM_BYTES,
        replay_limits: ReplayLimits | None = None,
        reassembly_limits: ReassemblyLimits | None = None,
    ) -> None:
        if not 0 < source_id < 0x10000:
            raise ValueError(f"source_id {source_id} out of range 1..65535")
        self.transport = transport
        self.source_id = source_id
        self.clock = clock
        self.max_datagram_bytes = max_datagram_bytes
        reassembly_limits = reassembly_limits or ReassemblyLimits()
        self.codec = Codec(keyring, reassembly_limits.max_message_bytes)
        # None: this node cannot sign as its source (a legacy key file, or another source's).
        self.signer = keyring.signer(source_id) if keyring is not None else None
        self._signing = keyring is not None and not keyring.legacy
        # None: this node enforces no authority (a master or legacy key file, or unsigned),
        # unless told to (enforce).
        self.authority = keyring.authority if keyring is not None else None
        self.replay = ReplayGuard(replay_limits)
        self.reassembler = Reassembler(reassembly_limits, keyring)
        self.stats: dict[str, ChannelStats] = {}
        self.rejects: Counter[tuple[int | None, str]] = Counter()
        self._subs: dict[str, _Route] = {}
        self._raw_handlers: list[RawHandler] = []
        self._next_seq: dict[str, int] = {}
        self._channel_bytes: dict[str, bytes] = {}
        # Start sequences at wall-clock microseconds so a restarted publisher continues above
        # its previous life and receivers' replay windows accept it (see protocol.replay).
        self._seq_base = time.time_ns() // 1000
        self._check_freshness = clock.synced
        # The C twin of _accept (protocol/_fastpath.c), for every plain datagram; None: Python only.
        self._receiver = (
            native.Receiver(self.codec.verifying_macs, self.codec.max_message_bytes, self._subs, self.replay, Envelope)
            if native is not None and isinstance(self.replay, native.ReplayGuard)
            else None
        )

    @classmethod
    def open(
        cls,
        url: str | None = None,
        *,
        source_id: int,
        clock: Clock | None = None,
        keyring: Keyring | None = None,
        signing: bool = True,
        **options: Any,
    ) -> Bus:
        """Open a bus by URL (``None``: ``$RASCAL_BUS_URL`` or the loopback default)."""
        if signing:
            keyring = keyring or default_keyring()
        elif keyring is not None:
            raise ValueError("signing=False and a keyring contradict each other")
        return cls(open_transport(url), source_id, keyring, clock or SharedClock(), **options)

    # -- publishing ---------------------------------------------------------------------------

    def publish(self, channel: str, msg: Any, t_meas_ns: int | None = None) -> int:
        """Sign and send ``msg`` on ``channel``; returns its sequence number."""
        seq, data = self.encode(channel, msg, t_meas_ns)
        self.send_raw(channel, data)
        return seq

    def encode(self, channel: str, msg: Any, t_meas_ns: int | None = None) -> tuple[int, bytes]:
        """Number, stamp and sign ``msg`` for ``channel`` without sending it (for callers that
        must timestamp the send itself); returns (seq, message bytes)."""
        channel_bytes = self._channel_bytes.get(channel)
        if channel_bytes is None:
            channel_bytes = self._declare(channel, type(msg))
        seq = self._next_seq.get(channel, self._seq_base)
        self._next_seq[channel] = seq + 1
        signer = None
        if self._signing and channel in GOVERNED and needs_signature(channel, msg):
            signer = self.signer
            if signer is None:
                raise PermissionError(
                    f"{channel}: this key file holds no signing key for source {self.source_id}, "
                    "so every node with an authority table would reject the message"
                )
        t_pub_ns = self.clock.now_ns()
        data = self.codec.encode(
            channel_bytes, msg, self.source_id, seq, t_pub_ns if t_meas_ns is None else t_meas_ns, t_pub_ns, signer
        )
        return seq, data

    def _declare(self, channel: str, msg_type: type) -> bytes:
        channels.type_for(channel, msg_type)
        info_for_class(msg_type)
        channel_bytes = self._channel_bytes[channel] = check_channel(channel)
        return channel_bytes

    def send_raw(self, channel: str, data: bytes) -> None:
        """Send encoded message bytes, fragmenting them if they exceed one datagram."""
        if len(data) <= self.max_datagram_bytes:
            self.transport.send(channel, data)
        else:
            parts = fragment(data, self.source_id, new_message_id(), self.max_datagram_bytes, self.codec.keyring)
            for part in parts:
                self.transport.send(channel, part)

    # -- subscribing --------------------------------------------------------------------------

    def subscribe(self, channel: str, handler: Handler, msg_type: type | None = None, *, wake: bool = True) -> None:
        """Call ``handler(msg, envelope)`` for every accepted message on ``channel``: as it
        arrives (a :meth:`poll` returns for it), or with ``wake=False`` when the poll's wait ends."""
        self._subscription(channel, msg_type, wake).handlers.append(handler)

    def latest(self, channel: str, max_age_ns: int, msg_type: type | None = None) -> Latest[Any]:
        """A latest-value entry for ``channel`` with temporal validity ``max_age_ns``. Its
        messages do not wake a :meth:`poll`: periodic work reads it after the wait, and only
        then are they received (a module is not woken at 100 Hz for a value it reads at 25)."""
        entry: Latest[Any] = Latest(channel, max_age_ns)
        self._subscription(channel, msg_type, wake=False).latest.append(entry)
        return entry

    def subscribe_raw(self, handler: RawHandler, *, wake: bool = True) -> None:
        """Every authenticated message on every channel, undecoded: for bus tools and loggers.
        ``handler(opened, message_bytes, recv_ns)``; ``wake=False`` as for :meth:`subscribe`
        (a recorder has no hurry: it takes what came when its periodic work is due)."""
        self._raw_handlers.append(handler)
        self.transport.listen_all(wake)

    def _subscription(self, channel: str, msg_type: type | None, wake: bool) -> _Route:
        resolved = channels.type_for(channel, msg_type)
        type_id = info_for_class(resolved).type_id
        sub = self._subs.get(channel)
        new = sub is None
        if sub is None:
            check_channel(channel)
            governed = self.authority is not None and channel in VERIFIED_ON_RECEIPT
            sub = self._subs[channel] = _Route(channel, type_id, governed)
        elif sub.type_id != type_id:
            raise TypeError(f"channel {channel} is already subscribed with another type")
        if new or (wake and not sub.wake):
            sub.wake = sub.wake or wake
            self.transport.listen(channel, kernel_timestamps=channel in KERNEL_TIMESTAMPED, wake=sub.wake)
        return sub

    # -- receiving ----------------------------------------------------------------------------

    def poll(self, timeout_s: float = 0.0, budget: int = 10_000) -> int:
        """Wait up to ``timeout_s`` for traffic, then handle what is waiting (at most ``budget``
        datagrams, so a flood cannot starve the caller's periodic work). Returns datagrams seen.
        Returns early when an incomplete fragmented message times out, to free it."""
        expiry_ns = self.reassembler.next_expiry_ns()
        if expiry_ns is not None:
            wait_s = max(0.0, (expiry_ns - self.clock.local_ns()) / 1e9) + EXPIRY_SLACK_S
            timeout_s = min(timeout_s, wait_s)
        handled = self.transport.receive(self._on_datagram, timeout_s, budget)
        self._check_freshness = self.clock.synced
        if self.reassembler.pending():  # also when no fragment comes to notice the timeout
            self.reassembler.expire(self.clock.local_ns())
        if self.reassembler.dropped:
            for error in self.reassembler.dropped:
                self._count_reject(error)
            self.reassembler.dropped.clear()
        return handled

    def _on_datagram(self, data: bytes, kernel_realtime_ns: int = 0) -> None:
        # The hot path (80 k msg/s), handlers first: statistics are bookkeeping and wait until
        # the message is delivered.
        clock = self.clock
        recv_local_ns = clock.from_realtime(kernel_realtime_ns) if kernel_realtime_ns else clock.local_ns()
        recv_ns = clock.to_shared(recv_local_ns)
        if len(data) <= FLAGS_AT:  # too short to say even whether it is a fragment
            self._count_reject(ProtocolError(Reason.TRUNCATED, f"{len(data)} B"))
            return
        try:
            accepted = None
            if self._receiver is not None and not self._raw_handlers and not data[FLAGS_AT] & FLAG_FRAGMENT:
                # Raises bad_mac for a wrong tag, so Python never computes it again; None leaves
                # the datagram to Python: refused before its tag, or authentic (and checked again
                # there, a cost only key holders can cause) but governed or of another layout.
                accepted = self._receiver.accept(data, recv_ns, recv_local_ns, self._check_freshness)
                if accepted is False:
                    return  # shares a port with a channel we want; not ours
            if accepted is None:
                accepted = self._accept(data, recv_ns, recv_local_ns)
                if accepted is None:
                    return
        except ProtocolError as error:
            self._count_reject(error)
            return
        route, msg, envelope, lost = accepted
        if msg is not None and route is not None:  # a message is decoded only for a route
            for latest in route.latest:
                latest.update(msg, envelope)
            for handler in route.handlers:
                handler(msg, envelope)
        stats = self.stats.get(envelope.channel)
        if stats is None:  # the channel count is bounded: by our subscriptions, or in _accept
            stats = self.stats[envelope.channel] = ChannelStats(type_id=envelope.type_id)
        stats.messages += 1
        stats.bytes += envelope.size
        if lost:
            stats.lost += lost
        if envelope.source_id != stats.last_source:
            stats.sources.add(envelope.source_id)
            stats.last_source = envelope.source_id
        stats.arrivals_ns.append(recv_ns)
        stats.latencies_ns.append(recv_ns - envelope.t_pub_ns)

    def _accept(self, data: bytes, recv_ns: int, recv_local_ns: int) -> tuple[_Route | None, Any, Envelope, int] | None:
        """Reassemble, open, check and decode one datagram: (route, msg or None, envelope, lost),
        or None when it completes nothing or is not ours. Raw handlers see it here; ProtocolError
        for anything wrong with it. Receiver.accept is the C twin of the common case."""
        if data[FLAGS_AT] & FLAG_FRAGMENT:
            whole = self.reassembler.feed(data, recv_local_ns)
            if whole is None:
                return None
            data = whole
        type_id, source_id, seq, t_meas_ns, t_pub_ns, channel, body = opened = self.codec.open(data)
        route = self._subs.get(channel)
        if route is None and not self._raw_handlers:
            return None  # shares a port with a channel we want; not ours
        signed = signed_part(data) if data[3] & FLAG_SIGNATURE else None
        if self.authority is not None and channel in VERIFIED_ON_RECEIPT:
            # Before the replay window: a forgery must leave no trace in its victim's stream.
            self.authority.check(channel, source_id, signed)
        if channel in REPLAY_EXEMPT:
            lost = 0
        else:
            lost = self.replay.check(source_id, channel, seq, t_pub_ns, recv_ns if self._check_freshness else None)
        msg = None
        if route is not None:
            if type_id != route.type_id:
                raise ProtocolError(Reason.WRONG_TYPE, f"type {type_id} on {channel}", source_id)
            try:
                msg = route.decode(unpack_body(body, source_id))
            except ProtocolError as error:
                error.source_id = source_id
                raise
        if channel not in self.stats and len(self.stats) >= MAX_CHANNELS:
            # Only reachable unsigned, or by a key holder gone mad: keep memory bounded.
            raise ProtocolError(Reason.BAD_HEADER, "too many channels", source_id)
        for raw_handler in self._raw_handlers:
            raw_handler(opened, data, recv_ns)
        envelope = _new(
            Envelope, (channel, source_id, seq, t_meas_ns, t_pub_ns, recv_ns, type_id, len(data), recv_local_ns, signed)
        )
        return route, msg, envelope, lost

    def enforce(self, authority: Authority) -> None:
        """Enforce ``authority`` from now on: for a node with the master file that knows its
        deployment (the supervisor; an operator tool told the deployment)."""
        self.authority = authority
        for route in self._subs.values():
            route.governed = route.channel in VERIFIED_ON_RECEIPT

    def authorized(self, envelope: Envelope) -> bool:
        """Whether a message on a channel whose handler verifies it (protocol.authority.
        VERIFIED_BY_HANDLER: time-sync replies) is by a source with authority: asked by the
        handler for the messages it means to use. A refusal is counted as a reject."""
        if self.authority is None:
            return True
        try:
            self.authority.check(envelope.channel, envelope.source_id, envelope.signed)
        except ProtocolError as error:
            self._count_reject(error)
            return False
        return True

    def _count_reject(self, error: ProtocolError) -> None:
        key = (error.source_id, error.reason.value)
        if key not in self.rejects and len(self.rejects) >= MAX_REJECT_SOURCES:
            # A spoofer cycling source ids must not grow this without bound.
            key = (None, error.reason.value)
        self.rejects[key] += 1

    def rejected_total(self) -> int:
        return sum(self.rejects.values())

    def close(self) -> None:
        self.transport.close()
