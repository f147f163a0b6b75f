"""A module's interface, declared once: what it reads and writes, at what rate, how old it may be.

Each Module subclass lists its ports in ``interface``. ``rascal module NAME --interface`` prints
them, and each module's README carries the same table, generated here (a test keeps the two in
step, and checks that the bus channels the module's code names are the ones it declares).
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

TABLE_HEADER = ("direction", "channel", "type", "rate", "max age")
NONE = "—"


@dataclass(frozen=True)
class Port:
    """One row of the interface. ``channel`` is a bus channel in backticks, optionally with a note
    (``"`PATH`"``, ``"`OBSTACLES_LIDAR` (horizontal lidars)"``), or another way in or out (a
    shared-memory ring, a file); ``carries`` the message type and what matters about it."""

    direction: Literal["in", "out"]
    channel: str
    carries: str
    rate: str
    max_age: str = NONE

    def __post_init__(self) -> None:
        if self.direction not in ("in", "out"):
            raise ValueError(f"a port's direction is 'in' or 'out', not {self.direction!r}")
        for name in ("channel", "carries", "rate", "max_age"):
            text = getattr(self, name)
            if not text or "|" in text or "\n" in text:
                raise ValueError(f"Port.{name} must be one non-empty line without '|', got {text!r}")

    @property
    def bus_channels(self) -> tuple[str, ...]:
        """The bus channels this port names (in backticks, upper case), none for other ways."""
        return tuple(re.findall(r"`([A-Z][A-Z0-9_]*)`", self.channel))


def interface_table(ports: Iterable[Port]) -> str:
    """The ports as the markdown table the module's README carries."""
    rows = [TABLE_HEADER, *((p.direction, p.channel, p.carries, p.rate, p.max_age) for p in ports)]
    lines = ["| " + " | ".join(row) + " |" for row in rows]
    lines.insert(1, "|" + "---|" * len(TABLE_HEADER))
    return "\n".join(lines)
