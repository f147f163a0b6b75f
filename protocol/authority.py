"""Command authority: which sources may publish on the channels that move, stop or steer the
vehicle, proved by an Ed25519 signature of that source (protocol/signing.py).

Every MAC-key holder can put any message on the bus under any source id; on a governed channel a
receiver that holds an authority table (a module key file) takes a message only when it carries
a valid signature by its ``source_id`` and that source has authority on the channel. Anything
else is rejected as ``unauthorized`` (SPEC.md section 7).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from protocol import channels
from protocol.errors import ProtocolError, Reason
from protocol.messages import TimeSyncKind
from protocol.signing import PUBLIC_KEY_BYTES, Signed, Verifier, public_key_of

# The source id of the operator's tools (`rascal stop | pause | resume` with the master file).
OPERATOR_SOURCE_ID = 0xFFF0
GOVERNED_CHANNELS = (channels.ACTUATOR_COMMAND, channels.PATH, channels.STOP, channels.CONFIG, channels.TIME_SYNC)
# Every node hears every time-sync reply but uses only those echoing its own requests: the one
# client that uses a reply verifies it (rascal/runtime/timeclient.py), not every node on receipt.
VERIFIED_BY_HANDLER = frozenset({channels.TIME_SYNC})
VERIFIED_ON_RECEIPT = frozenset(GOVERNED_CHANNELS) - VERIFIED_BY_HANDLER
GOVERNED = frozenset(GOVERNED_CHANNELS)


def needs_signature(channel: str, msg: Any) -> bool:
    """Whether a sender signs ``msg`` on ``channel``: everything on a governed channel except a
    time-sync request (which only draws a reply that no one but its sender uses)."""
    if channel == channels.TIME_SYNC:
        return bool(msg.kind != TimeSyncKind.REQUEST)
    return channel in GOVERNED


@dataclass(frozen=True)
class Authority:
    """Sources with authority per governed channel, and the public key of each of them."""

    table: Mapping[str, frozenset[int]]
    public_keys: Mapping[int, bytes]
    _verifiers: dict[int, Verifier] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        unknown = set(self.table) - GOVERNED
        if unknown:
            raise ValueError(f"no authority on {sorted(unknown)}: governed channels are {list(GOVERNED_CHANNELS)}")
        holders = set().union(*self.table.values())
        missing = holders - set(self.public_keys)
        if missing:
            raise ValueError(f"sources {sorted(missing)} hold authority but have no public key")
        if any(len(key) != PUBLIC_KEY_BYTES for key in self.public_keys.values()):
            raise ValueError(f"a public key is {PUBLIC_KEY_BYTES} bytes")
        object.__setattr__(self, "_verifiers", {sid: Verifier(key) for sid, key in self.public_keys.items()})

    @classmethod
    def derive(cls, table: Mapping[str, Iterable[int]], signing_master: bytes) -> Authority:
        """The authority of ``table`` (channel -> source ids), public keys derived from the master."""
        frozen = {channel: frozenset(sources) for channel, sources in table.items()}
        holders = sorted(set().union(*frozen.values()))
        return cls(frozen, {sid: public_key_of(signing_master, sid) for sid in holders})

    def check(self, channel: str, source_id: int, signed: Signed | None) -> None:
        """Raise ProtocolError(UNAUTHORIZED) unless ``source_id`` has authority on ``channel``
        and ``signed`` is its valid signature. The table is asked first: a source without
        authority costs no signature check."""
        if source_id not in self.table.get(channel, ()):
            raise ProtocolError(Reason.UNAUTHORIZED, f"source {source_id} has no authority on {channel}", source_id)
        if signed is None:
            raise ProtocolError(Reason.UNAUTHORIZED, f"{channel} without a signature", source_id)
        if not self._verifiers[source_id].verify(signed):
            raise ProtocolError(Reason.UNAUTHORIZED, f"{channel}: bad signature", source_id)
