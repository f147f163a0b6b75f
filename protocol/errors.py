"""The one error a peer can cause.

Anything wrong with bytes that came from the network raises :class:`ProtocolError` with a
machine-readable :class:`Reason`. The transport counts it per source and reason and drops the
datagram; every other exception is our own bug and is allowed to propagate.
"""

from __future__ import annotations

import enum


class Reason(enum.Enum):
    """Why a datagram was rejected. Values are the names shown in statistics."""

    TRUNCATED = "truncated"
    OVERSIZED = "oversized"
    BAD_MAGIC = "bad_magic"
    BAD_VERSION = "bad_version"
    BAD_HEADER = "bad_header"
    UNSIGNED = "unsigned"
    UNKNOWN_KEY = "unknown_key"
    BAD_MAC = "bad_mac"
    UNAUTHORIZED = "unauthorized"
    REPLAY = "replay"
    STALE = "stale"
    FUTURE = "future"
    UNKNOWN_TYPE = "unknown_type"
    WRONG_TYPE = "wrong_type"
    BAD_BODY = "bad_body"
    BAD_FRAGMENT = "bad_fragment"
    FRAGMENT_TIMEOUT = "fragment_timeout"
    FRAGMENT_EVICTED = "fragment_evicted"


class ProtocolError(Exception):
    """A datagram from the network is malformed, unauthentic or unwanted."""

    def __init__(self, reason: Reason, detail: str = "", source_id: int | None = None) -> None:
        super().__init__(f"{reason.value}: {detail}" if detail else reason.value)
        self.reason = reason
        self.detail = detail
        self.source_id = source_id
