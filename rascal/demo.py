"""`rascal demo` (and `make demo`): the whole stack drives the default scenario, start to finish.

The default deployment (deploy/localhost.toml) on this machine: the simulator and its sensors,
the ESVS, the INS, the brain and control, each its own process on the signed loopback bus,
supervised by ``rascal run``, which ends when the vehicle has finished the course (or after
``DEMO_LIMIT_S``). Prints the drive measures, where the run's files are and its report
(track, final map, speed, cross-track error and module timing images; rascal/report.py).
"""

from __future__ import annotations

import json
from pathlib import Path

from rascal.deployment import DEFAULT_DEPLOYMENT, LOCALHOST, load_deployment
from rascal.report import REPORT_DIR
from rascal.run import run

DEMO_LIMIT_S = 540.0  # the course takes about six minutes on a 2-core machine


def run_demo(runs_dir: Path = Path("runs")) -> int:
    deployment = load_deployment(DEFAULT_DEPLOYMENT)
    _, run_dir = run(deployment, LOCALHOST, runs_dir, DEMO_LIMIT_S)
    summary = json.loads((run_dir / "summary.json").read_text())
    report = run_dir / REPORT_DIR
    drive = summary.get("drive", {})
    ok = bool(drive.get("finished")) and drive.get("collisions") == 0 and drive.get("corridor_exits") == 0
    print(
        f"demo {'OK' if ok else 'FAILED'}: finished {drive.get('finished')}, "
        f"{100 * drive.get('completion', 0):.1f} % of {drive.get('route_length_m', 0):.0f} m in "
        f"{drive.get('time_s', 0):.0f} s, collisions {drive.get('collisions')}, "
        f"corridor exits {drive.get('corridor_exits')}; logs, run.mcap and summary.json in {run_dir}/"
    )
    if any(report.glob("*.png")):
        print(f"report: {report}/ ({', '.join(sorted(path.name for path in report.glob('*.png')))})")
    else:
        print(f"no report in {report}/ (rascal report {run_dir} says why)")
    return 0 if ok else 1
