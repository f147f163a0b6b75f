"""``make fuzz``: the receive-path fuzzer of test_fuzz.py over a million datagrams (or ``--inputs``).

Same generators and receivers as the test (genuine, replayed and skewed messages; bit flips,
byte writes, truncation, header rewrites, random bytes, splices, mutated fragments, hostile
msgpack bodies sealed with the right key), in both signed and unsigned mode, through the sans-IO
path (reassembly, codec, body decoder) and a Bus. Run in chunks, each with its own seed so a
finding is reproducible on its own: ``fuzz(signed, datagrams, seed)`` from test_fuzz.py.

Exits 1 on the first finding (a datagram that raised anything but ProtocolError, or one the Bus
did not account for), printing the datagram; else prints the totals.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from collections.abc import Sequence

from tests.protocol.test_fuzz import fuzz

CAMPAIGN_SEED = 0xCA4A_2005  # not the test's seed: the campaign covers new ground
CHUNK = 100_000


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="make fuzz", description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", type=int, default=1_000_000, help="datagrams in all, half per mode")
    parser.add_argument("--seed", type=int, default=CAMPAIGN_SEED, help="seed of the first chunk")
    args = parser.parse_args(argv)
    if args.inputs < 2:
        parser.error("--inputs must be at least 2")
    outcomes: Counter[str] = Counter()
    bus_rejects: Counter[str] = Counter()
    delivered = 0
    done = 0
    left = {True: (args.inputs + 1) // 2, False: args.inputs // 2}  # signed, unsigned
    started = time.monotonic()
    chunk_seed = args.seed
    while any(left.values()):
        for signed in (True, False):
            size = min(CHUNK, left[signed])
            if size == 0:
                continue
            try:
                sans_io, bus = fuzz(signed, size, chunk_seed)
            except AssertionError as finding:
                print(f"FINDING after {done:,} inputs: {finding}", file=sys.stderr)
                return 1
            left[signed] -= size
            done += size
            outcomes.update(sans_io.outcomes)
            for (_source, reason), count in bus.bus.rejects.items():
                bus_rejects[reason] += count
            delivered += bus.typed_accepted
            mode = "signed" if signed else "unsigned"
            print(f"{done:>9,} inputs  {time.monotonic() - started:7.1f} s  chunk seed {chunk_seed:#x} {mode}: ok")
        chunk_seed += 1
    elapsed = time.monotonic() - started
    print(f"\n{done:,} inputs in {elapsed:.1f} s ({done / elapsed:,.0f}/s): no findings")
    print(f"sans-IO outcomes: {dict(outcomes.most_common())}")
    print(f"Bus: {delivered:,} typed messages delivered; rejects by reason: {dict(bus_rejects.most_common())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
