"""Transports: URL selection, loopback multicast, unicast peers, non-blocking receive."""

from __future__ import annotations

import time

import pytest

from protocol import channels
from protocol.auth import Keyring
from protocol.messages import Obstacle, ObstacleList, WheelSpeed
from protocol.transport import MemTransport, UdpMulticastTransport, UrlError, open_transport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from tests.conftest import random_port


def test_default_url_is_loopback_multicast(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("RASCAL_BUS_URL", raising=False)
    transport = open_transport()
    assert isinstance(transport, UdpMulticastTransport)
    assert (transport.config.ttl, transport.config.iface) == (0, "127.0.0.1")
    transport.close()


def test_every_declared_channel_has_a_port_of_its_own_at_the_default_span() -> None:
    """So a socket wakes only for the channel it subscribed to; a new channel whose name collides
    needs another name or a larger span (the smallest collision-free one)."""
    offsets = {channel: channels.port_offset(channel) for channel in channels.CHANNEL_TYPES}
    shared = {offset for offset in offsets.values() if list(offsets.values()).count(offset) > 1}
    assert not shared, {channel: offset for channel, offset in offsets.items() if offset in shared}


def test_environment_overrides_the_default(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RASCAL_BUS_URL", "mem://from-env")
    assert isinstance(open_transport(), MemTransport)


@pytest.mark.parametrize(
    ("url", "complaint"),
    [
        ("udpm://239.255.76.67:7667?ttl=1", "iface="),
        ("udpm://10.0.0.1:7667?ttl=0", "not an IPv4 multicast group"),
        ("udpm://239.255.76.67:7667?tll=0", "unknown option"),
        ("udpm://239.255.76.67:7667?ttl=x", "ttl='x'"),
        ("udpm://239.255.76.67?ttl=0", "GROUP:PORT"),
        ("tcp://127.0.0.1:1", "unknown scheme"),
    ],
)
def test_bad_urls_are_refused_with_the_reason(url: str, complaint: str) -> None:
    with pytest.raises(UrlError, match=complaint):
        open_transport(url)


def obstacles(count: int) -> ObstacleList:
    return ObstacleList(1, 0, tuple(Obstacle(float(i), 2.0, 1.0, 1.0, 1.0, 0.0, 0.9, 10.0) for i in range(count)))


def receive(bus: Bus, want: int, timeout_s: float = 2.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and sum(s.messages for s in bus.stats.values()) < want:
        bus.poll(0.05)


def test_multicast_on_loopback_delivers_to_every_subscriber(bus_url: str) -> None:
    keyring = Keyring.generate()
    publisher = Bus.open(bus_url, source_id=1, clock=MasterClock(), keyring=keyring)
    receivers = [Bus.open(bus_url, source_id=2 + i, clock=MasterClock(), keyring=keyring) for i in range(2)]
    got: list[list[ObstacleList]] = [[], []]
    for bus, inbox in zip(receivers, got, strict=True):
        bus.subscribe(channels.OBSTACLES_LIDAR, lambda msg, env, inbox=inbox: inbox.append(msg))
    sent = [obstacles(3), obstacles(2000)]  # the second is ~70 KB: fragmented
    for msg in sent:
        publisher.publish(channels.OBSTACLES_LIDAR, msg)
    for bus in receivers:
        receive(bus, 2)
    assert got == [sent, sent]
    for bus in (publisher, *receivers):
        bus.close()


def test_poll_without_traffic_returns_at_once() -> None:
    bus = Bus.open(
        f"udpm://239.255.1.1:{random_port()}?ttl=0",
        source_id=5,
        clock=MasterClock(),
        keyring=Keyring.generate(),
    )
    bus.subscribe(channels.WHEEL_SPEED, lambda msg, env: None)
    start = time.perf_counter()
    assert bus.poll(0.0) == 0
    assert time.perf_counter() - start < 0.01
    bus.close()


def test_unicast_peers_receive_without_joining_multicast(bus_url: str) -> None:
    keyring = Keyring.generate()
    publisher = Bus.open(bus_url + "&peers=127.0.0.2", source_id=1, clock=MasterClock(), keyring=keyring)
    # A receiver on another group only hears the unicast copy sent to 127.0.0.2.
    other_group = bus_url.replace("udpm://239.", "udpm://238.") + "&peers=127.0.0.3"
    receiver = Bus.open(other_group, source_id=2, clock=MasterClock(), keyring=keyring)
    got: list[WheelSpeed] = []
    receiver.subscribe(channels.WHEEL_SPEED, lambda msg, env: got.append(msg))
    publisher.publish(channels.WHEEL_SPEED, WheelSpeed(3.0, 10.0))
    receive(receiver, 1)
    assert got == [WheelSpeed(3.0, 10.0)]
    publisher.close()
    receiver.close()


def test_a_latest_value_does_not_wake_the_poll_and_keeps_its_arrival_time(bus_url: str) -> None:
    """A module reads latest values in its periodic work: their messages wait for the end of the
    poll's wait, with the kernel's arrival time, while a handler's message ends the wait at once."""
    keyring = Keyring.generate()
    publisher = Bus.open(bus_url, source_id=1, clock=MasterClock(), keyring=keyring)
    receiver = Bus.open(bus_url, source_id=2, clock=MasterClock(), keyring=keyring)
    speed = receiver.latest(channels.WHEEL_SPEED, 5_000_000_000)
    # Linux turns receive timestamping on system-wide a moment after the first socket asks for it
    # (a deferred static key): until then a datagram is stamped when it is read.
    time.sleep(0.1)
    published_ns = time.time_ns()
    publisher.publish(channels.WHEEL_SPEED, WheelSpeed(3.0, 10.0))
    start = time.perf_counter()
    assert receiver.poll(0.3) == 1
    assert time.perf_counter() - start >= 0.29  # the whole wait: the value did not wake it
    envelope = speed.read(receiver.clock.now_ns()).envelope
    assert envelope is not None and envelope.recv_ns - published_ns < 50_000_000  # as it arrived, not 0.3 s later
    # A handler on the same channel makes it wake.
    got: list[WheelSpeed] = []
    receiver.subscribe(channels.WHEEL_SPEED, lambda msg, env: got.append(msg))
    publisher.publish(channels.WHEEL_SPEED, WheelSpeed(4.0, 11.0))
    start = time.perf_counter()
    assert receiver.poll(2.0) == 1
    assert time.perf_counter() - start < 0.2 and got == [WheelSpeed(4.0, 11.0)]
    assert speed.read(receiver.clock.now_ns()).value == WheelSpeed(4.0, 11.0)
    publisher.close()
    receiver.close()
