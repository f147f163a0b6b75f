"""What command authority costs: Ed25519 signing and verifying per message, and the CPU it adds.

In-process, one core: the time per message of publishing an ActuatorCommand with the MAC only
and with the signature, and of receiving one on a node that enforces authority (the signature
verified in Python) against a plain MAC-checked message (the C fast path where built). The CPU
rows scale those per-message differences to the rates the stack runs: control publishing at
50 Hz, each receiver of its commands, and time sync, where a client verifies only the replies it
uses (two a second once settled, ten before).

Usage: ``python -m benchmarks.bench_authority`` (also printed by ``benchmarks.bench_bus``).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence

from rich.console import Console

from benchmarks.report import Table, machine_line, print_table
from protocol import channels, fastpath
from protocol.auth import Keyring
from protocol.authority import Authority
from protocol.messages import ActuatorCommand
from protocol.signing import Signed
from protocol.transport import MemTransport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import ManualClock

COMMAND = ActuatorCommand(0.35, 0.0, -0.04, "")
CONTROL_HZ = 50.0
SETTLED_REPLIES_HZ = 2.0  # rascal.runtime.timeclient: one exchange per 500 ms once settled
UNSETTLED_REPLIES_HZ = 10.0
ROUNDS = 7
PER_ROUND = 400


def _us_per_call(fn: Callable[[], object]) -> float:
    """Median over ROUNDS of the mean time of PER_ROUND calls, in microseconds."""
    rounds = []
    for _ in range(ROUNDS):
        start = time.perf_counter()
        for _ in range(PER_ROUND):
            fn()
        rounds.append((time.perf_counter() - start) / PER_ROUND * 1e6)
    return statistics.median(rounds)


def _node(hub: str, source_id: int, keyring: Keyring) -> Bus:
    bus = Bus(MemTransport(hub), source_id, keyring, ManualClock())
    bus.subscribe(channels.ACTUATOR_COMMAND, lambda _msg, _env: None)
    return bus


def _receive_us(sender: Bus, receiver: Bus) -> float:
    """Per message: the receive path (Bus._on_datagram, as a poll calls it) of one command,
    encoded beforehand and numbered afresh so that the replay window takes each."""
    data = [sender.encode(channels.ACTUATOR_COMMAND, COMMAND)[1] for _ in range(ROUNDS * PER_ROUND)]
    feed = iter(data)
    return _us_per_call(lambda: receiver._on_datagram(next(feed)))


def measure() -> dict[str, float]:
    master = Keyring.generate()
    legacy = Keyring(master.keys, master.active)  # MAC only: as before command authority
    authority = Authority.derive({channels.ACTUATOR_COMMAND: [40], channels.TIME_SYNC: [1]}, master.signing_master)  # type: ignore[arg-type]
    signer = master.signer(40)
    assert signer is not None
    covered = bytes(81)  # header, channel and body of the ActuatorCommand above
    signed = Signed(covered, signer.sign(covered))
    mac_sender, mac_receiver = _node("bench-authority-mac", 40, legacy), _node("bench-authority-mac", 5, legacy)
    signed_sender = _node("bench-authority-signed", 40, master.for_module(40, authority))
    enforcing = _node("bench-authority-signed", 5, master.for_module(5, authority))
    return {
        "sign": _us_per_call(lambda: signer.sign(covered)),
        "verify": _us_per_call(lambda: authority.check(channels.ACTUATOR_COMMAND, 40, signed)),
        "encode_mac": _us_per_call(lambda: mac_sender.encode(channels.ACTUATOR_COMMAND, COMMAND)),
        "encode_signed": _us_per_call(lambda: signed_sender.encode(channels.ACTUATOR_COMMAND, COMMAND)),
        "receive_mac": _receive_us(mac_sender, mac_receiver),
        "receive_enforced": _receive_us(signed_sender, enforcing),
    }


def authority_table(costs: dict[str, float]) -> Table:
    table = Table(f"command authority: cost per message and CPU added ({fastpath.describe()})", ["what", "value"])
    table.add("Ed25519 sign (81 B ActuatorCommand)", f"{costs['sign']:.1f} us")
    table.add("Ed25519 verify, authority table first", f"{costs['verify']:.1f} us")
    table.add("publish-side encode, MAC only", f"{costs['encode_mac']:.1f} us")
    table.add("publish-side encode, signed + MAC", f"{costs['encode_signed']:.1f} us")
    table.add("receive, MAC only", f"{costs['receive_mac']:.1f} us")
    table.add("receive, signature checked (enforcing node)", f"{costs['receive_enforced']:.1f} us")
    signing = (costs["encode_signed"] - costs["encode_mac"]) * CONTROL_HZ / 1e4
    verifying = (costs["receive_enforced"] - costs["receive_mac"]) * CONTROL_HZ / 1e4
    table.add("control at 50 Hz: signing, % of one core", f"{signing:.3f} %")
    table.add("each receiver of control's 50 Hz, % of one core", f"{verifying:.3f} %")
    table.add("time client settled (2 replies/s), % of one core", f"{costs['verify'] * SETTLED_REPLIES_HZ / 1e4:.4f} %")
    table.add(
        "time client settling (10 replies/s), % of one core", f"{costs['verify'] * UNSETTLED_REPLIES_HZ / 1e4:.4f} %"
    )
    return table


def main(argv: Sequence[str] | None = None) -> int:
    del argv
    console = Console()
    console.print(machine_line("command authority"), markup=False, highlight=False, soft_wrap=True)
    print_table(console, authority_table(measure()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
