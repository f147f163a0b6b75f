"""Real processes on the signed loopback multicast bus: modules, tools and shared time."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zmq

from protocol import channels
from protocol.auth import Keyring, load_keyring
from protocol.codec import DEFAULT_MAX_MESSAGE_BYTES, Envelope
from protocol.messages import ModuleStatus, ObstacleList
from protocol.transport import ZmqSubscriberTransport
from rascal.bridge import MAX_SUBSCRIPTION_BYTES, Bridge
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock, SharedClock
from rascal.runtime.timeclient import TimeClient
from rascal.runtime.timesync import SyncState
from tests.conftest import ROOT, Processes, random_port

pytestmark = pytest.mark.slow


def listen(bus: Bus, seconds: float, time_client: TimeClient | None = None) -> None:
    end = time.monotonic() + seconds
    next_sync = 0.0
    while (now := time.monotonic()) < end:
        if time_client is not None and now >= next_sync:
            time_client.request()
            next_sync = now + 0.1
        bus.poll(0.02)


def rascal(*args: str, timeout: float = 30) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "rascal.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
        check=False,
    )


def rates_of(hz: subprocess.CompletedProcess[str]) -> list[float]:
    return [float(line.split("rate ")[1].split(" Hz")[0]) for line in hz.stdout.splitlines()]


def test_modules_exchange_signed_messages_over_multicast(bus_url: str, key_file: Path, processes: Processes) -> None:
    processes.module("time_service")
    processes.module("beacon", "--set", "rate_hz=20")
    bus = Bus.open(bus_url, source_id=900, clock=MasterClock(), keyring=load_keyring(key_file))
    received: list[tuple[ObstacleList, Envelope]] = []
    statuses: dict[str, ModuleStatus] = {}
    bus.subscribe(channels.OBSTACLES_BEACON, lambda msg, env: received.append((msg, env)))
    bus.subscribe(channels.MODULE_STATUS, lambda msg, env: statuses.__setitem__(msg.module, msg))
    listen(bus, 3.0)
    bus.close()
    assert len(received) >= 30, processes.log("beacon")
    assert all(env.source_id == 3 and len(msg.obstacles) == 4 for msg, env in received)
    seqs = [env.seq for _msg, env in received]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert bus.rejected_total() == 0
    assert statuses["beacon"].clock_state == SyncState.SYNCED  # the beacon synchronised to the master


def test_a_node_with_another_key_is_heard_by_no_one(
    bus_url: str, key_file: Path, processes: Processes, tmp_path: Path
) -> None:
    processes.module("beacon")
    genuine = Bus.open(bus_url, source_id=901, clock=MasterClock(), keyring=load_keyring(key_file))
    got: list[ObstacleList] = []
    genuine.subscribe(channels.OBSTACLES_BEACON, lambda msg, env: got.append(msg))
    listen(genuine, 1.0)
    got.clear()
    spoofer = Bus.open(bus_url, source_id=3, clock=MasterClock(), keyring=Keyring.generate())
    fake = ObstacleList(7, 0, ())
    for _ in range(50):
        spoofer.publish(channels.OBSTACLES_BEACON, fake)
    listen(genuine, 1.0)
    assert got and fake not in got
    assert genuine.rejects[(3, "bad_mac")] == 50
    spoofer.close()
    genuine.close()


def test_shared_time_on_loopback_within_50_us(bus_url: str, key_file: Path, processes: Processes) -> None:
    """The master reads the wall clock on this same host, so a client's shared time can be
    compared with the wall clock directly."""
    processes.module("time_service")
    clock = SharedClock()
    bus = Bus.open(bus_url, source_id=902, clock=clock, keyring=load_keyring(key_file))
    time_client = TimeClient(bus, clock)
    listen(bus, 3.0, time_client)
    errors = []
    for _ in range(200):
        before = time.time_ns()
        shared = clock.now_ns()
        after = time.time_ns()
        errors.append(abs(shared - (before + after) // 2))
    bus.close()
    assert clock.estimator.status(clock.local_ns()).state == SyncState.SYNCED
    errors.sort()
    assert errors[len(errors) // 2] <= 50_000, f"median error {errors[len(errors) // 2] / 1e3:.1f} us"


def test_a_skewed_node_still_stamps_shared_time(bus_url: str, key_file: Path, processes: Processes) -> None:
    """A beacon whose local clock is 250 ms off and drifts 100 ppm publishes in shared time."""
    processes.module("time_service")
    processes.module("beacon", "--clock-offset-ms", "250", "--clock-drift-ppm", "100", "--set", "rate_hz=50")
    bus = Bus.open(bus_url, source_id=903, clock=MasterClock(), keyring=load_keyring(key_file))
    lateness: list[int] = []
    bus.subscribe(channels.OBSTACLES_BEACON, lambda msg, env: lateness.append(env.recv_ns - env.t_pub_ns))
    listen(bus, 4.0)
    lateness.clear()
    listen(bus, 2.0)
    bus.close()
    lateness.sort()
    assert len(lateness) > 50
    # One-way latency is positive and well under a millisecond here; a 250 ms skew would show.
    assert -500_000 < lateness[len(lateness) // 2] < 2_000_000, lateness[len(lateness) // 2]


def test_bus_tools_show_the_traffic_as_plain_lines(bus_url: str, key_file: Path, processes: Processes) -> None:
    processes.module("time_service")
    processes.module("beacon", "--set", "rate_hz=20")
    time.sleep(1.0)
    listing = rascal("bus", "list", "--duration", "2")
    assert listing.returncode == 0, listing.stderr
    assert "OBSTACLES_BEACON" in listing.stdout and "ObstacleList" in listing.stdout
    echo = rascal("bus", "echo", channels.OBSTACLES_BEACON, "--count", "2", "--duration", "5")
    lines = [json.loads(line) for line in echo.stdout.splitlines()]
    assert len(lines) == 2 and len(lines[0]["msg"]["obstacles"]) == 4
    hz = rascal("bus", "hz", channels.OBSTACLES_BEACON, "--duration", "4.2", "--window", "2")
    assert rates_of(hz) and all(abs(rate - 20.0) <= 0.4 for rate in rates_of(hz)), hz.stdout
    status = rascal("time", "status", "--duration", "2")
    assert "time_service" in status.stdout and "SYNCED" in status.stdout


def test_bus_pub_reaches_a_subscriber(bus_url: str, key_file: Path) -> None:
    bus = Bus.open(bus_url, source_id=904, clock=MasterClock(), keyring=load_keyring(key_file))
    got = []
    bus.subscribe(channels.WHEEL_SPEED, lambda msg, env: got.append(msg))
    pub = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "rascal.cli",
            "bus",
            "pub",
            channels.WHEEL_SPEED,
            '{"speed_mps": 4.5, "odometer_m": 12}',
            "--count",
            "3",
            "--rate",
            "20",
        ],
        cwd=ROOT,
    )
    try:
        listen(bus, 2.5)
    finally:
        pub.wait(timeout=10)
    bus.close()
    assert [m.speed_mps for m in got] == [4.5, 4.5, 4.5]


def test_zmq_bridge_carries_verified_messages_over_tcp(bus_url: str, key_file: Path, processes: Processes) -> None:

    processes.module("beacon", "--set", "rate_hz=20")
    endpoint = f"tcp://127.0.0.1:{random_port(1)}"
    bridge = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "rascal.cli",
            "bus",
            "bridge",
            "--bind",
            endpoint,
            "--channels",
            "OBSTACLES_.*",
            "--duration",
            "4",
        ],
        cwd=ROOT,
    )
    try:
        ground = Bus.open(
            "zmq://" + endpoint.removeprefix("tcp://"),
            source_id=905,
            clock=MasterClock(),
            keyring=load_keyring(key_file),
        )
        got: list[ObstacleList] = []
        ground.subscribe(channels.OBSTACLES_BEACON, lambda msg, env: got.append(msg))
        listen(ground, 3.0)
        ground.close()
    finally:
        bridge.wait(timeout=10)
    assert len(got) >= 20 and ground.rejected_total() == 0


def test_the_bus_tools_work_at_the_far_end_of_a_bridge(bus_url: str, key_file: Path, processes: Processes) -> None:
    """The far end is receive-only: the tools hear in their own time and ask the master nothing."""

    processes.module("beacon", "--set", "rate_hz=20")
    endpoint = f"127.0.0.1:{random_port(1)}"
    bridge = subprocess.Popen(
        [sys.executable, "-m", "rascal.cli", "bus", "bridge", "--bind", f"tcp://{endpoint}", "--duration", "30"],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
    )
    far = ("--bus", f"zmq://{endpoint}")
    time.sleep(1.0)
    try:
        echo = rascal(*far, "bus", "echo", channels.OBSTACLES_BEACON, "--count", "2", "--duration", "5")
        assert echo.returncode == 0 and len(echo.stdout.splitlines()) == 2, echo.stderr
        hz = rascal(*far, "bus", "hz", channels.OBSTACLES_BEACON, "--duration", "4.2", "--window", "2")
        assert hz.returncode == 0 and rates_of(hz), hz.stderr
        assert all(abs(rate - 20.0) <= 0.4 for rate in rates_of(hz)), hz.stdout
        listing = rascal(*far, "bus", "list", "--duration", "1.5")
        assert listing.returncode == 0 and "OBSTACLES_BEACON" in listing.stdout, listing.stderr
    finally:
        bridge.terminate()
        bridge.wait(timeout=10)


def test_a_zmq_message_over_the_bus_limit_is_dropped_not_buffered() -> None:
    """No bridge sends a frame over the bus's largest message: the subscriber hangs up on a peer
    that does rather than take it in (libzmq does not reconnect after such a protocol error)."""
    pub = zmq.Context.instance().socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    sub = ZmqSubscriberTransport(f"tcp://127.0.0.1:{port}")
    sub.listen_all()
    largest = b"a" * DEFAULT_MAX_MESSAGE_BYTES
    got: list[bytes] = []
    try:
        assert sub._socket.getsockopt(zmq.MAXMSGSIZE) == DEFAULT_MAX_MESSAGE_BYTES
        deadline = time.monotonic() + 10
        while not got and time.monotonic() < deadline:  # again until the subscription has arrived
            pub.send_multipart([b"X\0", largest])
            sub.receive(got.append, 0.1, 10)
        assert got and got[0] == largest  # the largest the bus carries still passes
        pub.send_multipart([b"X\0", b"b" * (DEFAULT_MAX_MESSAGE_BYTES + 1)])
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:
            pub.send_multipart([b"X\0", b"small"])
            sub.receive(got.append, 0.05, 10)
        assert max(len(message) for message in got) == DEFAULT_MAX_MESSAGE_BYTES
    finally:
        sub.close()
        pub.close()


def test_the_zmq_bridge_takes_only_subscription_sized_frames() -> None:
    bridge = Bridge("mem://zmq-bridge-limit", "tcp://127.0.0.1:0", ".*")
    try:
        assert bridge._socket.getsockopt(zmq.MAXMSGSIZE) == MAX_SUBSCRIPTION_BYTES
    finally:
        bridge.close()
