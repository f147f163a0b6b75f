"""Link fault injection: a Transport wrapper that loses, delays, duplicates, reorders and corrupts.

netem is not available on these kernels, so faults live in the transport. They are applied on
the **receive** side: each process sees its own link, so one module can sit behind a lossy link
while the others hear the same multicast cleanly, and a rule can name the sources it hurts
(a host pair is "this module, from those sources"). Delayed datagrams wait in a bounded heap and
are released by :meth:`FaultyTransport.receive`, which waits no longer than the caller asked nor
past the next release, so a module's periodic tasks never wait on a held datagram.

Rules, first match wins (a datagram no rule matches passes untouched)::

    channels = "OBSTACLES_.*"   # regular expression, matched against the whole channel name
    sources = [21, 22]          # only datagrams from these source ids (empty: every source)
    loss_pct = 20               # dropped
    delay_ms = 5                # every matched datagram waits delay_ms + U(0, jitter_ms)
    jitter_ms = 20
    duplicate_pct = 1           # delivered twice (the copy with its own delay)
    reorder_pct = 5             # held reorder_ms longer, so later datagrams overtake it
    reorder_ms = 10
    corrupt_pct = 1             # one random bit flipped
    seed = 7                    # each rule draws from its own seeded generator: runs repeat

As text (a bus URL's ``faults=`` option, ``$RASCAL_FAULTS``), rules are separated by ``;``,
fields by ``,`` and sources by ``|``; channel expressions cannot contain ``,`` or ``;``::

    channels=OBSTACLES_.*,loss_pct=20,jitter_ms=20;channels=GPS,sources=31|32,delay_ms=100

The channel of a whole message is read from its header; a fragment's from the first fragment
of its message (remembered per source and message id); a fragment whose first was not seen,
and bytes too short to have a header, have the channel "".
"""

from __future__ import annotations

import heapq
import itertools
import math
import random
import re
import struct
import sys
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, fields
from typing import Any

from protocol.codec import FLAG_FRAGMENT, HEADER_BYTES
from protocol.framing import FRAGMENT_HEADER_BYTES
from protocol.transport import Deliver, Transport, UrlError

FAULTS_ENV = "RASCAL_FAULTS"
MAX_HELD_DATAGRAMS = 4096  # held for delay at once; beyond it a datagram is dropped and counted
MAX_DELAY_MS = 10_000.0
FRAGMENT_CHANNELS_REMEMBERED = 256
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_PERCENTS = ("loss_pct", "duplicate_pct", "reorder_pct", "corrupt_pct")


class FaultConfigError(ValueError):
    """A fault rule that cannot be used; the message names the rule and key."""


@dataclass(frozen=True)
class FaultRule:
    """What happens to the datagrams of matching channels (and sources) on this receiver."""

    channels: str = ".*"
    sources: tuple[int, ...] = ()
    loss_pct: float = 0.0
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    duplicate_pct: float = 0.0
    reorder_pct: float = 0.0
    reorder_ms: float = 10.0
    corrupt_pct: float = 0.0
    seed: int = 0

    def matches(self, channel: str, source_id: int) -> bool:
        return (not self.sources or source_id in self.sources) and _compiled(self.channels).fullmatch(
            channel
        ) is not None


_PATTERNS: dict[str, re.Pattern[str]] = {}


def _compiled(expression: str) -> re.Pattern[str]:
    pattern = _PATTERNS.get(expression)
    if pattern is None:
        pattern = _PATTERNS[expression] = re.compile(expression)
    return pattern


def rule_from_mapping(values: Mapping[str, Any], where: str) -> FaultRule:
    """Build and check one rule from TOML values or text; errors name ``where.key``."""
    known = {f.name for f in fields(FaultRule)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise FaultConfigError(f"{where}.{unknown[0]}: unknown key; known: {sorted(known)}")
    settings: dict[str, Any] = {}
    for key, value in values.items():
        name = f"{where}.{key}"
        if key == "channels":
            if not isinstance(value, str) or not value:
                raise FaultConfigError(f"{name}: expected a regular expression, got {value!r}")
            try:
                _compiled(value)
            except re.error as exc:
                raise FaultConfigError(f"{name}: {value!r} is not a regular expression: {exc}") from None
            settings[key] = value
        elif key == "sources":
            settings[key] = _sources(value, name)
        elif key == "seed":
            settings[key] = _integer(value, name)
        else:
            number = _number(value, name)
            high = 100.0 if key in _PERCENTS else MAX_DELAY_MS
            if not 0.0 <= number <= high:
                raise FaultConfigError(f"{name}: expected 0..{high:g}, got {value!r}")
            settings[key] = number
    return FaultRule(**settings)


def _number(value: Any, name: str) -> float:
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            raise FaultConfigError(f"{name}: expected a number, got {value!r}") from None
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        raise FaultConfigError(f"{name}: expected a number, got {value!r}")
    return float(value)


def _integer(value: Any, name: str) -> int:
    if isinstance(value, str) and value.lstrip("-").isdigit():
        value = int(value)
    if not isinstance(value, int) or isinstance(value, bool):
        raise FaultConfigError(f"{name}: expected an integer, got {value!r}")
    return value


def _sources(value: Any, name: str) -> tuple[int, ...]:
    items = [item for item in value.split("|") if item] if isinstance(value, str) else value
    if not isinstance(items, (list, tuple)):
        raise FaultConfigError(f"{name}: expected a list of source ids, got {value!r}")
    sources = tuple(_integer(item, name) for item in items)
    for source in sources:
        if not 1 <= source <= 0xFFFF:
            raise FaultConfigError(f"{name}: source id {source} is outside 1..65535")
    return sources


def parse_rules(text: str, where: str = FAULTS_ENV) -> tuple[FaultRule, ...]:
    """Rules from their text form (see the module docstring)."""
    rules = []
    for index, chunk in enumerate(part for part in text.split(";") if part.strip()):
        values: dict[str, str] = {}
        for item in chunk.split(","):
            key, equals, value = item.strip().partition("=")
            if not equals:
                raise FaultConfigError(f"{where}[{index}]: expected KEY=VALUE, got {item.strip()!r}")
            values[key.strip()] = value.strip()
        rules.append(rule_from_mapping(values, f"{where}[{index}]"))
    return tuple(rules)


def format_rules(rules: Iterable[FaultRule]) -> str:
    """The text form of ``rules``, which :func:`parse_rules` reads back; defaults are left out."""
    default = FaultRule()
    chunks = []
    for rule in rules:
        parts = []
        for f in fields(FaultRule):
            value = getattr(rule, f.name)
            if f.name != "channels" and value == getattr(default, f.name):
                continue
            if f.name == "sources":
                value = "|".join(map(str, value))
            elif isinstance(value, float) and value.is_integer():
                value = int(value)
            parts.append(f"{f.name}={value}")
        chunks.append(",".join(parts))
    return ";".join(chunks)


def header_route(datagram: bytes, first_fragments: OrderedDict[tuple[int, int], str] | None = None) -> tuple[str, int]:
    """(channel, source id) of a datagram, read from its header without checking it (see above)."""
    if len(datagram) < 8:
        return "", 0
    if datagram[3] & FLAG_FRAGMENT:
        (source_id,) = _U16.unpack_from(datagram, 4)
        if len(datagram) < FRAGMENT_HEADER_BYTES:
            return "", source_id
        (index,) = _U16.unpack_from(datagram, 6)
        key = (source_id, _U32.unpack_from(datagram, 12)[0])
        if index == 0:
            channel = _channel_at(datagram, FRAGMENT_HEADER_BYTES)
            if first_fragments is not None:
                first_fragments[key] = channel
                if len(first_fragments) > FRAGMENT_CHANNELS_REMEMBERED:
                    first_fragments.popitem(last=False)
            return channel, source_id
        return (first_fragments.get(key, "") if first_fragments is not None else ""), source_id
    (source_id,) = _U16.unpack_from(datagram, 6)
    return _channel_at(datagram, 0), source_id


def _channel_at(datagram: bytes, start: int) -> str:
    if len(datagram) < start + HEADER_BYTES:
        return ""
    length = datagram[start + 10]
    return datagram[start + HEADER_BYTES : start + HEADER_BYTES + length].decode("ascii", "replace")


class FaultyTransport(Transport):
    """Wraps any transport; applies ``rules`` to what it receives. Sending is untouched.

    ``stats`` counts per outcome: ``matched``, ``lost``, ``corrupted``, ``duplicated``,
    ``reordered``, ``delayed``, ``overflow`` (dropped because the hold queue was full).
    ``now_ns`` is the clock releases are timed by (monotonic; injected for tests).
    """

    def __init__(
        self,
        inner: Transport,
        rules: Iterable[FaultRule],
        *,
        now_ns: Callable[[], int] = time.monotonic_ns,
        max_held: int = MAX_HELD_DATAGRAMS,
        report: Callable[[str], None] | None = None,
    ) -> None:
        """``report``, if given, is handed :meth:`summary` on close (a process's log line)."""
        self.inner = inner
        self._report = report
        self.rules = tuple(rules)
        self.stats: Counter[str] = Counter()
        self._rngs = [random.Random(rule.seed) for rule in self.rules]
        self._now_ns = now_ns
        self._max_held = max_held
        self._held: list[tuple[int, int, bytes]] = []  # (due_ns, arrival order, datagram)
        self._order = itertools.count()
        self._first_fragments: OrderedDict[tuple[int, int], str] = OrderedDict()
        self._deliver: Deliver | None = None
        self._passed = 0

    def send(self, channel: str, datagram: bytes) -> None:
        self.inner.send(channel, datagram)

    def listen(self, channel: str, kernel_timestamps: bool = False, wake: bool = True) -> None:
        self.inner.listen(channel, kernel_timestamps, wake)

    def listen_all(self, wake: bool = True) -> None:
        self.inner.listen_all(wake)

    def held(self) -> int:
        """Datagrams waiting for their release time."""
        return len(self._held)

    def receive(self, deliver: Deliver, timeout_s: float, budget: int) -> int:
        handled = self._release(deliver, budget)
        if handled >= budget:
            return handled
        wait = max(timeout_s, 0.0) if handled == 0 else 0.0
        if self._held:
            wait = min(wait, max(0.0, (self._held[0][0] - self._now_ns()) / 1e9))
        self._deliver, self._passed = deliver, 0
        try:
            self.inner.receive(self._arrive, wait, budget - handled)
        finally:
            self._deliver = None
        handled += self._passed
        return handled + self._release(deliver, budget - handled)

    def _release(self, deliver: Deliver, budget: int) -> int:
        held = self._held
        if not held:
            return 0
        now = self._now_ns()
        released = 0
        while held and held[0][0] <= now and released < budget:
            # Without a kernel timestamp: the bus stamps the arrival now, which is what a delay means.
            deliver(heapq.heappop(held)[2])
            released += 1
        return released

    def _arrive(self, datagram: bytes, *stamp: int) -> None:
        channel, source_id = header_route(datagram, self._first_fragments)
        for index, rule in enumerate(self.rules):
            if rule.matches(channel, source_id):
                self._apply(rule, self._rngs[index], datagram, stamp)
                return
        self._pass(datagram, stamp)

    def _pass(self, datagram: bytes, stamp: tuple[int, ...]) -> None:
        assert self._deliver is not None
        self._deliver(datagram, *stamp)
        self._passed += 1

    def _apply(self, rule: FaultRule, rng: random.Random, datagram: bytes, stamp: tuple[int, ...]) -> None:
        stats = self.stats
        stats["matched"] += 1
        if rng.random() * 100.0 < rule.loss_pct:
            stats["lost"] += 1
            return
        if rng.random() * 100.0 < rule.corrupt_pct:
            datagram = flip_bit(datagram, rng)
            stats["corrupted"] += 1
        copies = 1
        if rng.random() * 100.0 < rule.duplicate_pct:
            copies = 2
            stats["duplicated"] += 1
        for _ in range(copies):
            delay_ms = rule.delay_ms + (rng.uniform(0.0, rule.jitter_ms) if rule.jitter_ms else 0.0)
            if rng.random() * 100.0 < rule.reorder_pct:
                delay_ms += rule.reorder_ms
                stats["reordered"] += 1
            if delay_ms <= 0.0:
                self._pass(datagram, stamp)
            elif len(self._held) >= self._max_held:
                stats["overflow"] += 1
            else:
                stats["delayed"] += 1
                heapq.heappush(self._held, (self._now_ns() + int(delay_ms * 1e6), next(self._order), datagram))

    def summary(self) -> str:
        """What the rules did so far, e.g. ``link faults: 5000 matched, lost 1002, delayed 3998``."""
        counts = ", ".join(f"{name} {count}" for name, count in self.stats.items() if name != "matched")
        return f"link faults: {self.stats['matched']} matched" + (f", {counts}" if counts else "")

    def close(self) -> None:
        self._held.clear()
        self.inner.close()
        if self._report is not None:
            self._report(self.summary())


def flip_bit(datagram: bytes, rng: random.Random) -> bytes:
    """``datagram`` with one bit, chosen by ``rng``, inverted."""
    if not datagram:
        return datagram
    buf = bytearray(datagram)
    buf[rng.randrange(len(buf))] ^= 1 << rng.randrange(8)
    return bytes(buf)


def wrap(transport: Transport, text: str, where: str) -> Transport:
    """``transport`` behind the rules of ``text`` (a URL option or the environment); a bad rule
    closes it and raises UrlError naming ``where``, as any other bad bus setting does."""
    try:
        rules = parse_rules(text, where)
    except FaultConfigError as exc:
        transport.close()
        raise UrlError(str(exc)) from None
    if not rules:
        return transport
    return FaultyTransport(transport, rules, report=lambda line: print(f"{line} ({where})", file=sys.stderr))
