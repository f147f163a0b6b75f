"""Command authority with real processes: `rascal run` gives each module its own key file, and a
rogue process holding only the lidar's (taken from the run directory, as a compromised lidar
would have it) can forge no ACTUATOR_COMMAND, STOP or TIME_SYNC reply that a module accepts,
while a genuine `rascal pause` with the master file is obeyed.

Run as ``python -m tests.integration.test_authority KEY_FILE BUS_URL DURATION_S`` it is the rogue.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import pytest

from protocol import channels
from protocol.auth import load_keyring
from protocol.authority import OPERATOR_SOURCE_ID, Authority
from protocol.codec import Codec, Envelope
from protocol.messages import ActuatorCommand, ModuleStatus, SimTruth, StopCommand, StopMode, TimeSync, TimeSyncKind
from protocol.signing import Signer
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from rascal.runtime.deployment import load_deployment
from rascal.runtime.timesync import SyncState
from tests.conftest import ROOT
from tests.integration.listener import Listener
from tests.integration.stack import rascal_run_command
from tests.modules.control.short_course import RDDF, SCENARIO

pytestmark = pytest.mark.slow

TIME_SERVICE, SIM, LIDAR, CONTROL, SUPERVISOR = 1, 5, 21, 40, 9
ROGUE_MARK = "rogue"
STEER_NS = 10_000_000_000  # what the forged time replies would move a clock by
ATTACK_S = 12.0
DEPLOYMENT = """
[deployment]
name = "authority"
bus = "{bus}"
scenario = "scenario.toml"
course = "course.rddf"

[modules.time_service]

[modules.sim]

[modules.control]

[modules.lidar_h_left]
module = "lidar"
source_id = 21
set = {{ sensor = "lidar_h_left" }}
"""


# -- the rogue --------------------------------------------------------------------------------------


class Rogue:
    """Everything a compromised lidar can send on the command channels: as the source with
    authority without a signature, as it with the lidar's own signature, and as itself."""

    def __init__(self, key_file: Path, bus_url: str) -> None:
        self.keyring = load_keyring(key_file)
        assert self.keyring.source_id == LIDAR and self.keyring.signing_master is None
        self.bus = Bus.open(bus_url, source_id=LIDAR, clock=MasterClock(), keyring=self.keyring)
        self.codec = Codec(self.keyring)
        self.own = self.keyring.signer(LIDAR)
        self.seq = time.time_ns() // 1000  # above any genuine stream's: the window would take them
        self.sent: dict[str, int] = defaultdict(int)
        self.bus.subscribe(channels.TIME_SYNC, self.on_time_sync)

    def forge(self, channel: str, msg: object, source_id: int, signer: Signer | None) -> None:
        self.seq += 1
        now = self.bus.clock.now_ns()
        self.bus.send_raw(channel, self.codec.encode(channel.encode(), msg, source_id, self.seq, now, now, signer))
        self.sent[channel] += 1

    def every_way(self, channel: str, msg: object, victim: int) -> None:
        self.forge(channel, msg, victim, None)
        self.forge(channel, msg, victim, self.own)
        self.forge(channel, msg, LIDAR, self.own)

    def on_time_sync(self, msg: TimeSync, _envelope: Envelope) -> None:
        """Answer every request at once, echoing its nonce, with a clock 10 s ahead."""
        if msg.kind != TimeSyncKind.REQUEST:
            return
        ahead = self.bus.clock.now_ns() + STEER_NS
        reply = TimeSync(TimeSyncKind.REPLY, msg.client_source_id, msg.t1_local_ns, ahead, ahead)
        self.every_way(channels.TIME_SYNC, reply, TIME_SERVICE)

    def run(self, duration_s: float) -> None:
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            self.every_way(channels.ACTUATOR_COMMAND, ActuatorCommand(1.0, 0.0, 0.3, ROGUE_MARK), CONTROL)
            self.every_way(channels.STOP, StopCommand(int(StopMode.ESTOP), ROGUE_MARK), SUPERVISOR)
            self.forge(channels.STOP, StopCommand(int(StopMode.ESTOP), ROGUE_MARK), OPERATOR_SOURCE_ID, None)
            self.bus.poll(0.02)
        self.bus.close()
        print(json.dumps(self.sent))


# -- the test ---------------------------------------------------------------------------------------


class Watch:
    """The test's view: heartbeats by source, control's own commands, the vehicle's speed."""

    def __init__(self, listener: Listener) -> None:
        self.status: dict[int, ModuleStatus] = {}
        self.reasons: list[str] = []  # control's genuine stop_reasons, in order
        self.speeds: list[float] = []
        self.offsets: dict[int, list[int]] = defaultdict(list)
        listener.subscribe(channels.MODULE_STATUS, self.on_status)
        listener.subscribe(channels.ACTUATOR_COMMAND, self.on_command)
        listener.subscribe(channels.SIM_TRUTH, lambda truth, _env: self.on_truth(truth))

    def on_status(self, status: ModuleStatus, envelope: Envelope) -> None:
        self.status[envelope.source_id] = status
        self.offsets[envelope.source_id].append(status.clock_offset_ns)

    def on_command(self, command: ActuatorCommand, envelope: Envelope) -> None:
        # The listener enforces the deployment's authority too: a forgery here would show its mark.
        if envelope.source_id == CONTROL:
            self.reasons.append(command.stop_reason)

    def on_truth(self, truth: SimTruth) -> None:
        self.speeds.append(truth.speed_mps)

    def synced(self, *sources: int) -> bool:
        return all(s in self.status and self.status[s].clock_state == SyncState.SYNCED for s in sources)

    def rejected(self, source: int) -> int:
        return self.status[source].rx_rejected


def test_a_module_with_only_its_own_key_can_forge_no_command(bus_url: str, key_file: Path, tmp_path: Path) -> None:
    (tmp_path / "course.rddf").write_text(RDDF)
    (tmp_path / "scenario.toml").write_text(SCENARIO)
    deploy = tmp_path / "deploy.toml"
    deploy.write_text(DEPLOYMENT.format(bus=bus_url))
    runs = tmp_path / "runs"
    log = tmp_path / "run.log"
    command = rascal_run_command(deploy, runs, 90)
    with log.open("wb") as out:
        run = subprocess.Popen(command, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
    listener = Listener(bus_url, key_file, source_id=916)
    master = load_keyring(key_file)
    listener.bus.enforce(Authority.derive(load_deployment(deploy).authority, master.signing_master))  # type: ignore[arg-type]
    watch = Watch(listener)
    rogue = None
    try:
        modules = (TIME_SERVICE, SIM, CONTROL, LIDAR)
        assert listener.wait_until(lambda: watch.synced(SIM, CONTROL, LIDAR) and len(watch.reasons) > 50, 30.0), (
            log.read_text()
        )
        (run_dir,) = runs.iterdir()
        lidar_key = run_dir / "keys" / "lidar_h_left.key"
        assert load_keyring(lidar_key).source_id == LIDAR
        before = {source: watch.rejected(source) for source in modules}
        commands_before = len(watch.reasons)

        rogue = subprocess.Popen(
            [sys.executable, "-m", "tests.integration.test_authority", str(lidar_key), bus_url, str(ATTACK_S)],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        attack_started = time.monotonic()
        listener.wait_until(lambda: time.monotonic() - attack_started > 5.0, 6.0)
        during = watch.reasons[commands_before:]
        assert during and not any(reason.startswith(("estop", "pause")) for reason in during), during[-3:]

        # A genuine order, given while the rogue goes on: obeyed.
        order = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "rascal.cli",
                "pause",
                "--reason",
                "genuine",
                "--timeout",
                "8",
                "--deployment",
                str(deploy),
            ],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "RASCAL_KEY_FILE": str(key_file), "RASCAL_BUS_URL": bus_url},
        )
        assert listener.wait_until(lambda: order.poll() is not None, 20.0)
        said = order.communicate()[0]
        assert order.returncode == 0 and "control obeyed the pause" in said and "clock synchronised" in said, said
        assert listener.wait_until(lambda: rogue.poll() is not None, ATTACK_S + 10.0)
        listener.wait_until(lambda: False, 2.5)  # two more heartbeats with the last rejects
        rogue_said = rogue.communicate()[0]
        assert rogue.returncode == 0, rogue_said
    finally:
        if rogue is not None and rogue.poll() is None:
            rogue.kill()
        listener.close()
        run.terminate()
        run.wait(timeout=40)
    sent = json.loads(rogue_said.strip().splitlines()[-1])
    assert sent[channels.ACTUATOR_COMMAND] > 300 and sent[channels.STOP] > 300 and sent[channels.TIME_SYNC] > 30
    # Nothing forged was obeyed: the vehicle never moved, control was stopped by nobody but the
    # operator, and no module's clock moved (all on this host: within 5 ms of the master).
    assert max(watch.speeds) < 0.05
    reasons = watch.reasons[commands_before:]
    assert not any(r.startswith("estop") or ROGUE_MARK in r for r in reasons)
    assert reasons[-1].startswith("pause: genuine")
    for source in (SIM, CONTROL, LIDAR):
        assert max(abs(offset) for offset in watch.offsets[source]) < 5_000_000, (source, watch.offsets[source])
        assert watch.status[source].clock_state == SyncState.SYNCED
    # Rejected and counted: sim the actuator commands, control the stops, and the clients the
    # forged replies that beat the genuine one to their own requests (a forged reply that comes
    # after finds its nonce used and is ignored unchecked).
    gained = {source: watch.rejected(source) - before[source] for source in modules}
    print(f"rogue sent {sent}; rejects gained by source {gained}; control commands seen {len(reasons)}")
    assert gained[SIM] >= sent[channels.ACTUATOR_COMMAND] * 0.9, gained
    assert gained[CONTROL] >= sent[channels.STOP] * 0.9, gained
    commands = sent[channels.ACTUATOR_COMMAND] + sent[channels.STOP]
    assert gained[SIM] + gained[CONTROL] + gained[LIDAR] > commands, (gained, sent)
    assert gained[TIME_SERVICE] == 0, gained  # it subscribes to none of the forged channels' messages
    assert run.returncode == 0, log.read_text()[-3000:]
    assert not (run_dir / "keys").exists()


if __name__ == "__main__":
    Rogue(Path(sys.argv[1]), sys.argv[2]).run(float(sys.argv[3]))
