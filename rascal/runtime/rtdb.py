"""Latest-value store with temporal validity, after CAMBADA's real-time database.

Each entry holds the newest value of one channel and the max age it is valid for. The age is
measured from the data's ``t_meas_ns`` (when the world was sensed), not from arrival. Readers
always learn the state explicitly: a stale entry never hands out its old value as if it were new.
"""

from __future__ import annotations

import enum
from typing import Generic, NamedTuple, TypeVar

from protocol.codec import Envelope

T = TypeVar("T")


class Validity(enum.Enum):
    NEVER = "never"
    FRESH = "fresh"
    STALE = "stale"


class Reading(NamedTuple, Generic[T]):
    validity: Validity
    value: T | None  # None unless FRESH
    age_ns: int | None  # None when NEVER received
    envelope: Envelope | None


class Latest(Generic[T]):
    """The newest value of one channel and how long it stays valid."""

    def __init__(self, channel: str, max_age_ns: int) -> None:
        if max_age_ns <= 0:
            raise ValueError(f"{channel}: max_age_ns must be positive")
        self.channel = channel
        self.max_age_ns = max_age_ns
        self._value: T | None = None
        self._envelope: Envelope | None = None
        self.updates = 0

    def update(self, value: T, envelope: Envelope) -> None:
        # Keep the newest measurement: a late, reordered message must not roll the value back.
        if self._envelope is None or envelope.t_meas_ns >= self._envelope.t_meas_ns:
            self._value = value
            self._envelope = envelope
        self.updates += 1

    def read(self, now_ns: int) -> Reading[T]:
        if self._envelope is None:
            return Reading(Validity.NEVER, None, None, None)
        age = now_ns - self._envelope.t_meas_ns
        if age > self.max_age_ns:
            return Reading(Validity.STALE, None, age, self._envelope)
        return Reading(Validity.FRESH, self._value, age, self._envelope)

    def fresh(self, now_ns: int) -> T | None:
        """The value if it is still valid, else None."""
        return self.read(now_ns).value

    def is_stale(self, now_ns: int) -> bool:
        return self.read(now_ns).validity is not Validity.FRESH
