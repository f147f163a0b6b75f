"""Notices silence: modules whose heartbeat stopped and inputs that went stale.

RASCAL's race ended because nothing noticed that the lidars had died. This module turns every
such silence, and the recovery from it, into a HealthEvent on the bus.
"""

from __future__ import annotations

from dataclasses import dataclass

from protocol import channels
from protocol.codec import Envelope
from protocol.messages import ModuleStatus, Severity
from rascal.runtime.config import ConfigError, setting
from rascal.runtime.module import Module
from rascal.runtime.ports import Port
from rascal.runtime.rtdb import Latest


@dataclass(frozen=True)
class HealthConfig:
    heartbeat_timeout_s: float = setting(3.0, "a module silent this long is reported")
    watch: tuple[str, ...] = setting((), "CHANNEL:MAX_AGE_S entries whose staleness is reported")
    check_period_s: float = setting(0.1, "how often freshness is checked")


class HealthMonitor(Module):
    """Reports modules whose heartbeats stop and watched inputs that go stale, and recoveries."""

    name = "health"
    default_source_id = 2
    Config = HealthConfig
    interface = (
        Port("in", "`MODULE_STATUS`", "ModuleStatus", "1 Hz per module", "`heartbeat_timeout_s` (3 s)"),
        Port(
            "in", "each `watch` entry `CHANNEL:MAX_AGE_S`", "the channel's type", "any", "`MAX_AGE_S`, from `t_meas_ns`"
        ),
        Port(
            "out", "`HEALTH`", "HealthEvent `module_silent`, `module_back`, `input_stale`, `input_fresh`", "on change"
        ),
        Port("out", "`MODULE_STATUS`", "ModuleStatus", "1 Hz"),
    )

    def on_start(self) -> None:
        self.last_heartbeat_ns: dict[str, int] = {}
        self.silent: set[str] = set()
        self.watched: list[Latest[object]] = [self.input(*parse_watch(entry)) for entry in self.config.watch]
        self.stale: set[str] = set()
        self.events = 0
        self.bus.subscribe(channels.MODULE_STATUS, self.on_status)
        self.every(self.config.check_period_s, self.check)

    def on_status(self, status: ModuleStatus, envelope: Envelope) -> None:
        self.last_heartbeat_ns[status.module] = envelope.recv_ns
        if status.module in self.silent:
            self.silent.discard(status.module)
            self.emit(Severity.INFO, "module_back", f"{status.module} is sending heartbeats again")

    def check(self) -> None:
        now = self.now_ns()
        timeout_ns = int(self.config.heartbeat_timeout_s * 1e9)
        for module, seen_ns in self.last_heartbeat_ns.items():
            if module not in self.silent and now - seen_ns > timeout_ns:
                self.silent.add(module)
                self.emit(
                    Severity.ERROR, "module_silent", f"no heartbeat from {module} for {(now - seen_ns) / 1e9:.1f} s"
                )
        for entry in self.watched:
            reading = entry.read(now)
            if entry.is_stale(now) and entry.channel not in self.stale and reading.age_ns is not None:
                self.stale.add(entry.channel)
                self.emit(Severity.WARNING, "input_stale", f"{entry.channel} is {reading.age_ns / 1e9:.2f} s old")
            elif not entry.is_stale(now) and entry.channel in self.stale:
                self.stale.discard(entry.channel)
                self.emit(Severity.INFO, "input_fresh", f"{entry.channel} is fresh again")

    def emit(self, severity: Severity, code: str, text: str) -> None:
        self.report(severity, code, text)
        self.events += 1

    def status_detail(self) -> str:
        return f"{len(self.last_heartbeat_ns)} modules seen, {len(self.silent)} silent, stale: {sorted(self.stale)}"


def parse_watch(entry: str) -> tuple[str, float]:
    channel, sep, age = entry.partition(":")
    try:
        max_age_s = float(age)
    except ValueError:
        max_age_s = -1.0
    if not sep or max_age_s <= 0 or channel not in channels.CHANNEL_TYPES:
        raise ConfigError(f"watch entry {entry!r}: expected DECLARED_CHANNEL:MAX_AGE_S with a positive age")
    return channel, max_age_s
