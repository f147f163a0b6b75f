"""``rascal log play``: put a recording back on the bus with its original timing, so modules can
be re-run on recorded input.

Why not just resend the recorded bytes: every receiver would reject them. The same (source,
channel, seq) is a replay for a receiver that heard it live, and once a receiver is
synchronised, a ``t_pub_ns`` more than 2 s old is stale (SPEC.md section 10). So by default
play **restamps** each message:

* source id, channel, type id and body bytes stay as recorded: modules see the same nodes
  saying the same things;
* ``seq`` is renumbered per (source, channel) stream, starting at the player's wall clock in
  microseconds as a fresh publisher does (so above anything the stream used before), with the
  recorded gaps kept; a recorded restart jump or reordering becomes a step of one;
* ``t_pub_ns`` is the player's shared time when it sends, and ``t_meas_ns`` is shifted with it
  so that each message is exactly as old at publication as it was live
  (``t_pub - t_meas`` unchanged): consumers' max-age checks behave as they did;
* the message is signed again with the current deployment key (the recording may predate a
  key change); a recorded command signature is made anew for its source when the key file holds
  that source's signing key (the master file), else dropped: nodes that enforce command authority
  then reject the message, as they should a replay no key holder vouches for.

Messages go out at their recorded receive times (``log_time``) scaled by ``1/speed`` from the
start of play; a player that falls behind sends at once and reports how late it got. Play ends
at the end of the file. ``TIME_SYNC`` is left out unless ``channels`` names it: the live time
service owns shared time. Do not play onto a bus where the recorded modules are running: both
would publish as the same sources.

``exact=True`` sends the recorded bytes unchanged instead, which is what an attacker with a
capture can do; receivers should reject them (replay, stale), and spoofing tests check that.
"""

from __future__ import annotations

import re
import time
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field

from protocol import channels as declared
from protocol.auth import Keyring
from protocol.codec import FLAG_SIGNATURE, FLAG_SIGNED, HEADER, HEADER_BYTES, body_span
from protocol.replay import RESTART_JUMP
from rascal.logread import Datagram
from rascal.runtime.bus import Bus
from rascal.runtime.timeclient import TimeClient

TIME_REQUEST_PERIOD_S = 0.1
DEFAULT_EXCLUDED = frozenset({declared.TIME_SYNC})


def restamp(data: bytes, seq: int, t_meas_ns: int, t_pub_ns: int, keyring: Keyring | None) -> bytes:
    """A recorded message with a new sequence number and times, signed with ``keyring`` (unsigned
    when None). Channel and body bytes are kept exactly."""
    (magic, version, flags, type_id, source_id, _key_id, channel_len, _reserved, _seq, _t_meas, _t_pub) = (
        HEADER.unpack_from(data)
    )
    _start, end = body_span(data)
    signer = keyring.signer(source_id) if keyring is not None and flags & FLAG_SIGNATURE else None
    flags, key_id = (FLAG_SIGNED, keyring.active) if keyring is not None else (0, 0)
    if signer is not None:
        flags |= FLAG_SIGNATURE
    head = HEADER.pack(magic, version, flags, type_id, source_id, key_id, channel_len, 0, seq, t_meas_ns, t_pub_ns)
    message = head + data[HEADER_BYTES:end]
    if signer is not None:
        message += signer.sign(message)
    return message + keyring.sign(message) if keyring is not None else message


class Renumber:
    """Fresh sequence numbers per (source, channel) stream that keep the recorded gaps."""

    def __init__(self, base: int) -> None:
        self.base = base
        self._streams: dict[tuple[int, str], tuple[int, int]] = {}  # -> (highest old, its new)

    def __call__(self, source_id: int, channel: str, seq: int) -> int:
        key = (source_id, channel)
        previous = self._streams.get(key)
        if previous is None:
            new = self.base
        else:
            old, last = previous
            step = seq - old
            new = last + (step if 0 < step <= RESTART_JUMP else 1)
            seq = max(seq, old)
        self._streams[key] = (seq, new)
        return new


@dataclass
class PlayResult:
    sent: Counter[str] = field(default_factory=Counter)
    skipped: Counter[str] = field(default_factory=Counter)  # channels left out
    max_late_s: float = 0.0  # how far behind the recorded timing a send got
    duration_s: float = 0.0
    recorded_span_s: float = 0.0  # from the first to the last played message's log time

    @property
    def total(self) -> int:
        return sum(self.sent.values())


class Player:
    """Sends datagrams of a recording onto ``bus`` on their recorded schedule."""

    def __init__(
        self,
        bus: Bus,
        time_client: TimeClient | None = None,
        *,
        speed: float = 1.0,
        channels: str | None = None,
        exact: bool = False,
    ) -> None:
        if not speed >= 0:
            raise ValueError(f"speed must be positive (0: as fast as possible), not {speed}")
        self.bus = bus
        self.time_client = time_client
        self.speed = speed
        self.pattern = re.compile(channels) if channels is not None else None
        self.exact = exact
        self.renumber = Renumber(time.time_ns() // 1000)
        self._next_sync = 0.0

    def wanted(self, channel: str) -> bool:
        if self.pattern is None:
            return channel not in DEFAULT_EXCLUDED
        return self.pattern.fullmatch(channel) is not None

    def sync(self, timeout_s: float) -> bool:
        """Ask the time master for up to ``timeout_s`` until this node is synchronised."""
        deadline = time.monotonic() + timeout_s
        while not self.bus.clock.synced and time.monotonic() < deadline:
            self._wait_until(min(deadline, time.monotonic() + TIME_REQUEST_PERIOD_S))
        return self.bus.clock.synced

    def play(self, datagrams: Iterable[Datagram]) -> PlayResult:
        result = PlayResult()
        start = time.monotonic()
        first_log_ns: int | None = None
        last_log_ns = 0
        for datagram in datagrams:
            if not self.wanted(datagram.channel):
                result.skipped[datagram.channel] += 1
                continue
            if first_log_ns is None:  # the clock starts with the first message, not with reading the file
                first_log_ns, start = datagram.log_time_ns, time.monotonic()
            last_log_ns = max(last_log_ns, datagram.log_time_ns)
            due = start + (datagram.log_time_ns - first_log_ns) / 1e9 / self.speed if self.speed else start
            self._wait_until(due)
            result.max_late_s = max(result.max_late_s, time.monotonic() - due)
            self.bus.send_raw(datagram.channel, datagram.data if self.exact else self._restamped(datagram))
            result.sent[datagram.channel] += 1
        result.duration_s = time.monotonic() - start
        result.recorded_span_s = (last_log_ns - first_log_ns) / 1e9 if first_log_ns is not None else 0.0
        return result

    def _restamped(self, datagram: Datagram) -> bytes:
        seq = self.renumber(datagram.source_id, datagram.channel, datagram.seq)
        t_pub_ns = self.bus.clock.now_ns()
        t_meas_ns = t_pub_ns - (datagram.t_pub_ns - datagram.t_meas_ns)
        return restamp(datagram.data, seq, t_meas_ns, t_pub_ns, self.bus.codec.keyring)

    def _wait_until(self, due: float) -> None:
        """Keep the bus (time-sync replies) and the time requests going until ``due``."""
        while True:
            now = time.monotonic()
            if self.time_client is not None and now >= self._next_sync:
                self.time_client.request()
                self._next_sync = now + TIME_REQUEST_PERIOD_S
            if now >= due:
                return
            wake = min(due, self._next_sync) if self.time_client is not None else due
            self.bus.poll(max(0.0, wake - now))
