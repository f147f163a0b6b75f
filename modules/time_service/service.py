"""The shared time master."""

from __future__ import annotations

from dataclasses import dataclass

from rascal.runtime.module import Module


@dataclass(frozen=True)
class TimeServiceConfig:
    """The master has nothing to tune: it answers requests as they come."""


class TimeService(Module):
    """Shared time master: answers every node's 4-timestamp time request with its wall clock."""

    name = "time_service"
    default_source_id = 1
    Config = TimeServiceConfig
    time_master = True

    def status_detail(self) -> str:
        master = self.runtime.time_master
        return f"answered {master.answered if master else 0} requests"
