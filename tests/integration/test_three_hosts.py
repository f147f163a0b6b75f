"""The stack split over three hosts, as on the vehicle: three network namespaces on one bridge,
each running `rascal run DEPLOY --host NAME` for its part of deploy/vehicle-3hosts.toml (sensors
+ ESVS; brain + INS + time master; control + simulator + referee) over multicast between them.

First the split stack drives a short course to its end; every host sees the finish. Then it
starts again, and mid-drive the brain host is unplugged at the switch: control, on the drive
host, loses navigation and path at once and must brake the vehicle to a stop by itself, seen on
the drive host's own bus. No supervisor may restart anything over a link it cannot see across.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest

from benchmarks.netns import BridgedHosts, bridged_hosts, unavailable_reason
from protocol import channels
from protocol.codec import Envelope
from protocol.messages import ActuatorCommand, SimTruth
from protocol.transport import open_transport
from rascal.logread import read_metadata
from rascal.runtime.deployment import DEFAULT_DEPLOYMENT, load_deployment
from tests.conftest import ROOT
from tests.integration.listener import Listener
from tests.integration.stack import write_deployment
from tests.integration.test_closed_loop import RDDF, SCENARIO

pytestmark = pytest.mark.skipif(unavailable_reason() is not None, reason=f"network namespaces: {unavailable_reason()}")

VEHICLE = DEFAULT_DEPLOYMENT.parent / "vehicle-3hosts.toml"
HOSTS = ("sensors", "brainbox", "drive")
CUT_HOST = "brainbox"
CUT_AT_M = 60.0
CUT_MIN_SPEED_MPS = 2.0  # moving for sure; at load 45 the stack crawls at ~2 m/s (10-11 m/s usually)
PATH_MAX_AGE_S = 0.5  # control's default; VEHICLE_STATE's (0.2 s) goes stale first
STOPPED_MPS = 0.1
DRIVE_TIMEOUT_S = 300.0  # the short course with start-up: 55-65 s at load 15-25, 190 s at load 45
ENDING_TIMEOUT_S = 120.0  # after the course or Ctrl-C: pause, stop the modules, summarise the run


@pytest.fixture
def network() -> Iterator[BridgedHosts]:
    with bridged_hosts(HOSTS) as hosts:
        yield hosts


def write_three_hosts(tmp_path: Path, network: BridgedHosts, bus_url: str) -> Path:
    """deploy/vehicle-3hosts.toml's modules and hosts, on this network, this bus, a short course."""
    vehicle = tomllib.loads(VEHICLE.read_text())
    assert set(vehicle["hosts"]) == set(HOSTS)
    private = urlsplit(bus_url)  # the fixture's random group and port; ttl=1 to leave each host
    bus = f"udpm://{private.hostname}:{private.port}?ttl=1&iface={network.addresses[HOSTS[0]]}"
    hosts = "".join(f'[hosts.{host}]\naddress = "{network.addresses[host]}"\n' for host in HOSTS)
    return write_deployment(tmp_path, bus, RDDF, SCENARIO, overrides=vehicle["modules"], extra=hosts)


class Stack:
    """One `rascal run --host NAME` per host, each in its namespace with its own runs directory."""

    def __init__(self, network: BridgedHosts, deploy: Path, out: Path, duration_s: float) -> None:
        self.out = out
        self.runs: dict[str, subprocess.Popen[bytes]] = {}
        for host in HOSTS:
            (out / host).mkdir(parents=True)
            argv = [sys.executable, "-m", "rascal.cli", "run", str(deploy), "--host", host]
            argv += ["--duration", str(duration_s), "--runs-dir", str(out / host), "--no-images"]
            with (out / f"{host}.log").open("wb") as log:
                self.runs[host] = subprocess.Popen(
                    network.command(host, argv), cwd=ROOT, stdout=log, stderr=subprocess.STDOUT
                )

    def logs(self) -> str:
        """Each host's rascal run output, and the end of every module log that has a traceback."""
        parts = [f"--- {host}\n{(self.out / f'{host}.log').read_text()[-2000:]}" for host in HOSTS]
        for log in sorted(self.out.glob("*/*/*.log")):
            text = log.read_text(errors="replace")
            if "Traceback" in text:
                parts.append(f"--- {log.relative_to(self.out)}\n{text[-1500:]}")
        return "\n".join(parts)

    def wait(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        for host, run in self.runs.items():
            try:
                run.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pytest.fail(f"rascal run on {host} still running after {timeout_s:.0f} s\n{self.logs()}")
            assert run.returncode == 0, f"rascal run on {host} exited with {run.returncode}\n{self.logs()}"

    def interrupt(self) -> None:
        """Ctrl-C on every host: each pauses the vehicle and stops its modules in order."""
        for run in self.runs.values():
            if run.poll() is None:
                run.send_signal(signal.SIGINT)

    def kill(self) -> None:
        for run in self.runs.values():
            if run.poll() is None:
                run.kill()
                run.wait()

    def summary(self, host: str) -> dict[str, Any]:
        (run_dir,) = (self.out / host).iterdir()
        return json.loads((run_dir / "summary.json").read_text())

    def restarts(self) -> dict[str, list[str]]:
        """Every restart any supervisor made, by host/module, with its reasons."""
        return {
            f"{host}/{label}": module["restart_reasons"]
            for host in HOSTS
            for label, module in self.summary(host)["modules"].items()
            if module["restarts"]
        }

    def recorded_rejects(self, host: str) -> dict[str, int]:
        """The datagrams the recorder on ``host`` refused, by reason (its recording's metadata)."""
        (run_dir,) = (self.out / host).iterdir()
        counts: dict[str, int] = {}
        for key, value in read_metadata(run_dir / "run.mcap").get("recording", {}).items():
            if key.startswith("rejected/"):
                reason = key.rsplit("/", 1)[1]
                counts[reason] = counts.get(reason, 0) + int(value)
        return counts

    def recorded(self, host: str, channel: str) -> int:
        (run_dir,) = (self.out / host).iterdir()
        return int(read_metadata(run_dir / "run.mcap").get("recording", {}).get(f"received/{channel}", 0))

    def rejected(self) -> dict[str, int]:
        """Datagrams any module refused (a recorder hears all: two senders sharing an id show
        here), less the recorders' fragmented messages timed out for a lost fragment: a loaded
        machine drops some of the brain's 1 Hz map snapshots (bounded in the test)."""
        counts = {}
        for host in HOSTS:
            for label, module in self.summary(host)["modules"].items():
                count = module["rx_rejected"]
                if label == "recorder":
                    count -= self.recorded_rejects(host).get("fragment_timeout", 0)
                if count:
                    counts[f"{host}/{label}"] = count
        return counts


def drive_host_listener(network: BridgedHosts, deploy: Path, key_file: Path) -> Listener:
    """The test's ears on the drive host's side of the network."""
    bus = load_deployment(deploy).bus_on("drive")
    with network.entered("drive"):
        return Listener(bus, key_file, source_id=915)


def test_the_bridge_carries_the_bus_between_hosts_and_a_cut_host_hears_only_itself(network: BridgedHosts) -> None:
    transports = {}
    for host in HOSTS:
        with network.entered(host):
            transports[host] = open_transport(f"udpm://239.255.77.1:41000?ttl=1&iface={network.addresses[host]}")
            transports[host].listen("PING")

    def exchange(expected: dict[str, set[str]]) -> dict[str, set[str]]:
        """Every host sends its name; who heard whom, once ``expected`` arrived (and 0.2 s more) or after 2 s."""
        for host, transport in transports.items():
            transport.send("PING", host.encode())
        heard: dict[str, set[str]] = {host: set() for host in HOSTS}
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            for host, transport in transports.items():
                transport.receive(lambda datagram, *_, names=heard[host]: names.add(datagram.decode()), 0.01, 10)
            if heard == expected:
                deadline = min(deadline, time.monotonic() + 0.2)
        return heard

    everyone = {host: set(HOSTS) for host in HOSTS}
    others = set(HOSTS) - {CUT_HOST}
    split = {CUT_HOST: {CUT_HOST}, **{host: others for host in others}}
    try:
        assert exchange(everyone) == everyone
        network.cut(CUT_HOST)
        assert exchange(split) == split
        network.reconnect(CUT_HOST)
        assert exchange(everyone) == everyone
    finally:
        for transport in transports.values():
            transport.close()


@pytest.mark.slow
def test_three_hosts_drive_a_short_course_then_the_drive_host_brakes_when_the_brain_host_drops_off(
    network: BridgedHosts, bus_url: str, key_file: Path, tmp_path: Path
) -> None:
    deploy = write_three_hosts(tmp_path, network, bus_url)

    # 1. The split stack completes the course; each host ends by itself at the finish.
    stack = Stack(network, deploy, tmp_path / "course", DRIVE_TIMEOUT_S)
    try:
        stack.wait(DRIVE_TIMEOUT_S + ENDING_TIMEOUT_S)
    finally:
        stack.kill()
    drive = stack.summary("drive")["drive"]
    print("course:", json.dumps(drive))
    assert all(stack.summary(host)["finished"] for host in HOSTS), stack.logs()
    # Tracking quality is the closed-loop test's (one host): here it falls with the machine's load
    # (RMS 0.08-0.22 m at load 20-30, 1.0 m at load 40), not with the split.
    assert drive["finished"] and drive["collisions"] == 0 and drive["corridor_exits"] == 0
    assert stack.restarts() == {}
    assert stack.rejected() == {}
    for host in HOSTS:  # seen in CI: 7 of about 40 snapshots lost at load, none alone
        lost, heard = stack.recorded_rejects(host).get("fragment_timeout", 0), stack.recorded(host, "MAP_SNAPSHOT")
        assert heard > 0 and lost <= 0.25 * (heard + lost), f"{host}: {lost} map snapshots lost, {heard} heard"

    # 2. Again; mid-drive the brain host loses its link.
    stack = Stack(network, deploy, tmp_path / "cut", DRIVE_TIMEOUT_S)
    listener = drive_host_listener(network, deploy, key_file)
    truth: list[tuple[float, SimTruth]] = []
    commands: list[tuple[float, ActuatorCommand]] = []
    with network.entered("drive"):
        listener.subscribe(channels.SIM_TRUTH, lambda msg, _env: truth.append((time.monotonic(), msg)))

        def on_command(command: ActuatorCommand, _env: Envelope) -> None:
            commands.append((time.monotonic(), command))

        listener.subscribe(channels.ACTUATOR_COMMAND, on_command)
    try:
        driving = listener.wait_until(
            lambda: bool(truth) and truth[-1][1].progress_m >= CUT_AT_M and truth[-1][1].speed_mps >= CUT_MIN_SPEED_MPS,
            DRIVE_TIMEOUT_S,
        )
        assert driving, f"never at {CUT_AT_M} m and {CUT_MIN_SPEED_MPS} m/s: {truth[-1:]}\n{stack.logs()}"
        cut_at = time.monotonic()  # before the unplugging `ip` command: reactions are measured long, not short
        network.cut(CUT_HOST)
        speed_at_cut = truth[-1][1].speed_mps

        def failsafe_brakes() -> list[tuple[float, ActuatorCommand]]:
            return [(t, c) for t, c in commands if t > cut_at and c.brake >= 0.99 and "stale" in c.stop_reason]

        def stopped() -> bool:
            return bool(failsafe_brakes()) and truth[-1][0] > cut_at and truth[-1][1].speed_mps < STOPPED_MPS

        assert listener.wait_until(stopped, 15.0), f"no fail-safe stop: {commands[-1:]} {truth[-1:]}"
        braked_at, first = failsafe_brakes()[0]
        stopped_at = next(t for t, s in truth if t > braked_at and s.speed_mps < STOPPED_MPS)
        print(
            f"{CUT_HOST} cut at {speed_at_cut:.1f} m/s: control braking after {(braked_at - cut_at) * 1000:.0f} ms "
            f"({first.stop_reason}), stopped {stopped_at - cut_at:.1f} s after the cut"
        )
        assert braked_at - cut_at <= PATH_MAX_AGE_S + 0.15  # the longer stale timeout, one tick and slack
        # Held on the brake while the inputs stay away (2 s more), and the vehicle stays put.
        listener.wait_until(lambda: False, 2.0)
        after = [c for t, c in commands if t > braked_at]
        assert after and all(c.brake >= 0.99 and c.throttle == 0.0 for c in after), after[-3:]
        assert max(s.speed_mps for t, s in truth if t > stopped_at) < STOPPED_MPS
    finally:
        listener.close()
        stack.interrupt()
    try:
        stack.wait(ENDING_TIMEOUT_S)
    finally:
        stack.kill()
    assert stack.restarts() == {}, "a supervisor restarted a module over the cut link"
    assert not stack.summary("drive")["finished"]
