"""``rascal spoof``: every kind of hostile datagram, sent by a real spoofer process to a real
receiving Bus on a private loopback bus, is rejected and counted per source and reason, and none
is delivered; replays of a recording meet the replay window; off-host buses are refused."""

from __future__ import annotations

import json
import random
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import pytest

from protocol import channels
from protocol.auth import load_keyring
from protocol.codec import Codec, Envelope, decode_body
from protocol.errors import ProtocolError
from protocol.messages import ActuatorCommand
from protocol.replay import ReplayLimits
from rascal.recording import RecordingWriter
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from rascal.spoof import DEFAULT_SOURCE_ID, Forger, SpoofError, fake_message, loopback_only, spoof
from tests.conftest import ROOT
from tests.protocol.wire_samples import keyring

RECEIVER_ID = 60
GENUINE_ID = 61


class Receiver:
    """A Bus on the test's bus, subscribed to one channel, counting what its handler gets."""

    def __init__(self, bus_url: str, key_file: Path, channel: str, **options: Any) -> None:
        self.bus = Bus.open(
            bus_url, source_id=RECEIVER_ID, clock=MasterClock(), keyring=load_keyring(key_file), **options
        )
        self.delivered = 0
        self.bus.subscribe(channel, self._count)
        if channel != channels.ACTUATOR_COMMAND:
            self.bus.subscribe(channels.ACTUATOR_COMMAND, self._count)

    def _count(self, _msg: Any, _envelope: Envelope) -> None:
        self.delivered += 1

    def rejects(self) -> Counter[tuple[int | None, str]]:
        return Counter(self.bus.rejects)

    def wait_for(self, child: subprocess.Popen[str], timeout_s: float = 60.0) -> dict[str, Any]:
        """Poll while the spoofer runs; return its report once every datagram it sent is counted."""
        deadline = time.monotonic() + timeout_s
        while child.poll() is None and time.monotonic() < deadline:
            self.bus.poll(0.02)
        stdout, stderr = child.communicate(timeout=max(1.0, deadline - time.monotonic()))
        assert child.returncode == 0, stderr
        report = json.loads(stdout.strip().splitlines()[-1])
        while time.monotonic() < deadline and self.bus.rejected_total() + self.delivered < report["total"]:
            self.bus.poll(0.05)
        self.bus.poll(0.2)  # anything more would be a miscount
        return report

    def close(self) -> None:
        self.bus.close()


def start_spoofer(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "rascal.cli", "spoof", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )


@pytest.mark.slow
@pytest.mark.parametrize(
    ("args", "reasons"),
    [
        (("forge", "--channel", "OBSTACLES_LIDAR", "--rate", "1000", "--count", "1000"), {"bad_mac"}),
        (("forge", "--channel", "OBSTACLES_ESVS", "--sign", "none"), {"unsigned"}),
        (("forge", "--channel", "ACTUATOR_COMMAND", "--rate", "1000", "--count", "1000"), {"bad_mac"}),
        (("mutate", "--sign", "deployment", "--count", "300", "--rate", "2000"), None),
        (("truncate", "--count", "300", "--rate", "2000"), None),
        (("oversize", "--count", "300", "--rate", "2000"), {"oversized"}),
        (("garbage", "--count", "300", "--rate", "2000"), None),
    ],
    ids=[
        "fake-obstacles-wrong-key",
        "fake-esvs-unsigned",
        "fake-commands",
        "mutate",
        "truncate",
        "oversize",
        "garbage",
    ],
)
def test_every_spoofed_kind_is_rejected_counted_and_never_delivered(
    bus_url: str, key_file: Path, args: tuple[str, ...], reasons: set[str] | None
) -> None:
    channel = args[args.index("--channel") + 1] if "--channel" in args else channels.ACTUATOR_COMMAND
    receiver = Receiver(bus_url, key_file, channel)
    try:
        report = receiver.wait_for(start_spoofer(*args, "--seed", "5"))
        rejects = receiver.rejects()
        assert receiver.delivered == 0
        assert sum(rejects.values()) == report["total"] > 0, (rejects, report)
        if reasons is not None:
            # Well-formed spoofs are counted against the source they claim.
            assert set(rejects) == {(DEFAULT_SOURCE_ID, reason) for reason in reasons}, rejects
    finally:
        receiver.close()


@pytest.mark.slow
def test_replayed_recordings_meet_the_replay_window_and_freshness(bus_url: str, key_file: Path, tmp_path: Path) -> None:
    keys = load_keyring(key_file)
    # A receiver that heard the originals; its freshness window is wide so only the sequence window judges.
    heard = Receiver(bus_url, key_file, channels.ACTUATOR_COMMAND, replay_limits=ReplayLimits(max_age_ns=600 * 10**9))
    writer = RecordingWriter(tmp_path / "run.mcap", {"test": "replay"})
    heard.bus.subscribe_raw(writer.write)
    genuine = Bus.open(bus_url, source_id=GENUINE_ID, clock=MasterClock(), keyring=keys)
    for _ in range(50):
        genuine.publish(channels.ACTUATOR_COMMAND, ActuatorCommand(0.3, 0.0, 0.01))
        heard.bus.poll(0.005)
    deadline = time.monotonic() + 10
    while heard.delivered < 50 and time.monotonic() < deadline:
        heard.bus.poll(0.05)
    writer.close({})
    published_s = time.monotonic()
    genuine.close()
    assert heard.delivered == 50
    try:
        # A receiver that never heard them, past the 2 s freshness window: they are stale.
        fresh = Receiver(bus_url, key_file, channels.ACTUATOR_COMMAND)
        time.sleep(max(0.0, published_s + 2.5 - time.monotonic()))
        child = start_spoofer("replay", "--recording", str(tmp_path / "run.mcap"), "--count", "100", "--rate", "500")
        report = heard.wait_for(child)
        fresh.bus.poll(0.5)
        assert report["total"] == 100 and report["sent"] == {"replay: replayed": 100}
        assert heard.delivered == 50 and heard.rejects() == {(GENUINE_ID, "replay"): 100}
        assert fresh.delivered == 0 and fresh.rejects() == {(GENUINE_ID, "stale"): 100}
        fresh.close()
    finally:
        heard.close()


@pytest.mark.parametrize(
    ("url", "complaint"),
    [
        ("udpm://239.255.1.2:30000?ttl=1&iface=10.0.0.5", "ttl=1 leaves this host"),
        ("udpm://239.255.1.2:30000?ttl=0&iface=10.0.0.5", "10.0.0.5 is not a loopback address"),
        ("udpm://239.255.1.2:30000?ttl=0&peers=127.0.0.2,192.168.1.9", "192.168.1.9 is not a loopback"),
        ("zmq://127.0.0.1:7700", "only udpm://"),
    ],
)
def test_destinations_off_this_host_are_refused(url: str, complaint: str) -> None:
    with pytest.raises(SpoofError, match=complaint):
        loopback_only(url)
    loopback_only("udpm://239.255.1.2:30000?ttl=0&peers=127.0.0.2")  # loopback peers are fine


def test_the_command_refuses_off_host_buses_and_unbounded_runs(key_file: Path) -> None:
    for args, complaint in [
        (("forge", "--bus", "udpm://239.255.1.2:30000?ttl=2&iface=10.0.0.5"), "ttl=2 leaves this host"),
        (("forge", "--count", "2000000"), "--count must be"),
        (("forge", "--duration", "3600"), "--duration must be"),
        (("forge", "--rate", "0"), "--rate must be"),
        (("forge", "--sign", "deployment"), "only for mutate"),
        (("forge", "--channel", "GPS"), "no built-in fake for GPS"),
    ]:
        result = subprocess.run(
            [sys.executable, "-m", "rascal.cli", "spoof", *args], capture_output=True, text=True, cwd=ROOT, timeout=60
        )
        assert result.returncode == 2 and complaint in result.stderr, (args, result.stderr)
        assert not result.stdout


class FakeTime:
    def __init__(self) -> None:
        self.t = 0.0

    def sleep(self, seconds: float) -> None:
        self.t += seconds

    def monotonic(self) -> float:
        return self.t


class Sink:
    def __init__(self) -> None:
        self.sent: list[tuple[str, bytes]] = []

    def send(self, channel: str, datagram: bytes) -> None:
        self.sent.append((channel, datagram))


def forger(kind_sign: str = "wrong", channel: str = channels.ACTUATOR_COMMAND) -> Forger:
    keys = keyring() if kind_sign == "deployment" else keyring(9)
    return Forger(channel, fake_message(channel, None), keys, DEFAULT_SOURCE_ID, random.Random(1), time.time_ns)


def test_runs_stop_at_the_count_or_the_duration_at_the_rate() -> None:
    clock, sink = FakeTime(), Sink()
    sent = spoof(sink, forger(), "forge", 500, 60.0, 100.0, clock.sleep, clock.monotonic)  # type: ignore[arg-type]
    assert sent == {"forge: forged": 500} and clock.t == pytest.approx(4.99)
    clock, sink = FakeTime(), Sink()
    sent = spoof(sink, forger(), "forge", 10_000, 2.0, 100.0, clock.sleep, clock.monotonic)  # type: ignore[arg-type]
    assert sum(sent.values()) == 200 and len(sink.sent) == 200


def test_mutations_always_break_even_a_correctly_signed_message() -> None:
    """Mutated deployment-signed messages never pass the codec: no mutation is a no-op."""
    sink, clock = Sink(), FakeTime()
    spoof(sink, forger("deployment"), "mutate", 3000, 60.0, 1e5, clock.sleep, clock.monotonic)  # type: ignore[arg-type]
    codec = Codec(keyring())
    for _channel, datagram in sink.sent:
        with pytest.raises(ProtocolError):
            opened = codec.open(datagram)
            decode_body(opened.type_id, opened.body)


def test_fake_messages_and_json_bodies() -> None:
    assert fake_message(channels.OBSTACLES_LIDAR, None).obstacles[0].x_m == 8.0
    assert fake_message(channels.ACTUATOR_COMMAND, '{"throttle": 0.5, "brake": 0, "steering_rad": 0}').throttle == 0.5
    with pytest.raises(SpoofError, match="not a ActuatorCommand"):
        fake_message(channels.ACTUATOR_COMMAND, '{"speed": 1}')
    with pytest.raises(SpoofError, match="not declared"):
        fake_message("NOPE", None)
