"""The operator's stop or pause, kept on disk so a restarted control process honours it.

Control keeps the last stop order in memory only as a cache: every change is written here first
(atomically: a crash mid-write leaves the old order, never half a file), and a control process
that starts reads it back. A pause stays a pause; an e-stop, latched for the life of the process
that received it, comes back as a hold that only an explicit RUN releases: a restart must never
be a way to drive again, and must not make the vehicle impossible to release either.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from protocol.messages import StopMode


@dataclass(frozen=True)
class StopOrder:
    mode: StopMode
    reason: str


RUN = StopOrder(StopMode.RUN, "")


class StopLatch:
    """One file holding the current stop order; ``path=None`` keeps it in memory only."""

    def __init__(self, path: Path | None) -> None:
        self.path = path

    def load(self) -> tuple[StopOrder, str | None]:
        """The order to start with, and a warning when the file could not be read. An unreadable
        file holds the vehicle (someone asked for something); a missing one means RUN."""
        if self.path is None:
            return RUN, None
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
            order = StopOrder(StopMode[doc["mode"]], str(doc.get("reason", "")))
        except FileNotFoundError:
            return RUN, None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            return StopOrder(StopMode.PAUSE, "stop file unreadable"), f"{self.path}: {exc}; holding as PAUSE"
        if order.mode is StopMode.ESTOP:
            return StopOrder(StopMode.PAUSE, f"e-stop before restart ({order.reason or 'no reason'})"), None
        return order, None

    def store(self, order: StopOrder) -> None:
        """Write ``order`` durably before it takes effect (fsync: a real vehicle loses power)."""
        if self.path is None:
            return
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        text = json.dumps({"mode": order.mode.name, "reason": order.reason})
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
        try:
            os.write(fd, text.encode("utf-8"))
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, self.path)
