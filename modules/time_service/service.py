"""The shared time master."""

from __future__ import annotations

from dataclasses import dataclass

from rascal.runtime.module import Module
from rascal.runtime.ports import Port


@dataclass(frozen=True)
class TimeServiceConfig:
    """The master has nothing to tune: it answers requests as they come."""


class TimeService(Module):
    """Shared time master: answers every node's 4-timestamp time request with its wall clock."""

    name = "time_service"
    default_source_id = 1
    Config = TimeServiceConfig
    interface = (
        Port(
            "in",
            "`TIME_SYNC`",
            "TimeSync REQUEST",
            "10 Hz per node until its estimate settles (32 exchanges), then one per 2 s",
            "judged by t1 matching, not age",
        ),
        Port("out", "`TIME_SYNC`", "TimeSync REPLY (t1 echoed, t2 receive, t3 send)", "one per request"),
        Port("out", "`MODULE_STATUS`", "ModuleStatus", "1 Hz"),
    )
    time_master = True

    def status_detail(self) -> str:
        master = self.runtime.time_master
        return f"answered {master.answered if master else 0} requests"
