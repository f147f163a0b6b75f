"""``rascal spoof KIND``: hostile datagrams for fault testing, bounded and on this host only.

Kinds (each datagram built with the protocol's own codec and framing, then spoiled):

    forge     well-formed messages signed with a wrong key (--sign wrong) or unsigned (--sign none):
              fake obstacles on OBSTACLES_LIDAR/ESVS/BEACON, fake commands on ACTUATOR_COMMAND,
              or any channel's message given with --json
    replay    a recording's genuine signed datagrams (run.mcap), sent again byte for byte
    mutate    a message with bits flipped, bytes overwritten or a header field rewritten
    truncate  a message cut short at a random length
    oversize  fragments of a message larger than any receiver accepts (256 KiB)
    garbage   random bytes, half of them behind a plausible header prefix

``--rate`` sets the pace (a flood is just a high rate). Every run is bounded by ``--count`` and
``--duration`` (defaults 100 and 10 s; caps 1,000,000 datagrams, 600 s, 100,000/s).

Destinations: only this host's loopback. The bus URL must be ``mem://`` or ``udpm://`` with
``ttl=0`` through a 127.0.0.0/8 interface and loopback peers only; anything else is refused.
In a network namespace, run the spoofer inside it (``ip netns exec``): its loopback is its own.

Prints one JSON line: the bus, the elapsed time and the datagrams sent by kind.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import random
import re
import secrets
import struct
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from protocol import channels
from protocol import messages as m
from protocol.auth import Keyring, default_keyring, load_keyring
from protocol.codec import HEADER, HEADER_BYTES, Codec, check_channel
from protocol.framing import DEFAULT_MAX_DATAGRAM_BYTES, fragment
from protocol.transport import Transport, UrlError, default_url, open_transport
from rascal.bustools import from_jsonable
from rascal.logread import RecordingError, iter_datagrams

KINDS = ("forge", "replay", "mutate", "truncate", "oversize", "garbage")
MAX_COUNT = 1_000_000
MAX_DURATION_S = 600.0
MAX_RATE_HZ = 100_000.0
DEFAULT_SOURCE_ID = 0xBAD
OVERSIZE_BYTES = 300 * 1024  # over the receivers' 256 KiB message limit
LOOPBACK = ipaddress.ip_network("127.0.0.0/8")
# (offset, struct format) of the header fields a mutation may rewrite: version, flags, type,
# source, key id, channel length, seq, t_pub.
HEADER_FIELDS = ((2, "B"), (3, "B"), (4, "<H"), (6, "<H"), (8, "<H"), (10, "B"), (12, "<Q"), (28, "<Q"))
Batch = tuple[str, str, list[bytes]]


class SpoofError(ValueError):
    """A spoofing request that is refused or cannot be carried out; the message says why."""


def loopback_only(url: str) -> None:
    """Refuse, before any socket exists, a bus URL that could carry a datagram off this host."""
    parts = urlsplit(url)
    if parts.scheme == "mem":
        return
    if parts.scheme != "udpm":
        raise SpoofError(f"{url}: only udpm:// (ttl=0, loopback) and mem:// buses can be spoofed")
    query = {key: values[-1] for key, values in parse_qs(parts.query, keep_blank_values=True).items()}
    if query.get("ttl", "0") != "0":
        raise SpoofError(f"{url}: ttl={query['ttl']} leaves this host; the spoofer sends only with ttl=0")
    for address in (query.get("iface", "127.0.0.1"), *(peer for peer in query.get("peers", "").split(",") if peer)):
        try:
            on_loopback = ipaddress.ip_address(address) in LOOPBACK
        except ValueError:
            on_loopback = False
        if not on_loopback:
            raise SpoofError(f"{url}: {address} is not a loopback address (127.0.0.0/8); refused")


def fake_message(channel: str, body_json: str | None) -> Any:
    """The message a forged datagram carries: ``body_json`` as the channel's type, or a fake
    obstacle dead ahead, or full throttle with hard left steering."""
    msg_type = channels.CHANNEL_TYPES.get(channel)
    if msg_type is None:
        raise SpoofError(f"channel {channel!r} is not declared in protocol.channels")
    if body_json is not None:
        try:
            return from_jsonable(msg_type, json.loads(body_json))
        except (ValueError, TypeError) as exc:
            raise SpoofError(f"--json is not a {msg_type.__name__}: {exc}") from None
    if msg_type is m.ObstacleList:
        wall = m.Obstacle(8.0, 0.0, 1.0, 6.0, 1.5, 0.0, 1.0, 8.0)  # across the path, 8 m ahead
        return m.ObstacleList(int(m.Sensor.UNKNOWN), int(m.Frame.VEHICLE), (wall,))
    if msg_type is m.ActuatorCommand:
        return m.ActuatorCommand(throttle=1.0, brake=0.0, steering_rad=0.5, stop_reason="")
    raise SpoofError(f"no built-in fake for {channel}; give the message with --json")


class Forger:
    """Builds each kind's datagrams: ``next_<kind>()`` returns (variant, channel, datagrams)."""

    def __init__(
        self,
        channel: str,
        msg: Any,
        keyring: Keyring | None,
        source_id: int,
        rng: random.Random,
        now_ns: Callable[[], int],
        recording: Iterator[tuple[str, bytes]] | None = None,
    ) -> None:
        self.channel = channel
        self.channel_bytes = check_channel(channel)
        self.msg = msg
        self.codec = Codec(keyring)
        self.source_id = source_id
        self.rng = rng
        self.now_ns = now_ns
        self.recording = recording
        self.seq = now_ns() // 1000  # as a real publisher: wall-clock microseconds
        self.message_id = rng.getrandbits(32)
        self.big: list[bytes] = []

    def message(self) -> bytes:
        self.seq += 1
        now = self.now_ns()
        return self.codec.encode(self.channel_bytes, self.msg, self.source_id, self.seq, now, now)

    def datagrams(self, message: bytes) -> list[bytes]:
        self.message_id = (self.message_id + 1) & 0xFFFFFFFF
        return fragment(message, self.source_id, self.message_id, DEFAULT_MAX_DATAGRAM_BYTES)

    def next_forge(self) -> Batch:
        return "forged", self.channel, self.datagrams(self.message())

    def next_replay(self) -> Batch:
        assert self.recording is not None
        channel, data = next(self.recording)
        source_id = HEADER.unpack_from(data)[4]
        self.message_id = (self.message_id + 1) & 0xFFFFFFFF
        return "replayed", channel, fragment(data, source_id, self.message_id, DEFAULT_MAX_DATAGRAM_BYTES)

    def next_mutate(self) -> Batch:
        """Every mutation changes the bytes (no flip undone, no byte rewritten to itself), so
        even a message signed with the deployment key must fail its check."""
        buf = bytearray(self.message())
        how = self.rng.randrange(3)
        if how == 0:
            for bit in self.rng.sample(range(8 * len(buf)), self.rng.choice((1, 1, 2, 4, 8))):
                buf[bit // 8] ^= 1 << (bit % 8)
            return "bit flips", self.channel, [bytes(buf)]
        if how == 1:
            for index in self.rng.sample(range(len(buf)), self.rng.randint(1, 4)):
                buf[index] ^= self.rng.randrange(1, 256)
            return "byte writes", self.channel, [bytes(buf)]
        offset, fmt = self.rng.choice(HEADER_FIELDS)
        (old,) = struct.unpack_from(fmt, buf, offset)
        struct.pack_into(fmt, buf, offset, old ^ self.rng.randrange(1, 1 << (8 * struct.calcsize(fmt))))
        return "header field", self.channel, [bytes(buf)]

    def next_truncate(self) -> Batch:
        data = self.message()
        return "truncated", self.channel, [data[: self.rng.randrange(len(data))]]

    def next_oversize(self) -> Batch:
        if not self.big:  # one huge message's fragments, sent one per step
            body = m.ObstacleList(0, 0, tuple(m.Obstacle(*(float(i),) * 8) for i in range(OVERSIZE_BYTES // 70)))
            huge = Codec(None, 2 * OVERSIZE_BYTES).encode(self.channel_bytes, body, self.source_id, 1, 0, 0)
            self.big = self.datagrams(huge)
        return "oversized fragment", self.channel, [self.big[self.rng.randrange(len(self.big))]]

    def next_garbage(self) -> Batch:
        noise = self.rng.randbytes(self.rng.randrange(1, DEFAULT_MAX_DATAGRAM_BYTES))
        if self.rng.random() < 0.5:
            return "random bytes", self.channel, [noise]
        return "header prefix + random", self.channel, [self.message()[:HEADER_BYTES] + noise]


def recorded(path: Path, channel_pattern: str) -> Iterator[tuple[str, bytes]]:
    """A recording's (channel, datagram bytes), round and round."""
    try:
        first = [(d.channel, d.data) for d in iter_datagrams(path, channel_pattern)]
    except (RecordingError, re.error) as exc:
        raise SpoofError(str(exc)) from None
    if not first:
        raise SpoofError(f"{path}: no messages on channels matching {channel_pattern!r}")
    while True:
        yield from first


def spoof(
    transport: Transport,
    forger: Forger,
    kind: str,
    count: int,
    duration_s: float,
    rate_hz: float,
    sleep: Callable[[float], None] = time.sleep,
    monotonic: Callable[[], float] = time.monotonic,
) -> Counter[str]:
    """Send ``count`` datagrams of ``kind`` at ``rate_hz`` (stopping at ``duration_s``); return
    how many of each variant were sent."""
    make = getattr(forger, f"next_{kind}")
    sent: Counter[str] = Counter()
    started = monotonic()
    total = 0
    pending: list[bytes] = []
    variant = channel = ""
    try:
        while total < count:
            due = started + total / rate_hz
            now = monotonic()
            if max(due, now) - started >= duration_s:
                break
            if due > now:
                sleep(due - now)
            if not pending:
                variant, channel, pending = make()
            transport.send(channel, pending.pop(0))
            sent[f"{kind}: {variant}"] += 1
            total += 1
    except KeyboardInterrupt:
        pass  # Ctrl-C ends the run early; the report still says what was sent
    return sent


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="rascal spoof", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("kind", choices=KINDS)
    parser.add_argument("--bus", help="bus URL (default: $RASCAL_BUS_URL); loopback only")
    parser.add_argument("--channel", default=channels.ACTUATOR_COMMAND, help="channel to spoof (default %(default)s)")
    parser.add_argument("--json", help="the forged message's body, as for rascal bus pub")
    parser.add_argument(
        "--sign",
        choices=("wrong", "none", "deployment"),
        default="wrong",
        help="sign with a random wrong key (default), not at all, or (mutate, truncate) the deployment key",
    )
    parser.add_argument("--key-file", type=Path, help="the deployment key for --sign deployment")
    parser.add_argument("--recording", type=Path, help="run.mcap to replay (kind replay)")
    parser.add_argument("--channels", default=".*", help="replay only channels matching this expression")
    parser.add_argument("--count", type=int, default=100, help=f"datagrams to send (at most {MAX_COUNT:,})")
    parser.add_argument("--duration", type=float, default=10.0, help=f"seconds at most (at most {MAX_DURATION_S:g})")
    parser.add_argument("--rate", type=float, default=100.0, help=f"datagrams per second (at most {MAX_RATE_HZ:,.0f})")
    parser.add_argument("--source-id", type=int, default=DEFAULT_SOURCE_ID, help="source id to claim")
    parser.add_argument("--seed", type=int, default=0, help="seed of the mutations and random bytes")
    args = parser.parse_args(argv)
    try:
        return _run(args)
    except (SpoofError, UrlError) as exc:
        print(f"rascal spoof: {exc}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    if not 1 <= args.count <= MAX_COUNT:
        raise SpoofError(f"--count must be 1..{MAX_COUNT:,}")
    if not 0 < args.duration <= MAX_DURATION_S:
        raise SpoofError(f"--duration must be in (0, {MAX_DURATION_S:g}] seconds")
    if not 0 < args.rate <= MAX_RATE_HZ:
        raise SpoofError(f"--rate must be in (0, {MAX_RATE_HZ:,.0f}] per second")
    if not 1 <= args.source_id <= 0xFFFF:
        raise SpoofError("--source-id must be 1..65535")
    if args.sign == "deployment" and args.kind not in ("mutate", "truncate"):
        raise SpoofError("--sign deployment is only for mutate and truncate (forging with it is rascal bus pub)")
    if args.kind == "replay" and args.recording is None:
        raise SpoofError("replay needs --recording RUN.mcap")
    keyring: Keyring | None = None
    if args.sign == "wrong":
        keyring = Keyring({1: secrets.token_bytes(32)}, 1)  # key id 1: the usual id, the wrong key
    elif args.sign == "deployment":
        keyring = load_keyring(args.key_file) if args.key_file else default_keyring()
    msg = fake_message(args.channel, args.json) if args.kind not in ("replay", "oversize") else None
    recording = recorded(args.recording, args.channels) if args.kind == "replay" else None
    url = args.bus or default_url()
    loopback_only(url)
    transport = open_transport(url)
    try:
        forger = Forger(args.channel, msg, keyring, args.source_id, random.Random(args.seed), time.time_ns, recording)
        started = time.monotonic()
        sent = spoof(transport, forger, args.kind, args.count, args.duration, args.rate)
        elapsed = time.monotonic() - started
    finally:
        transport.close()
    report = {"bus": url, "elapsed_s": round(elapsed, 3), "total": sum(sent.values()), "sent": sent}
    print(json.dumps(report))
    return 0
