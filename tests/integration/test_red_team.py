"""The red team of issue 25: its network attacks against real processes on loopback.

A genuine publisher process sends fragmented PATH (~2.3 KB, 2 fragments) and MAP_SNAPSHOT
(~30 KB, 22 fragments) messages at 100 Hz, alternating; a receiving process counts what it is
given and what it rejects. The attacker is this test process and holds no key: a raw UDP socket
that is a member of the bus's multicast group, so it hears every genuine datagram (the bus is
authenticated, not encrypted), and sends its forgeries to the group's ports the moment it hears
a genuine fragment, where they hurt most, at 1,000 datagrams/s (bursts of at most 10). Only
loopback: TTL 0 through 127.0.0.1, refused otherwise (rascal.spoof.loopback_only). Each flood is
bounded in datagrams and in time and stops by itself.

Attacks (issue 25, "Where it stands"): 1. forged fragments with each heard and each predictable
message id, another count/total_len; a garbage first copy of each fragment; fragments under
the victim's source id declaring 256 KiB each; fragments from 100 made-up sources. 5. a sender
restarted with its wall clock 10 s back, while the attacker replays its previous life. 6. a
flood of 16 KB datagrams with a wrong tag (MAC amplification). Forged commands from a module
holding only its own key (item 3) are tests/integration/test_authority.py; items 2, 4, 7 and 8
are not attacks on the bus.

Run as ``python -m tests.integration.test_red_team receive URL MAX_S`` or ``... publish URL
FIRST_ID COUNT RATE_HZ STEP_BACK_S`` it is one of the two genuine processes.
"""

from __future__ import annotations

import itertools
import json
import random
import select
import signal
import socket
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple
from unittest import mock
from urllib.parse import urlsplit

import pytest

from protocol import channels
from protocol import messages as m
from protocol.auth import FRAGMENT_TAG_BYTES, TAG_BYTES, Keyring
from protocol.codec import FLAG_FRAGMENT, FLAG_SIGNED, MAGIC, VERSION, Codec
from protocol.framing import FRAGMENT_HEADER, FRAGMENT_HEADER_BYTES
from protocol.transport import RECV_BUFFER_BYTES, UdpConfig
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from rascal.spoof import loopback_only
from tests.conftest import ROOT

pytestmark = pytest.mark.slow

PUBLISHER, RECEIVER = 30, 31
CHANNELS = (channels.PATH, channels.MAP_SNAPSHOT)
MESSAGES = 200  # per attack, half of each channel
RATE_HZ = 100.0
FORGED_HZ = 1000.0
FORGED_BURST = 10
SETTLE_S = 0.8  # after the last genuine message: longer than the 500 ms reassembly timeout
RECEIVER_MAX_S = 20.0
DELIVERED = 0.99
MIN_FORGED = 0.8 * FORGED_HZ * MESSAGES / RATE_HZ  # the attacker kept up its rate
LIFE_TWO = 1000  # the first message id of the restarted publisher
STEP_BACK_S = 10.0
BAD_MAC_BYTES = 16_000
GENUINE_FAILURES = ("fragment_evicted", "bad_fragment")
GENUINE_HELD_BYTES = 64 * 1024  # what the genuine partials alone reserve at most: a MAP_SNAPSHOT and a PATH


# -- the genuine processes ------------------------------------------------------------------------


def genuine(message_id: int, rng: random.Random) -> tuple[str, Any]:
    """Even ids PATH (80 points), odd ids MAP_SNAPSHOT (30,000 random cells); the id in both."""
    if message_id % 2:
        return channels.MAP_SNAPSHOT, m.MapSnapshot(float(message_id), 0.0, 0.2, 150, 200, rng.randbytes(30_000))
    points = tuple(m.PathPoint(512.25 + 0.5 * k, -88.0 + rng.random(), 6.7) for k in range(80))
    return channels.PATH, m.Path(message_id, points, False)


def message_id_of(msg: Any) -> int:
    return msg.path_id if isinstance(msg, m.Path) else int(msg.origin_east_m)


def publish(url: str, first_id: int, count: int, rate_hz: float, step_back_s: float) -> None:
    """Publish ``count`` messages at ``rate_hz``. ``step_back_s``: restarted while the host's wall
    clock, from which the bus takes its sequence base, is that far back (its shared time is right)."""
    clock = MasterClock()
    with mock.patch.object(time, "time_ns", return_value=time.time_ns() - int(step_back_s * 1e9)):
        bus = Bus.open(url, source_id=PUBLISHER, clock=clock)
    rng = random.Random(first_id)
    due = time.monotonic()
    for message_id in range(first_id, first_id + count):
        bus.publish(*genuine(message_id, rng))
        due += 1.0 / rate_hz
        time.sleep(max(0.0, due - time.monotonic()))
    bus.close()
    print(json.dumps({"sent": count}), flush=True)


def receive(url: str, max_s: float) -> None:
    """Count deliveries by message id and rejects by reason until SIGTERM or ``max_s``; print them."""
    bus = Bus.open(url, source_id=RECEIVER, clock=MasterClock())
    delivered: list[int] = []
    worst_ms = [0.0]  # the longest from publication to delivery

    def on_message(msg: Any, envelope: Any) -> None:
        delivered.append(message_id_of(msg))
        worst_ms[0] = max(worst_ms[0], (envelope.recv_ns - envelope.t_pub_ns) / 1e6)

    for channel in CHANNELS:
        bus.subscribe(channel, on_message)
    stopping: list[int] = []
    signal.signal(signal.SIGTERM, lambda signum, _frame: stopping.append(signum))
    print("ready", flush=True)
    held = 0
    cpu = time.process_time()
    end = time.monotonic() + max_s
    while not stopping and time.monotonic() < end:
        bus.poll(0.05)
        held = max(held, bus.reassembler.held_bytes())
    rejects: Counter[str] = Counter()
    for (_source, reason), count in bus.rejects.items():
        rejects[reason] += count
    summary = {
        "delivered": delivered,
        "rejects": rejects,
        "max_held_bytes": held,
        "pending": bus.reassembler.pending(),
        "max_latency_ms": worst_ms[0],
        "cpu_s": time.process_time() - cpu,
    }
    bus.close()
    print(json.dumps(summary), flush=True)


def start(role: str, *args: object) -> subprocess.Popen[str]:
    command = [sys.executable, "-m", "tests.integration.test_red_team", role, *map(str, args)]
    return subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def read_line(child: subprocess.Popen[str], timeout_s: float) -> str:
    assert child.stdout is not None
    ready, _, _ = select.select([child.stdout], [], [], timeout_s)
    assert ready, f"{child.args[3]} said nothing in {timeout_s} s"
    return child.stdout.readline().strip()


def summary_of(child: subprocess.Popen[str]) -> dict[str, Any]:
    out, err = child.communicate(timeout=10)
    assert child.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


# -- the keyless attacker -------------------------------------------------------------------------


class Heard(NamedTuple):
    """A genuine fragment as the attacker heard it."""

    channel: str
    datagram: bytes
    source_id: int
    index: int
    count: int
    message_id: int
    total_len: int


Forged = list[tuple[str, bytes]]
Attack = Callable[[Heard, int, random.Random], Forged]


class Attacker:
    """A member of the bus's group with no key: hears the genuine fragments and answers each with
    up to ``FORGED_BURST`` forged datagrams, ``FORGED_HZ`` on average."""

    def __init__(self, url: str) -> None:
        loopback_only(url)  # refuses anything but TTL 0 through a 127.0.0.0/8 address
        parts = urlsplit(url)
        assert parts.hostname is not None and parts.port is not None
        self.config = UdpConfig(parts.hostname, parts.port)
        self.tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
        self.tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        self.tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        self.tx.bind(("127.0.0.1", 0))  # so that its own datagrams are told from the genuine ones
        self.ears = {self.config.port(channel): self._ear(self.config.port(channel)) for channel in CHANNELS}
        self.channel_of = {self.config.port(channel): channel for channel in CHANNELS}
        self.sent = 0

    def _ear(self, port: int) -> socket.socket:
        ear = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        ear.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        ear.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        ear.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECV_BUFFER_BYTES)
        ear.bind((self.config.group, port))
        membership = socket.inet_aton(self.config.group) + socket.inet_aton("127.0.0.1")
        ear.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
        ear.setblocking(False)
        return ear

    def heard(self, timeout_s: float) -> list[Heard]:
        """Genuine fragments heard within ``timeout_s`` (the attacker's own are skipped)."""
        ready, _, _ = select.select(list(self.ears.values()), [], [], timeout_s)
        own = self.tx.getsockname()
        fragments = []
        for ear in ready:
            channel = self.channel_of[ear.getsockname()[1]]
            while True:
                try:
                    datagram, sender = ear.recvfrom(65535)
                except BlockingIOError:
                    break
                if sender != own and len(datagram) > FRAGMENT_HEADER_BYTES and datagram[3] & FLAG_FRAGMENT:
                    _m, _v, _f, source_id, index, count, _k, message_id, total_len = FRAGMENT_HEADER.unpack_from(
                        datagram
                    )
                    fragments.append(Heard(channel, datagram, source_id, index, count, message_id, total_len))
        return fragments

    def run(self, attack: Attack, running: Callable[[], bool], max_s: float, seed: int) -> None:
        """Attack while ``running()``, for at most ``max_s`` and ``FORGED_HZ * max_s`` datagrams."""
        rng = random.Random(seed)
        budget = int(FORGED_HZ * max_s)
        tokens, last = 0.0, time.monotonic()
        end = last + max_s
        while running() and self.sent < budget and (now := time.monotonic()) < end:
            tokens, last = min(float(FORGED_BURST), tokens + (now - last) * FORGED_HZ), now
            for heard in self.heard(0.002):
                forged = attack(heard, min(int(tokens), budget - self.sent), rng)
                for channel, datagram in forged:
                    self.tx.sendto(datagram, (self.config.group, self.config.port(channel)))
                tokens -= len(forged)
                self.sent += len(forged)

    def close(self) -> None:
        for sock in (self.tx, *self.ears.values()):
            sock.close()


def forged_fragment(
    heard: Heard, index: int, count: int, message_id: int, total_len: int, data: bytes, rng: random.Random
) -> bytes:
    """A fragment as a keyless attacker makes it: unsigned, or 'signed' with a made-up tag."""
    signed = rng.random() < 0.5
    flags = FLAG_FRAGMENT | (FLAG_SIGNED if signed else 0)
    head = FRAGMENT_HEADER.pack(MAGIC, VERSION, flags, heard.source_id, index, count, 1, message_id, total_len)
    return head + data + (rng.randbytes(FRAGMENT_TAG_BYTES) if signed else b"")


def predicted_ids(heard: Heard, n: int, rng: random.Random) -> Forged:
    """21-byte fragments with another count and total_len, for the heard message id (its later
    fragments may still be coming) and the ids after it (what the old counter would use next)."""
    ids = [heard.message_id if k % 2 == 0 else (heard.message_id + 1 + k // 2) & 0xFFFFFFFF for k in range(n)]
    return [(heard.channel, forged_fragment(heard, 0, heard.count + 1, i, heard.total_len - 1, b"x", rng)) for i in ids]


def garbage_first_copies(heard: Heard, n: int, rng: random.Random) -> Forged:
    """Same-sized garbage copies of the fragments still to come: the heard message's later ones,
    then those of the ids the old counter would use next."""
    size = len(heard.datagram) - FRAGMENT_HEADER_BYTES - FRAGMENT_TAG_BYTES
    later = ((heard.message_id, i) for i in range(heard.index + 1, heard.count))
    ahead = (((heard.message_id + k) & 0xFFFFFFFF, i) for k in itertools.count(1) for i in range(heard.count))
    return [
        (heard.channel, forged_fragment(heard, i, heard.count, mid, heard.total_len, rng.randbytes(size), rng))
        for mid, i in itertools.islice(itertools.chain(later, ahead), n)
    ]


def byte_bound_eviction(heard: Heard, n: int, rng: random.Random) -> Forged:
    """Fragments under the victim's source id, each starting a new 256 KiB message: four used to
    evict the genuine partial message (1 MiB per source)."""
    return [
        (heard.channel, forged_fragment(heard, 0, 200, rng.getrandbits(32), 256 * 1024, rng.randbytes(1300), rng))
        for _ in range(n)
    ]


def fake_sources(heard: Heard, n: int, rng: random.Random) -> Forged:
    """Fragments from 100 made-up sources, 256 KiB each: the 64-source table used to evict the
    victim, and 64 of them pinned 64 MiB."""
    forged = []
    for _ in range(n):
        fake = heard._replace(source_id=1000 + rng.randrange(100))
        datagram = forged_fragment(fake, 0, 200, rng.getrandbits(32), 256 * 1024, b"y" * 64, rng)
        forged.append((heard.channel, datagram))
    return forged


class BadMac:
    """Whole 16 KB messages under the victim's source id with a wrong tag: each one used to be
    verified three times (C receiver, C open, Python)."""

    def __init__(self) -> None:
        msg = m.MapSnapshot(0.0, 0.0, 0.2, 100, 100, random.randbytes(BAD_MAC_BYTES))
        now = time.time_ns()
        self.template = Codec(Keyring.generate()).encode(channels.MAP_SNAPSHOT.encode(), msg, PUBLISHER, 1, now, now)

    def __call__(self, heard: Heard, n: int, rng: random.Random) -> Forged:
        return [(channels.MAP_SNAPSHOT, self.template[:-TAG_BYTES] + rng.randbytes(TAG_BYTES)) for _ in range(n)]


class Replay:
    """First records every genuine fragment (sending nothing), then sends them again, newest
    first (fresh enough to pass the freshness window at first), round and round: a sniffer's
    replay of the publisher's previous life, whose sequence numbers are above the new life's."""

    def __init__(self) -> None:
        self.recorded: list[Heard] = []
        self.replaying = False
        self.next = 0

    def start(self) -> None:
        self.replaying = True

    def __call__(self, heard: Heard, n: int, rng: random.Random) -> Forged:
        if not self.replaying:
            self.recorded.append(heard)
            return []
        forged = []
        for _ in range(n):
            old = self.recorded[-1 - self.next % len(self.recorded)]
            forged.append((old.channel, old.datagram))
            self.next += 1
        return forged


# -- the test -------------------------------------------------------------------------------------


class Outcome(NamedTuple):
    delivered: Counter[int]
    rejects: Counter[str]
    forged: int
    summary: dict[str, Any]


def attack_once(
    bus_url: str, attack: Attack, lives: list[tuple[int, float]], after_life: Callable[[], None] = lambda: None
) -> Outcome:
    """A receiver, then one publisher per (first id, wall clock step back) in turn, each under
    attack while it runs (``after_life`` after each); the receiver's summary once all are done."""
    attacker = Attacker(bus_url)
    receiver = start("receive", bus_url, RECEIVER_MAX_S)
    publishers: list[subprocess.Popen[str]] = []
    try:
        assert read_line(receiver, 15.0) == "ready"
        for first_id, step_back_s in lives:
            publisher = start("publish", bus_url, first_id, MESSAGES, RATE_HZ, step_back_s)
            publishers.append(publisher)
            attacker.run(attack, lambda child=publisher: child.poll() is None, 10.0, first_id)
            assert json.loads(read_line(publisher, 10.0)) == {"sent": MESSAGES}
            after_life()
        time.sleep(SETTLE_S)
        receiver.send_signal(signal.SIGTERM)
        summary = summary_of(receiver)
    finally:
        for child in (receiver, *publishers):
            if child.poll() is None:
                child.kill()
            child.wait()
        attacker.close()
    return Outcome(Counter(summary["delivered"]), Counter(summary["rejects"]), attacker.sent, summary)


def report(name: str, outcome: Outcome, lives: int = 1) -> None:
    """One line for the record (docs/RELIABILITY.md)."""
    delivered, sent = len(outcome.delivered), MESSAGES * lives
    summary = outcome.summary
    print(
        f"{name}: {delivered} of {sent} genuine delivered ({100 * delivered / sent:.1f} %), "
        f"{outcome.forged} forged sent, rejects {dict(outcome.rejects)}, "
        f"max held {summary['max_held_bytes']} B, max latency {summary['max_latency_ms']:.1f} ms, "
        f"receiver CPU {summary['cpu_s']:.2f} s"
    )


def assert_delivered(outcome: Outcome, ids: range) -> None:
    """At least 99 % of each channel's genuine messages, each once."""
    for parity, channel in enumerate(CHANNELS):
        wanted = [i for i in ids if i % 2 == parity]
        got = [i for i in wanted if i in outcome.delivered]
        assert len(got) >= DELIVERED * len(wanted), (channel, len(got), len(wanted), outcome.rejects)
    assert max(outcome.delivered.values()) == 1, outcome.delivered.most_common(3)


FRAGMENT_ATTACKS: dict[str, Attack] = {
    "predicted-id": predicted_ids,
    "garbage-first-copy": garbage_first_copies,
    "byte-bound-eviction": byte_bound_eviction,
    "fake-sources": fake_sources,
}


@pytest.mark.parametrize("name", FRAGMENT_ATTACKS)
def test_forged_fragments_cost_no_genuine_message(name: str, bus_url: str, key_file: Path) -> None:
    """>= 99 % of the genuine fragmented messages arrive at 1,000 forged datagrams/s; every forged
    datagram that reaches the receiver is rejected as unauthentic, holds nothing and evicts
    nothing."""
    outcome = attack_once(bus_url, FRAGMENT_ATTACKS[name], [(0, 0.0)])
    report(name, outcome)
    assert_delivered(outcome, range(MESSAGES))
    assert outcome.forged >= MIN_FORGED, outcome.forged
    forged_rejects = outcome.rejects["bad_mac"] + outcome.rejects["unsigned"]
    assert 0.99 * outcome.forged <= forged_rejects <= outcome.forged, (outcome.forged, outcome.rejects)
    assert not any(outcome.rejects[reason] for reason in GENUINE_FAILURES), outcome.rejects
    assert outcome.summary["max_held_bytes"] <= GENUINE_HELD_BYTES, outcome.summary["max_held_bytes"]
    assert outcome.summary["pending"] == 0


def test_a_bad_mac_flood_is_counted_once_and_costs_no_message(bus_url: str, key_file: Path) -> None:
    """16 KB datagrams with a wrong tag at 1,000/s: each rejected as bad_mac exactly once (the
    receiver's CPU for it is in the report line), the genuine traffic unharmed."""
    outcome = attack_once(bus_url, BadMac(), [(0, 0.0)])
    report("bad-mac", outcome)
    assert_delivered(outcome, range(MESSAGES))
    assert outcome.forged >= MIN_FORGED, outcome.forged
    assert 0.99 * outcome.forged <= outcome.rejects["bad_mac"] <= outcome.forged, (outcome.forged, outcome.rejects)
    assert not any(outcome.rejects[reason] for reason in (*GENUINE_FAILURES, "unsigned")), outcome.rejects


def test_a_sender_restarted_with_its_clock_back_is_heard_while_its_old_life_is_replayed(
    bus_url: str, key_file: Path
) -> None:
    """The publisher's second life starts with its wall clock 10 s back (sequence numbers far
    below its first life's) while the attacker replays the first life at 1,000 datagrams/s: the
    second life is delivered from its first messages on, within 1 s of publication, and no
    replayed message is delivered again."""
    replay = Replay()
    outcome = attack_once(bus_url, replay, [(0, 0.0), (LIFE_TWO, STEP_BACK_S)], replay.start)
    report("replay-stepped-back", outcome, lives=2)
    assert_delivered(outcome, range(MESSAGES))
    assert_delivered(outcome, range(LIFE_TWO, LIFE_TWO + MESSAGES))
    assert LIFE_TWO in outcome.delivered or LIFE_TWO + 1 in outcome.delivered
    assert outcome.summary["max_latency_ms"] < 1000.0, outcome.summary
    assert outcome.forged >= MIN_FORGED, outcome.forged
    assert outcome.rejects["replay"] + outcome.rejects["stale"] > 0, outcome.rejects
    unexpected = (*GENUINE_FAILURES, "bad_mac", "unsigned")
    assert not any(outcome.rejects[reason] for reason in unexpected), outcome.rejects


if __name__ == "__main__":
    role, url, *rest = sys.argv[1:]
    if role == "receive":
        receive(url, float(rest[0]))
    else:
        publish(url, int(rest[0]), int(rest[1]), float(rest[2]), float(rest[3]))
