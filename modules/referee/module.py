"""The referee process: watches the simulator's truth and the planned path, and writes the drive
measures (modules/referee/measures.py) as JSON when it stops.

Simulation only, like the simulator: it reads the truth the stack never sees. It writes to
``out``, or, when that is empty, to ``drive.json`` in ``$RASCAL_RUN_DIR`` (set by ``rascal run``
for every module it starts).

Neither the truth (100 Hz) nor the paths wake it: what arrived is judged once a second, when it
writes (and for its heartbeat), in the order it arrived.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from operator import itemgetter
from pathlib import Path
from typing import Any

from brain.vehicle import VehicleGeometry
from modules.referee.measures import Referee as Measures
from modules.sim.scenario import DEFAULT_SCENARIO, load_scenario
from modules.sim.vehicle import VehicleParams
from protocol import channels
from protocol.codec import Envelope
from protocol.messages import Path as PlannedPath
from protocol.messages import SimTruth
from rascal.runtime.config import section, setting
from rascal.runtime.module import Module, Runtime, run_artefact
from rascal.runtime.ports import Port

SUMMARY_PERIOD_S = 1.0


@dataclass(frozen=True)
class RefereeConfig:
    scenario: str = setting(str(DEFAULT_SCENARIO), "scenario TOML whose route and obstacles are judged")
    out: str = setting("", "JSON file for the measures (empty: $RASCAL_RUN_DIR/drive.json, or none)")
    vehicle: VehicleGeometry = section(VehicleGeometry, "the footprint judged: clearance, hazard entries")


class Referee(Module):
    """Judges the drive from the simulator's truth: completion, speed, cross-track, clearance."""

    name = "referee"
    default_source_id = 6
    Config = RefereeConfig
    interface = (
        Port("in", "`SIM_TRUTH`", "SimTruth (true pose, speed, progress, collision and exit counts)", "100 Hz"),
        Port("in", "`PATH`", "Path (the brain's plans: cross-track is measured to the newest)", "10 Hz"),
        Port("out", "`drive.json`", "the measures below, rewritten every second and at the end", "1 Hz"),
        Port(
            "out",
            "`MODULE_STATUS`",
            "ModuleStatus: completion, time, speed ratio, cross-track, infractions, clearance",
            "1 Hz",
        ),
    )

    def __init__(self, config: RefereeConfig, runtime: Runtime) -> None:
        super().__init__(config, runtime)
        self.out = Path(config.out) if config.out else run_artefact("drive.json")

    def on_start(self) -> None:
        self.measures = Measures(load_scenario(self.config.scenario), VehicleParams(geometry=self.config.vehicle))
        self.arrivals: list[tuple[int, Callable[[Any], None], Any]] = []
        # Judged when the referee next looks, not as they come: neither stream needs it awake
        # (truth alone would wake it 100 times a second). Their arrival times keep the order.
        self.bus.subscribe(channels.SIM_TRUTH, self.on_truth, wake=False)
        self.bus.subscribe(channels.PATH, self.on_path, wake=False)
        self.every(SUMMARY_PERIOD_S, self.write, priority=1)

    def on_truth(self, truth: SimTruth, envelope: Envelope) -> None:
        self.arrivals.append((envelope.recv_ns, self.measures.on_truth, truth))

    def on_path(self, path: PlannedPath, envelope: Envelope) -> None:
        self.arrivals.append((envelope.recv_ns, self.measures.on_path, path))

    def judge(self) -> None:
        """Feed the measures what arrived since the last call, in order of arrival (each socket
        is read in turn, so handlers see the two channels' messages in batches)."""
        self.arrivals.sort(key=itemgetter(0))
        for _recv_ns, feed, message in self.arrivals:
            feed(message)
        self.arrivals.clear()

    def write(self) -> None:
        """Written every second, not only at the end: a killed referee leaves its last word."""
        self.judge()
        if self.out is not None:
            tmp = self.out.with_suffix(".tmp")
            tmp.write_text(json.dumps(self.measures.result().as_dict(), indent=2))
            tmp.replace(self.out)

    def on_stop(self) -> None:
        self.write()

    def status_detail(self) -> str:
        self.judge()
        r = self.measures.result()
        return (
            f"{100 * r.completion:.1f} % in {r.time_s:.0f} s, {r.mean_speed_mps:.1f} m/s "
            f"({100 * r.speed_ratio:.0f} % of allowed), xtrack rms {r.cross_track_rms_m:.2f} m, "
            f"collisions {r.collisions}, exits {r.corridor_exits}, hazard entries {r.hazard_entries}, "
            f"clearance {r.min_clearance_m:.2f} m"
        )
