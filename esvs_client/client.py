"""EsvsClient: the ESVS seen from the rest of the vehicle, as a device on the network.

RASCAL's ESVS was a box: once mounted and powered it sent obstacle and lane-border reports over
Ethernet and received what its algorithms needed from the brain. This client is the brain's end
of that: typed callbacks for the reports, vehicle state and configuration going the other way,
the device's status, and loss detection (stale reports, sequence gaps) so that a silent ESVS is
noticed, not trusted.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from protocol import channels
from protocol.auth import default_keyring, load_keyring
from protocol.codec import Envelope
from protocol.messages import (
    ConfigUpdate,
    HealthEvent,
    LaneBorder,
    LaneBorders,
    ModuleStatus,
    Obstacle,
    ObstacleList,
    VehicleState,
)
from rascal.runtime.bus import Bus
from rascal.runtime.clock import SharedClock
from rascal.runtime.timeclient import TimeClient

DEFAULT_SOURCE_ID = 50
TIME_REQUEST_PERIOD_S = 0.1


class ObstacleReport(NamedTuple):
    """One OBSTACLES_ESVS report: obstacles in the VEHICLE frame at the frame's exposure time."""

    obstacles: tuple[Obstacle, ...]
    frame_time_ns: int  # exposure time of the stereo pair (shared time)
    received_ns: int  # shared time it arrived
    seq: int
    source_id: int

    @property
    def age_ns(self) -> int:
        """Exposure to arrival: how old the picture of the world was when it got here."""
        return self.received_ns - self.frame_time_ns


class LaneReport(NamedTuple):
    """One LANE_BORDERS report: borders in the VEHICLE frame at the frame's exposure time."""

    borders: tuple[LaneBorder, ...]
    frame_time_ns: int
    received_ns: int
    seq: int
    source_id: int

    @property
    def age_ns(self) -> int:
        return self.received_ns - self.frame_time_ns


class _Sequence:
    """Per-source sequence tracking of one report channel: gaps are reports lost on the way."""

    def __init__(self) -> None:
        self.last: dict[int, int] = {}
        self.gaps = 0

    def see(self, source_id: int, seq: int) -> None:
        last = self.last.get(source_id)
        if last is not None and seq > last + 1:
            self.gaps += seq - last - 1
        if last is None or seq > last:
            self.last[source_id] = seq


class EsvsClient:
    """Reports, status and loss detection for one ESVS (``module``, optionally one ``source_id``).

    Callbacks run inside :meth:`poll`. ``stale`` turns True when no obstacle report has come for
    ``stale_rounds`` ESVS rounds (the round period comes from the ESVS's own status once it has
    been heard, ``round_period_s`` until then); ``on_stale(True)`` and ``on_stale(False)`` mark
    the moments it stops and resumes."""

    def __init__(
        self,
        bus: Bus,
        *,
        module: str = "esvs",
        source_id: int | None = None,
        round_period_s: float = 0.1,
        stale_rounds: float = 3.0,
        on_obstacles: Callable[[ObstacleReport], None] | None = None,
        on_lanes: Callable[[LaneReport], None] | None = None,
        on_status: Callable[[ModuleStatus], None] | None = None,
        on_health: Callable[[HealthEvent], None] | None = None,
        on_stale: Callable[[bool], None] | None = None,
        time_client: TimeClient | None = None,
        owns_bus: bool = False,
        now_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if round_period_s <= 0 or stale_rounds <= 0:
            raise ValueError("round_period_s and stale_rounds must be positive")
        self.bus = bus
        self.module = module
        self.source_id = source_id
        self.round_period_s = round_period_s
        self.stale_rounds = stale_rounds
        self.on_obstacles = on_obstacles
        self.on_lanes = on_lanes
        self.on_status = on_status
        self.on_health = on_health
        self.on_stale = on_stale
        self._time_client = time_client
        self._owns_bus = owns_bus
        self._now_ns = now_ns
        self._next_time_request_ns = 0
        self._last_report_ns = now_ns()  # staleness counts from the client's start
        self.stale = False
        self.status: ModuleStatus | None = None
        self.last_obstacles: ObstacleReport | None = None
        self.last_lanes: LaneReport | None = None
        self.obstacle_reports = 0
        self.lane_reports = 0
        self.stale_events = 0
        self._obstacle_seq = _Sequence()
        self._lane_seq = _Sequence()
        bus.subscribe(channels.OBSTACLES_ESVS, self._on_obstacles, ObstacleList)
        bus.subscribe(channels.LANE_BORDERS, self._on_lanes, LaneBorders)
        bus.subscribe(channels.MODULE_STATUS, self._on_status, ModuleStatus)
        bus.subscribe(channels.HEALTH, self._on_health, HealthEvent)

    @classmethod
    def open(
        cls,
        bus_url: str | None = None,
        *,
        key_file: str | Path | None = None,
        source_id: int = DEFAULT_SOURCE_ID,
        **options: Any,
    ) -> EsvsClient:
        """Open the bus (``bus_url`` or ``$RASCAL_BUS_URL``; the deployment key, or ``key_file``)
        with a clock this client keeps synchronised to the time service while it polls."""
        keyring = load_keyring(Path(key_file)) if key_file is not None else default_keyring()
        clock = SharedClock()
        bus = Bus.open(bus_url, source_id=source_id, clock=clock, keyring=keyring)
        return cls(bus, time_client=TimeClient(bus, clock), owns_bus=True, **options)

    # -- the loop -------------------------------------------------------------------------------

    def poll(self, timeout_s: float = 0.0) -> int:
        """Handle what arrived (waiting up to ``timeout_s``), then check for staleness."""
        if self._time_client is not None and self._now_ns() >= self._next_time_request_ns:
            self._time_client.request()
            self._next_time_request_ns = self._now_ns() + int(TIME_REQUEST_PERIOD_S * 1e9)
        handled = self.bus.poll(timeout_s)
        self.check()
        return handled

    def wait_until(self, done: Callable[[], bool], timeout_s: float, step_s: float = 0.01) -> bool:
        """Poll until ``done()`` or ``timeout_s``; True if done."""
        deadline = self._now_ns() + int(timeout_s * 1e9)
        while not done():
            if self._now_ns() >= deadline:
                return False
            self.poll(step_s)
        return True

    def close(self) -> None:
        if self._owns_bus:
            self.bus.close()

    # -- to the ESVS ----------------------------------------------------------------------------

    def send_vehicle_state(self, state: VehicleState, t_meas_ns: int | None = None) -> int:
        """Publish the navigation solution (VEHICLE_STATE); returns its sequence number."""
        return self.bus.publish(channels.VEHICLE_STATE, state, t_meas_ns=t_meas_ns)

    def configure(self, key: str, value: object) -> int:
        """Ask the ESVS to change one setting; it answers with a HEALTH event (code ``config``
        when done, ``config_rejected`` with the reason when not)."""
        text = str(value).lower() if isinstance(value, bool) else str(value)
        return self.bus.publish(channels.CONFIG, ConfigUpdate(self.module, key, text))

    # -- loss -----------------------------------------------------------------------------------

    @property
    def gaps(self) -> int:
        """Reports missing from the sequences (obstacles and lanes), i.e. lost on the way."""
        return self._obstacle_seq.gaps + self._lane_seq.gaps

    @property
    def stale_after_s(self) -> float:
        period = self.round_period_s
        if self.status is not None and self.status.loop_period_ns > 0:
            period = self.status.loop_period_ns / 1e9
        return self.stale_rounds * period

    def check(self) -> None:
        """Judge staleness now (``poll`` does; a module whose Runtime polls the bus calls this
        from one of its periodic tasks)."""
        silent_ns = self._now_ns() - self._last_report_ns
        if not self.stale and silent_ns > self.stale_after_s * 1e9:
            self._set_stale(True)

    def _set_stale(self, stale: bool) -> None:
        self.stale = stale
        if stale:
            self.stale_events += 1
        if self.on_stale is not None:
            self.on_stale(stale)

    # -- from the ESVS --------------------------------------------------------------------------

    def _accepts(self, envelope: Envelope) -> bool:
        return self.source_id is None or envelope.source_id == self.source_id

    def _on_obstacles(self, message: ObstacleList, envelope: Envelope) -> None:
        if not self._accepts(envelope):
            return
        self._obstacle_seq.see(envelope.source_id, envelope.seq)
        self._last_report_ns = self._now_ns()
        if self.stale:
            self._set_stale(False)
        env = envelope
        report = ObstacleReport(message.obstacles, env.t_meas_ns, env.recv_ns, env.seq, env.source_id)
        self.last_obstacles = report
        self.obstacle_reports += 1
        if self.on_obstacles is not None:
            self.on_obstacles(report)

    def _on_lanes(self, message: LaneBorders, envelope: Envelope) -> None:
        if not self._accepts(envelope):
            return
        self._lane_seq.see(envelope.source_id, envelope.seq)
        report = LaneReport(message.borders, envelope.t_meas_ns, envelope.recv_ns, envelope.seq, envelope.source_id)
        self.last_lanes = report
        self.lane_reports += 1
        if self.on_lanes is not None:
            self.on_lanes(report)

    def _on_status(self, message: ModuleStatus, envelope: Envelope) -> None:
        if message.module != self.module or not self._accepts(envelope):
            return
        self.status = message
        if self.on_status is not None:
            self.on_status(message)

    def _on_health(self, message: HealthEvent, envelope: Envelope) -> None:
        if message.module != self.module or not self._accepts(envelope):
            return
        if self.on_health is not None:
            self.on_health(message)
