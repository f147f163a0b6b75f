"""A lossy, jittery network under the whole stack (`rascal run`, tests/integration/stack.py): every
module loses 20 % of the datagrams it receives on every channel and gets the rest 0-20 ms late
(the deployment's [[faults]], applied in each process's transport, protocol/faults.py). The
course must still be completed, with no collision and no corridor exit.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from protocol.faults import FAULTS_ENV
from tests.integration.stack import MODULES, drive, rock, scenario, write_deployment
from tests.integration.test_supervisor import pids_of

pytestmark = pytest.mark.slow

# About 300 m: 180 m east, then a gentle bend to the north-east; 25 mph limit, 40 ft boundary.
COURSE = "1,34.8650000,-116.8900000,40,25\n2,34.8650000,-116.8880000,40,25\n3,34.8658000,-116.8868000,40,25\n"
SCENARIO = scenario(19, rock(150.0, 0.8))
LOSS_PCT = 20
JITTER_MS = 20
LINK_FAULTS = f"""
[[faults]]
channels = ".*"
loss_pct = {LOSS_PCT}
jitter_ms = {JITTER_MS}
seed = 23
"""


def test_20_percent_loss_and_20_ms_jitter_on_every_channel_still_completes_the_course(
    bus_url: str, key_file: Path, tmp_path: Path
) -> None:
    deploy = write_deployment(tmp_path, bus_url, COURSE, SCENARIO, extra=LINK_FAULTS)
    with drive(tmp_path, bus_url, key_file, deploy) as stack:
        stack.wait_for_progress(50.0, 180.0)
        # Every module process got the rules (the fault layer's own tests show it applies them).
        for module in {table.get("module", label) for label, table in MODULES.items()}:
            pids = pids_of(module, bus_url)
            assert pids, f"no {module} process"
            for pid in pids:
                environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
                rules = next((v for v in environ if v.startswith(FAULTS_ENV.encode() + b"=")), b"")
                assert f"loss_pct={LOSS_PCT}".encode() in rules and f"jitter_ms={JITTER_MS}".encode() in rules, rules
    drive_measures = stack.drive
    assert stack.summary["finished"] and drive_measures["finished"], stack.tail("did not finish")
    assert drive_measures["collisions"] == 0 and drive_measures["corridor_exits"] == 0, drive_measures
    assert drive_measures["min_clearance_m"] > 0.3, drive_measures
    restarts = {label: m["restarts"] for label, m in stack.summary["modules"].items() if m["restarts"]}
    d = drive_measures
    print(
        f"\n{LOSS_PCT} % loss + {JITTER_MS} ms jitter on every channel: finished in {d['time_s']:.0f} s at "
        f"{d['mean_speed_mps']:.1f} m/s mean, cross-track rms {d['cross_track_rms_m']:.2f} m, "
        f"clearance {d['min_clearance_m']:.2f} m, brain mode changes {len(stack.modes())}, "
        f"restarts {restarts or 'none'}"
    )
