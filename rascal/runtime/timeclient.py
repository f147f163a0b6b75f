"""Both ends of the shared-time exchange, wired to a Bus (the estimator itself is sans-IO)."""

from __future__ import annotations

from collections import OrderedDict

from protocol import channels
from protocol.codec import Envelope
from protocol.messages import TimeSync, TimeSyncKind
from rascal.runtime.bus import Bus
from rascal.runtime.clock import SharedClock

OUTSTANDING_REQUESTS = 32
ENCODE_SMOOTHING = 8  # the master's mean reply encoding time: an exponential mean over ~8 replies
# Once the estimate has settled, one exchange per this long keeps it: the fit models the clock's
# drift, so its error grows by about 0.1 ppm of the gap (NTP clients poll every 64 s). Faster is
# costly, because every node hears every exchange and a multicast send delivers to each of them:
# at 0.5 s, time sync was half of the recorder's and an idle module's CPU (py-spy).
SETTLED_REQUEST_PERIOD_NS = 2_000_000_000
# ... and not before this many exchanges (3.2 s at the callers' 10 Hz, once per node start): a fit
# on the first few samples, taken while every module starts at once on a busy machine, was 50-65 us
# off while it coasted 2 s (test_shared_time_on_loopback_within_50_us under load).
SETTLE_SAMPLES = 32
SETTLED_ERROR_BOUND_NS = 1_000_000  # a jittery link keeps asking at the callers' rate until this good
# However fast a caller calls (a tool that asks whenever its poll returns is woken by its own
# request): every request costs the master a signed reply, and a flood of them delays each reply
# past the 32 outstanding nonces, so that none is ever used.
MIN_REQUEST_PERIOD_NS = 10_000_000


class TimeClient:
    """Asks the master for the time and feeds the answers to the clock's estimator.

    Only replies that echo the t1 of one of our own outstanding requests count, so replayed or
    foreign replies cannot steer the clock (the freshness window cannot protect this channel,
    since an unsynchronised node cannot judge freshness yet). Where the bus enforces command
    authority, such a reply must also be signed by a source with authority on TIME_SYNC: checked
    here, for the few replies this node uses, rather than by every node for every reply.
    """

    def __init__(self, bus: Bus, clock: SharedClock) -> None:
        self.bus = bus
        self.clock = clock
        # t1 as sent (the nonce the master echoes) -> local time just before the send.
        self._outstanding: OrderedDict[int, int] = OrderedDict()
        self._last_request_ns: int | None = None
        self.replies = 0
        bus.subscribe(channels.TIME_SYNC, self._on_time_sync)

    def request(self) -> None:
        """Ask the master for the time: every call (callers call at 10 Hz; at most once per
        MIN_REQUEST_PERIOD_NS) until the estimate has settled within SETTLED_ERROR_BOUND_NS, then
        at most once per SETTLED_REQUEST_PERIOD_NS."""
        nonce = self.clock.local_ns()
        last = self._last_request_ns
        if last is not None and (
            nonce - last < MIN_REQUEST_PERIOD_NS or (nonce - last < SETTLED_REQUEST_PERIOD_NS and self.settled(nonce))
        ):
            return
        self._last_request_ns = nonce
        _seq, data = self.bus.encode(channels.TIME_SYNC, TimeSync(TimeSyncKind.REQUEST, self.bus.source_id, nonce))
        # Stamp t1 right before the send, after encoding: encoding is slow when this process
        # wakes with cold caches and would otherwise sit in the outbound delay only, biasing
        # the offset by half of it (~40 us measured on loopback). After the send is no better:
        # the woken master can preempt us inside sendto.
        self._outstanding[nonce] = self.clock.local_ns()
        self.bus.send_raw(channels.TIME_SYNC, data)
        if len(self._outstanding) > OUTSTANDING_REQUESTS:
            self._outstanding.popitem(last=False)

    def settled(self, local_ns: int) -> bool:
        """Whether the estimate is good enough to ask only every SETTLED_REQUEST_PERIOD_NS."""
        estimator = self.clock.estimator
        if not estimator.settled:
            return False
        status = estimator.status(local_ns)
        return status.samples >= SETTLE_SAMPLES and status.error_bound_ns <= SETTLED_ERROR_BOUND_NS

    def _on_time_sync(self, msg: TimeSync, envelope: Envelope) -> None:
        if msg.kind != TimeSyncKind.REPLY or msg.client_source_id != self.bus.source_id:
            return
        # A forged reply echoing a genuine nonce must not use it up: the genuine reply follows.
        if msg.t1_local_ns not in self._outstanding or not self.bus.authorized(envelope):
            return
        sent_local_ns = self._outstanding.pop(msg.t1_local_ns)
        self.replies += 1
        self.clock.estimator.add_sample(sent_local_ns, msg.t2_master_ns, msg.t3_master_ns, envelope.recv_local_ns)


class TimeMaster:
    """Answers every time request with the master clock's receive and send times."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.answered = 0
        # t3 is signed into the reply, so it is stamped before signing (~35 us of Ed25519): as
        # PTP's one-step clocks do, it is the predicted send time, stamp + the mean time encoding
        # and signing a reply has taken. Unpredicted, that wait biased every client's offset by
        # half of it (-50 to -62 us on loopback). The send itself is not counted: on loopback
        # the kernel delivers, and the clients stamp, within sendto.
        self.encode_ns = 0
        bus.subscribe(channels.TIME_SYNC, self._on_time_sync)

    def _on_time_sync(self, msg: TimeSync, envelope: Envelope) -> None:
        if msg.kind != TimeSyncKind.REQUEST:
            return
        clock = self.bus.clock
        stamped = clock.now_ns()
        reply = TimeSync(
            TimeSyncKind.REPLY, msg.client_source_id, msg.t1_local_ns, envelope.recv_ns, stamped + self.encode_ns
        )
        _seq, data = self.bus.encode(channels.TIME_SYNC, reply)
        self.encode_ns += (clock.now_ns() - stamped - self.encode_ns) // ENCODE_SMOOTHING
        self.bus.send_raw(channels.TIME_SYNC, data)
        self.answered += 1
