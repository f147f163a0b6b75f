"""Bus benchmark: rascal's Bus beside raw UDP + msgpack (the floor) and LCM's Python binding.

Everything is measured side by side in one run, between two processes, on loopback only:

1. one-way latency (p50, p99) of a ~300 B ObstacleList in two regimes, rounds interleaved;
2. sustained throughput at 20k, 50k and 80k msg/s: achieved send rate, received, loss;
3. what command authority costs (benchmarks/bench_authority.py, in-process): Ed25519 signing and
   verifying per command, and the CPU they add at control's 50 Hz.

Latency regimes: "cold" paces 1,000 msg/s and the subscriber sleeps in poll/select between
messages, so every message wakes a sleeping process with cold caches. "hot" is the setting of
classic ping-pong tests: the publisher spins a fixed 200 us between sends (one message in flight)
and the subscriber busy-polls without ever sleeping, so the per-message cost of encoding, sending
and decoding dominates instead of process wake-up.

Timing: the publisher stamps ``time.monotonic_ns()`` just before encoding and the subscriber's
handler reads it again after full decode; CLOCK_MONOTONIC is system-wide, so the difference is
the one-way latency. Raw UDP and LCM carry the stamp in the body. rascal carries it in the
header's ``t_pub_ns``: both rascal processes get a clock whose shared time *is* the monotonic
clock (benchmarks.bus_peers.MonotonicClock), so the bus's own stamp is the send time.

Network: as root the benchmark re-executes itself in a fresh network namespace that has only
``lo`` (multicast routed to it), because LCM multicasts along the default route. Without root,
or when the namespace cannot be made, it runs on the host's loopback and skips LCM.

Usage: ``python -m benchmarks.bench_bus`` (``--inside NAME`` is the re-executed half).
"""

from __future__ import annotations

import argparse
import importlib.util
import itertools
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType, ModuleType

from rich.console import Console

from benchmarks.bench_authority import authority_table
from benchmarks.bench_authority import measure as measure_authority
from benchmarks.bus_peers import Contender, Lcm, Rascal, RawUdp, generate_lcm_types
from benchmarks.harness import BenchError, PairResult, run_pair
from benchmarks.netns import (
    NamespaceError,
    loopback_namespace,
    raise_rmem_max,
    run_in_namespace,
    unavailable_reason,
)
from benchmarks.report import Table, machine_line, print_table
from protocol import fastpath
from protocol.auth import Keyring
from protocol.channels import DEFAULT_PORT_SPAN
from protocol.transport import RECV_BUFFER_BYTES

PROJECT_ROOT = Path(__file__).resolve().parents[1]

# Rounds interleave the contenders and both regimes, so a burst of load from elsewhere on the
# machine lands on all of them instead of skewing one column.
LATENCY_ROUNDS = 3
LATENCY_WARMUP = 300
LATENCY_SAMPLES_PER_ROUND = 1_000
THROUGHPUT_RATES_HZ = (20_000, 50_000, 80_000)
THROUGHPUT_SECONDS = 2.5
ACCEPT_RATE_HZ = 80_000
FLOOR_FACTOR = 1.6
# A throughput run only counts as "at" its target if the publisher really got close to it.
RATE_TOLERANCE = 0.95
SIZE_RANGE = (300, 370)
NAMESPACE_RMEM_MAX = 16 * 1024 * 1024
# The re-executed half runs under a minute; this bound only catches a hang.
INSIDE_TIMEOUT_S = 180.0

RAW_GROUP = "239.255.77.68"
RASCAL_GROUP = "239.255.77.67"
LCM_GROUP = "239.255.76.67"
# Every measurement gets fresh ports, so no datagram of an earlier run can reach a later one;
# the stride covers the ports rascal spreads channels over.
BASE_PORT = 27_000
PORT_STRIDE = DEFAULT_PORT_SPAN

RAW, LCM, SIGNED, UNSIGNED = "raw", "lcm", "signed", "unsigned"


@dataclass(frozen=True)
class Regime:
    """How one latency table is measured (see the module docstring)."""

    name: str
    rate_hz: int
    # Publisher spins between sends and the subscriber busy-polls, instead of both sleeping.
    busy: bool

    def setting(self) -> str:
        if self.busy:
            gap_us = 1e6 / self.rate_hz
            return f"one in flight: publisher spins {gap_us:.0f} us between sends, subscriber busy-polls"
        return "paced, subscriber sleeping in poll/select between messages"


COLD = Regime("cold", 1_000, busy=False)
# 200 us between sends is several times every contender's hot p50 (tens of us), so a message is
# normally handled before the next one is sent.
HOT = Regime("hot", 5_000, busy=True)
REGIMES = (COLD, HOT)


@dataclass
class LatencyRow:
    """Latencies of one contender pooled over all rounds."""

    name: str
    wire_bytes: int
    samples_us: list[float] = field(default_factory=list)
    lost: int = 0
    failed_rounds: int = 0

    def add(self, result: PairResult | None) -> None:
        if result is None:
            self.failed_rounds += 1
            return
        # The first messages pay for imports, allocation and cold caches; they are not the bus.
        self.samples_us += [ns / 1e3 for ns in result.subscriber.latencies_ns[LATENCY_WARMUP:]]
        self.lost += result.lost

    def p50(self) -> float | None:
        return self._percentile(50)

    def p99(self) -> float | None:
        return self._percentile(99)

    def _percentile(self, p: int) -> float | None:
        if len(self.samples_us) < 2:
            return None
        return statistics.quantiles(self.samples_us, n=100, method="inclusive")[p - 1]


LatencyRows = dict[str, LatencyRow]


@dataclass(frozen=True)
class ThroughputRow:
    key: str
    name: str
    target_hz: int
    result: PairResult | None


class Lineup:
    """Builds each contender afresh, on its own ports, for every measurement."""

    def __init__(self, keyring: Keyring, lcm_types: ModuleType | None) -> None:
        self._keyring = keyring
        self._lcm_types = lcm_types
        self._ports = itertools.count(BASE_PORT, PORT_STRIDE)

    def kinds(self) -> list[str]:
        return [RAW, *([LCM] if self._lcm_types else []), SIGNED, UNSIGNED]

    def build(self, key: str) -> Contender:
        port = next(self._ports)
        if key == RAW:
            return RawUdp(RAW_GROUP, port)
        if key == LCM and self._lcm_types is not None:
            provider = f"udpm://{LCM_GROUP}:{port}?ttl=0&recv_buf_size={RECV_BUFFER_BYTES}"
            return Lcm(provider, self._lcm_types)
        if key in (SIGNED, UNSIGNED):
            keyring = self._keyring if key == SIGNED else None
            return Rascal(f"udpm://{RASCAL_GROUP}:{port}?ttl=0", keyring, name=f"rascal Bus, {key}")
        raise ValueError(f"no contender {key!r}")


# -- measurements -----------------------------------------------------------------------------


def _attempt(label: str, run: Callable[[], PairResult], log: Console) -> PairResult | None:
    """One measurement; a failed one is reported and left out rather than ending the run."""
    started = time.monotonic()
    try:
        result = run()
    except BenchError as exc:
        _say(log, f"  {label}: FAILED: {exc}")
        return None
    _say(log, f"  {label}: {time.monotonic() - started:.1f} s")
    return result


def measure_latency(lineup: Lineup, log: Console) -> dict[Regime, LatencyRows]:
    rows: dict[Regime, LatencyRows] = {regime: {} for regime in REGIMES}
    for round_index in range(1, LATENCY_ROUNDS + 1):
        for regime in REGIMES:
            for key in lineup.kinds():
                contender = lineup.build(key)
                row = rows[regime].setdefault(key, LatencyRow(contender.name, contender.wire_bytes()))
                label = f"latency {regime.name} {contender.name}, round {round_index}/{LATENCY_ROUNDS}"
                row.add(_attempt(label, lambda c=contender, r=regime: _latency_pair(c, r), log))
    return rows


def _latency_pair(contender: Contender, regime: Regime) -> PairResult:
    count = LATENCY_WARMUP + LATENCY_SAMPLES_PER_ROUND
    return run_pair(contender, regime.rate_hz, count, True, busy=regime.busy)


def measure_throughput(lineup: Lineup, log: Console) -> list[ThroughputRow]:
    rows = []
    for rate_hz in THROUGHPUT_RATES_HZ:
        count = int(rate_hz * THROUGHPUT_SECONDS)
        for key in (k for k in lineup.kinds() if k != UNSIGNED):
            contender = lineup.build(key)
            label = f"throughput {contender.name} @ {rate_hz:,}/s"
            result = _attempt(label, lambda c=contender, r=rate_hz, n=count: run_pair(c, r, n, False), log)
            rows.append(ThroughputRow(key, contender.name, rate_hz, result))
    return rows


# -- report -----------------------------------------------------------------------------------


def _us(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def latency_table(regime: Regime, rows: LatencyRows) -> Table:
    table = Table(
        f"One-way latency, {regime.name}: ObstacleList (4 obstacles) at {regime.rate_hz:,} msg/s, {regime.setting()}; "
        f"{LATENCY_ROUNDS} interleaved rounds of {LATENCY_SAMPLES_PER_ROUND:,} after {LATENCY_WARMUP} warm-up",
        ["contender", "datagram B", "p50 us", "p99 us", "samples", "lost"],
    )
    for row in rows.values():
        lost = str(row.lost) + (f" ({row.failed_rounds} rounds failed)" if row.failed_rounds else "")
        table.add(row.name, str(row.wire_bytes), _us(row.p50()), _us(row.p99()), f"{len(row.samples_us):,}", lost)
    return table


def throughput_table(rows: list[ThroughputRow]) -> Table:
    table = Table(
        f"Sustained throughput, one publisher -> one subscriber, {THROUGHPUT_SECONDS} s per run",
        ["contender", "target msg/s", "achieved msg/s", "sent", "received", "lost %", "send drops"],
    )
    for row in rows:
        if row.result is None:
            table.add(row.name, f"{row.target_hz:,}", "failed", "-", "-", "-", "-")
            continue
        pub, sub = row.result.publisher, row.result.subscriber
        lost_pct = 100.0 * row.result.lost / pub.sent if pub.sent else 0.0
        table.add(
            row.name,
            f"{row.target_hz:,}",
            f"{pub.rate_hz:,.0f}",
            f"{pub.sent:,}",
            f"{sub.received:,}",
            f"{lost_pct:.2f}",
            f"{pub.send_drops:,}",
        )
    return table


def acceptance(latency: dict[Regime, LatencyRows], throughput: list[ThroughputRow]) -> list[tuple[str, str]]:
    """(PASS/FAIL/SKIP, description) for each acceptance criterion."""
    cold, hot = latency[COLD], latency[HOT]
    return [
        _lcm_check(COLD, cold),
        _floor_check(COLD, cold),
        _zero_loss_check(throughput),
        _lcm_check(HOT, hot),
        _floor_check(HOT, hot),
    ]


def _lcm_check(regime: Regime, latency: LatencyRows) -> tuple[str, str]:
    label = f"[{regime.name}] rascal signed p50 <= LCM p50"
    if LCM not in latency:
        return "SKIP", f"{label}: LCM not measured"
    signed, lcm = latency[SIGNED].p50(), latency[LCM].p50()
    ok = signed is not None and lcm is not None and signed <= lcm
    return _verdict(ok), f"{label}: {_us(signed)} us vs {_us(lcm)} us"


def _floor_check(regime: Regime, latency: LatencyRows) -> tuple[str, str]:
    signed, raw = latency[SIGNED].p50(), latency[RAW].p50()
    bound = None if raw is None else FLOOR_FACTOR * raw
    ok = signed is not None and bound is not None and signed <= bound
    label = f"[{regime.name}] rascal signed p50 <= {FLOOR_FACTOR}x raw floor p50"
    return _verdict(ok), f"{label}: {_us(signed)} us vs {FLOOR_FACTOR} x {_us(raw)} = {_us(bound)} us"


def _zero_loss_check(throughput: list[ThroughputRow]) -> tuple[str, str]:
    label = f"rascal signed at {ACCEPT_RATE_HZ:,} msg/s: 0 loss"
    row = next((r for r in throughput if r.key == SIGNED and r.target_hz == ACCEPT_RATE_HZ), None)
    if row is None or row.result is None:
        return "FAIL", f"{label}: run failed"
    pub = row.result.publisher
    ok = row.result.lost == 0 and pub.rate_hz >= RATE_TOLERANCE * ACCEPT_RATE_HZ
    detail = f"achieved {pub.rate_hz:,.0f}/s, received {row.result.subscriber.received:,} of {pub.sent:,}"
    return _verdict(ok), f"{label}: {detail}"


def _verdict(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def size_line(rows: LatencyRows) -> str:
    size = rows[SIGNED].wire_bytes
    low, high = SIZE_RANGE
    verdict = "within" if low <= size <= high else "OUTSIDE"
    return (
        f"rascal signed ObstacleList datagram: {size} B ({verdict} the {low}-{high} B target); "
        f"receive and send path: {fastpath.describe()}"
    )


# -- running ----------------------------------------------------------------------------------


def run_benchmark(where: str, lcm_skip: str | None, notes: list[str]) -> int:
    console = Console()
    log = Console(stderr=True)
    machine = machine_line("bus", where)
    with tempfile.TemporaryDirectory(prefix="rascal-bench-lcm-") as tmp:
        lcm_types = None
        if lcm_skip is None:
            lcm_types, lcm_skip = _load_lcm(Path(tmp))
        lineup = Lineup(Keyring.generate(), lcm_types)
        _say(log, "measuring (under a minute)...")
        latency = measure_latency(lineup, log)
        throughput = measure_throughput(lineup, log)
    skipped = [f"LCM skipped: {lcm_skip}"] if lcm_skip else []
    lines = [machine, *notes, buffer_line(), *skipped, size_line(latency[COLD])]
    _say(console, "\n".join([*lines, ""]))
    for regime in REGIMES:
        print_table(console, latency_table(regime, latency[regime]))
    print_table(console, throughput_table(throughput))
    print_table(console, authority_table(measure_authority()))
    _say(console, "\n".join(f"{verdict}  {text}" for verdict, text in acceptance(latency, throughput)))
    return 0


def _say(console: Console, text: str) -> None:
    # Verbatim and unwrapped: these lines are read in logs as often as on a terminal.
    console.print(text, markup=False, highlight=False, soft_wrap=True)


def _load_lcm(tmp: Path) -> tuple[ModuleType | None, str | None]:
    """The generated LCM types, or why the LCM column is skipped."""
    if importlib.util.find_spec("lcm") is None:
        return None, "the lcm package is not installed (pip install -e '.[bench]')"
    try:
        return generate_lcm_types(tmp), None
    except subprocess.CalledProcessError as exc:
        return None, f"lcm-gen failed: {exc.stderr.decode(errors='replace').strip()}"
    except (OSError, subprocess.SubprocessError) as exc:
        return None, f"lcm-gen failed: {exc}"


def buffer_line() -> str:
    mib = RECV_BUFFER_BYTES // 2**20
    how = "SO_RCVBUFFORCE" if os.geteuid() == 0 else "SO_RCVBUF, capped by net.core.rmem_max"
    return (
        f"receive buffers: {mib} MiB asked by rascal and raw UDP ({how}); "
        f"LCM recv_buf_size={mib} MiB (LCM uses SO_RCVBUF, capped by net.core.rmem_max)"
    )


def _exit_on_term(signum: int, _frame: FrameType | None) -> None:
    # Turn SIGTERM into SystemExit so finally blocks stop children and remove temporary files.
    sys.exit(128 + signum)


def main(argv: Sequence[str] | None = None) -> int:
    try:
        return _run(argv)
    except KeyboardInterrupt:
        # Children and the namespace were already cleaned up by the finally blocks on the way out.
        print("interrupted", file=sys.stderr)
        return 130


def _run(argv: Sequence[str] | None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_bus", description=__doc__.splitlines()[0])
    parser.add_argument("--inside", metavar="NAMESPACE", help="already inside the benchmark's namespace")
    args = parser.parse_args(argv)
    signal.signal(signal.SIGTERM, _exit_on_term)
    if args.inside:
        where = f"network namespace {args.inside} (lo only)"
        return run_benchmark(where, None, [raise_rmem_max(NAMESPACE_RMEM_MAX)])
    reason = unavailable_reason()
    if reason is None:
        name = f"rascal-bench-{os.getpid()}"
        try:
            with loopback_namespace(name):
                command = [sys.executable, "-m", "benchmarks.bench_bus", "--inside", name]
                return run_in_namespace(name, command, INSIDE_TIMEOUT_S, PROJECT_ROOT)
        except NamespaceError as exc:
            reason = str(exc)
    skip = f"{reason}; LCM multicasts via the default route, so it runs only in a private network namespace"
    return run_benchmark("host loopback", skip, [])


if __name__ == "__main__":
    sys.exit(main())
