"""`rascal stop | pause | resume`: an operator's order to control, repeated until control obeys.

One datagram can be lost, and one stamped by an unsynchronised laptop can be rejected as stale or
from the future while the tool says "published". So the tool first synchronises to the time
master, then sends the order every ``REPEAT_S`` until control's own actuator commands show it in
force (their ``stop_reason`` starts with "estop" or "pause"; after a resume, with neither), and
says which happened. The order is repeated, not the effect assumed.

Control obeys only a STOP signed by a source with authority on it (protocol/authority.py): with
the deployment's master key file the tool signs as the operator (``OPERATOR_SOURCE_ID``), with a
module key file as that module (authority as the deployment gives it). Given the deployment's
authority table, a tool with the master file also enforces it on what it hears, so no forged
time-sync reply can skew the clock its orders are stamped with (and have them refused as stale).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from protocol import channels
from protocol.auth import Keyring, default_keyring
from protocol.authority import OPERATOR_SOURCE_ID, Authority
from protocol.codec import Envelope
from protocol.messages import ActuatorCommand, StopCommand, StopMode
from rascal.bustools import tool_bus
from rascal.runtime.timeclient import MIN_REQUEST_PERIOD_NS

REPEAT_S = 0.2
SYNC_POLL_S = MIN_REQUEST_PERIOD_NS / 1e9  # as often as the time client will ask: synced in tens of ms
HOLD_PREFIXES = ("estop", "pause")  # control's stop_reason while an operator stop holds


@dataclass(frozen=True)
class OrderResult:
    confirmed: bool
    sends: int
    elapsed_s: float
    synced: bool
    last_reason: str | None  # control's latest stop_reason seen, None when control was not heard


def in_force(mode: StopMode, stop_reason: str) -> bool:
    """Whether an actuator command with ``stop_reason`` shows ``mode`` obeyed."""
    if mode is StopMode.RUN:
        return not stop_reason.startswith(HOLD_PREFIXES)
    return stop_reason.startswith("estop" if mode is StopMode.ESTOP else HOLD_PREFIXES)


def order_source_id(keyring: Keyring) -> int | None:
    """Whom an order comes from: the operator with the master file, a module key file's own
    source, else (a legacy key file, no authority) a tool's random id."""
    if keyring.signing_master is not None:
        return OPERATOR_SOURCE_ID
    return keyring.source_id


def give_order(
    url: str | None,
    mode: StopMode,
    reason: str,
    timeout_s: float,
    sync_s: float = 1.0,
    authority: dict[str, tuple[int, ...]] | None = None,
) -> OrderResult:
    """Synchronise (for up to ``sync_s``), then send the order until control obeys or ``timeout_s``.
    ``authority``: the deployment's table (channel -> source ids), enforced with a master file."""
    keyring = default_keyring()
    bus, time_client = tool_bus(url, keyring=keyring, source_id=order_source_id(keyring))
    if authority is not None and keyring.signing_master is not None:
        bus.enforce(Authority.derive(authority, keyring.signing_master))
    start = time.monotonic()
    sends = 0
    heard: list[str] = []

    def on_command(command: ActuatorCommand, _envelope: Envelope) -> None:
        # Heard after the first send: sent before control had the order, it still shows the old
        # mode, which confirms nothing unless the old mode was the one asked for.
        if sends:
            heard.append(command.stop_reason)

    bus.subscribe(channels.ACTUATOR_COMMAND, on_command)
    try:
        while not bus.clock.synced and time.monotonic() - start < sync_s:
            time_client.request()
            bus.poll(SYNC_POLL_S)
        synced = bus.clock.synced
        order = StopCommand(int(mode), reason)
        while time.monotonic() - start < timeout_s:
            bus.publish(channels.STOP, order)
            sends += 1
            until = time.monotonic() + REPEAT_S
            while (left := until - time.monotonic()) > 0 and not (heard and in_force(mode, heard[-1])):
                time_client.request()
                bus.poll(min(left, SYNC_POLL_S))
            if heard and in_force(mode, heard[-1]):
                return OrderResult(True, sends, time.monotonic() - start, synced, heard[-1])
        return OrderResult(False, sends, time.monotonic() - start, synced, heard[-1] if heard else None)
    finally:
        bus.close()


def describe(mode: StopMode, result: OrderResult) -> str:
    """One line for the operator."""
    what = {StopMode.ESTOP: "e-stop", StopMode.PAUSE: "pause", StopMode.RUN: "resume"}[mode]
    clock = "clock synchronised" if result.synced else "no time master answered: sent on this host's clock"
    sent = f"{result.sends} order(s)"
    if result.confirmed:
        return f"control obeyed the {what} after {sent} in {result.elapsed_s * 1000:.0f} ms ({clock})"
    if result.last_reason is None:
        return f"{what} NOT confirmed: no actuator command heard in {result.elapsed_s:.1f} s ({sent}; {clock})"
    return f"{what} NOT confirmed in {result.elapsed_s:.1f} s ({sent}; {clock}): control says {result.last_reason!r}"
