"""Both ends of the shared-time exchange, wired to a Bus (the estimator itself is sans-IO)."""

from __future__ import annotations

from collections import OrderedDict

from protocol import channels
from protocol.codec import Envelope
from protocol.messages import TimeSync, TimeSyncKind
from rascal.bus import Bus
from rascal.clock import SharedClock

OUTSTANDING_REQUESTS = 32


class TimeClient:
    """Asks the master for the time and feeds the answers to the clock's estimator.

    Only replies that echo the t1 of one of our own outstanding requests count, so replayed or
    foreign replies cannot steer the clock (the freshness window cannot protect this channel,
    since an unsynchronised node cannot judge freshness yet).
    """

    def __init__(self, bus: Bus, clock: SharedClock) -> None:
        self.bus = bus
        self.clock = clock
        # t1 as sent (the nonce the master echoes) -> local time just before the send.
        self._outstanding: OrderedDict[int, int] = OrderedDict()
        self.replies = 0
        bus.subscribe(channels.TIME_SYNC, self._on_time_sync)

    def request(self) -> None:
        nonce = self.clock.local_ns()
        _seq, data = self.bus.encode(channels.TIME_SYNC, TimeSync(TimeSyncKind.REQUEST, self.bus.source_id, nonce))
        # Stamp t1 right before the send, after encoding: encoding is slow when this process
        # wakes with cold caches and would otherwise sit in the outbound delay only, biasing
        # the offset by half of it (~40 us measured on loopback). After the send is no better:
        # the woken master can preempt us inside sendto.
        self._outstanding[nonce] = self.clock.local_ns()
        self.bus.send_raw(channels.TIME_SYNC, data)
        if len(self._outstanding) > OUTSTANDING_REQUESTS:
            self._outstanding.popitem(last=False)

    def _on_time_sync(self, msg: TimeSync, envelope: Envelope) -> None:
        if msg.kind != TimeSyncKind.REPLY or msg.client_source_id != self.bus.source_id:
            return
        sent_local_ns = self._outstanding.pop(msg.t1_local_ns, None)
        if sent_local_ns is None:
            return
        self.replies += 1
        self.clock.estimator.add_sample(sent_local_ns, msg.t2_master_ns, msg.t3_master_ns, envelope.recv_local_ns)


class TimeMaster:
    """Answers every time request with the master clock's receive and send times."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.answered = 0
        bus.subscribe(channels.TIME_SYNC, self._on_time_sync)

    def _on_time_sync(self, msg: TimeSync, envelope: Envelope) -> None:
        if msg.kind != TimeSyncKind.REQUEST:
            return
        reply = TimeSync(
            TimeSyncKind.REPLY, msg.client_source_id, msg.t1_local_ns, envelope.recv_ns, self.bus.clock.now_ns()
        )
        self.bus.publish(channels.TIME_SYNC, reply)
        self.answered += 1
