"""`rascal demo` (and `make demo`): the whole stack drives the default scenario, start to finish.

The default deployment (deploy/localhost.toml) on this machine: the simulator and its sensors,
the ESVS, the INS, the brain and control, each its own process on the signed loopback bus,
supervised by ``rascal run``, which ends when the vehicle has finished the course (or after
``DEMO_LIMIT_S``). ``rascal run`` prints where the run's files and its report are (track, final
map, speed, cross-track error and module timing images, each PNG and SVG; rascal/report.py); the demo adds one line
of drive measures and its verdict.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from modules.referee.measures import drove_safely
from rascal.run import run
from rascal.runtime.deployment import DEFAULT_DEPLOYMENT, LOCALHOST, load_deployment

DEMO_LIMIT_S = 540.0  # the course takes about six minutes on a 2-core machine


def _latency(summary: dict[str, Any]) -> str:
    latency = summary.get("latency_ms", {}).get("obstacle_to_actuator")
    return f", obstacle-to-actuator latency p99 {latency['p99']:.0f} ms" if latency else ""


def run_demo(runs_dir: Path = Path("runs")) -> int:
    deployment = load_deployment(DEFAULT_DEPLOYMENT)
    _, run_dir = run(deployment, LOCALHOST, runs_dir, DEMO_LIMIT_S)
    summary = json.loads((run_dir / "summary.json").read_text())
    drive = summary.get("drive", {})
    ok = drove_safely(drive)
    print(
        f"demo {'OK' if ok else 'FAILED'}: finished {drive.get('finished')}, "
        f"{100 * drive.get('completion', 0):.1f} % of {drive.get('route_length_m', 0):.0f} m in "
        f"{drive.get('time_s', 0):.0f} s, collisions {drive.get('collisions')}, "
        f"corridor exits {drive.get('corridor_exits')}, ditch/berm entries {drive.get('hazard_entries')}, "
        f"mean speed {drive.get('mean_speed_mps', 0):.2f} of "
        f"{drive.get('allowed_mean_speed_mps', 0):.2f} m/s allowed ({100 * drive.get('speed_ratio', 0):.1f} %), "
        f"cross-track RMS {drive.get('cross_track_rms_m', 0):.2f} m{_latency(summary)}"
    )
    return 0 if ok else 1
