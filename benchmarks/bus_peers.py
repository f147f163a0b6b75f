"""The contenders of the bus benchmark behind one small interface.

A :class:`Sender` stamps one ~300 B obstacle list with ``time.monotonic_ns()`` and sends it; a
:class:`Receiver` decodes what arrives and calls ``on_message(t_send_ns)`` after full decode, at
the moment a module's handler would run. CLOCK_MONOTONIC is system-wide, so the difference
between the receiver's and the sender's readings is the one-way latency across processes.

Every contender is built inside the process that uses it (sockets and LCM's receive thread must
not cross a fork); the objects here only hold configuration until then.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, Protocol

import msgpack

from protocol import channels
from protocol.auth import Keyring
from protocol.codec import Envelope
from protocol.messages import Frame, Obstacle, ObstacleList, Sensor
from protocol.transport import MAX_UDP_BYTES, RECV_BUFFER_BYTES
from rascal.runtime.bus import Bus

OnMessage = Callable[[int], None]

CHANNEL = channels.OBSTACLES_LIDAR
PUBLISHER_ID = 101
SUBSCRIBER_ID = 102
LCM_TYPES = Path(__file__).with_name("obstacle_list.lcm")

OBSTACLES = ObstacleList(
    sensor=Sensor.LIDAR_H_LEFT,
    frame=Frame.VEHICLE,
    obstacles=tuple(
        Obstacle(12.5 + 3.25 * i, -1.75 + 1.125 * i, 4.2, 1.9, 1.6, 0.05 * i, 0.93, 12.8 + 3.3 * i) for i in range(4)
    ),
)


class Sender(Protocol):
    def send(self) -> None: ...

    def dropped(self) -> int:
        """Datagrams the OS refused at send time (a full non-blocking socket)."""

    def close(self) -> None: ...


class Receiver(Protocol):
    def pump(self, timeout_s: float) -> int:
        """Handle what is waiting, blocking at most ``timeout_s`` for the first; return count.

        ``timeout_s=0.0`` must never block: the hot latency regime busy-polls with it."""

    def close(self) -> None: ...


class Contender(Protocol):
    name: str

    def wire_bytes(self) -> int:
        """Size of one encoded obstacle list as this contender sends it (its own framing included)."""

    def sender(self) -> Sender: ...

    def receiver(self, on_message: OnMessage) -> Receiver: ...


class MonotonicClock:
    """rascal Clock on CLOCK_MONOTONIC in every process, so header ``t_pub_ns`` is the send time.

    Synced, so the bus also runs its freshness check as it does on a synchronised vehicle."""

    synced = True

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def local_ns(self) -> int:
        return time.monotonic_ns()

    def to_shared(self, local_ns: int) -> int:
        return local_ns


# -- raw UDP + msgpack: the floor ------------------------------------------------------------


def _multicast_tx() -> socket.socket:
    # Same options as rascal's transport, so all contenders take the same kernel path.
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
    return sock


def _multicast_rx(group: str, port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    force = getattr(socket, "SO_RCVBUFFORCE", None)
    # The buffer rascal's transport asks for, so loss compares the code and not the buffer.
    if force is not None and os.geteuid() == 0:
        sock.setsockopt(socket.SOL_SOCKET, force, RECV_BUFFER_BYTES)
    else:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECV_BUFFER_BYTES)
    sock.bind((group, port))
    membership = socket.inet_aton(group) + socket.inet_aton("127.0.0.1")
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
    return sock


def _raw_payload() -> bytes:
    sensor, frame, obstacles = OBSTACLES
    return msgpack.packb((time.monotonic_ns(), sensor, frame, obstacles))


class _RawSender:
    def __init__(self, target: tuple[str, int]) -> None:
        self._sock = _multicast_tx()
        self._target = target

    def send(self) -> None:
        self._sock.sendto(_raw_payload(), self._target)

    def dropped(self) -> int:
        return 0  # a blocking socket waits instead of dropping

    def close(self) -> None:
        self._sock.close()


class _RawReceiver:
    def __init__(self, group: str, port: int, on_message: OnMessage) -> None:
        self._sock = _multicast_rx(group, port)
        self._timeout_s = self._sock.gettimeout()
        self._on_message = on_message

    def pump(self, timeout_s: float) -> int:
        # settimeout() is a syscall every time; a busy-polling caller repeats the same value, and
        # an extra syscall per poll would inflate the floor everything is compared against.
        if timeout_s != self._timeout_s:
            self._sock.settimeout(timeout_s)
            self._timeout_s = timeout_s
        try:
            data = self._sock.recv(MAX_UDP_BYTES)
        except (TimeoutError, BlockingIOError):
            # TimeoutError when a wait ran out; BlockingIOError from a timeout of 0.0, which puts
            # the socket in non-blocking mode.
            return 0
        t_send_ns, _sensor, _frame, _obstacles = msgpack.unpackb(data, use_list=False)
        self._on_message(t_send_ns)
        return 1

    def close(self) -> None:
        self._sock.close()


@dataclass(frozen=True)
class RawUdp:
    group: str
    port: int
    name: str = "raw UDP + msgpack"

    def wire_bytes(self) -> int:
        return len(_raw_payload())

    def sender(self) -> Sender:
        return _RawSender((self.group, self.port))

    def receiver(self, on_message: OnMessage) -> Receiver:
        return _RawReceiver(self.group, self.port, on_message)


# -- LCM's Python binding ---------------------------------------------------------------------


def generate_lcm_types(out_dir: Path) -> ModuleType:
    """Run lcm-gen on the benchmark's .lcm file into ``out_dir`` and import the result."""
    lcm_gen = Path(sys.executable).with_name("lcm-gen")
    subprocess.run(
        [str(lcm_gen), "-p", "--ppath", str(out_dir), str(LCM_TYPES)], check=True, capture_output=True, timeout=30
    )
    sys.path.insert(0, str(out_dir))
    import rascal_bench  # generated just above

    return rascal_bench


def _lcm_message(types: ModuleType) -> Any:
    msg = types.obstacle_list_t()
    msg.sensor, msg.frame, obstacles = OBSTACLES
    for source in obstacles:
        item = types.obstacle_t()
        for name, value in zip(Obstacle._fields, source, strict=True):
            setattr(item, name, value)
        msg.obstacles.append(item)
    msg.count = len(msg.obstacles)
    return msg


class _LcmSender:
    def __init__(self, provider: str, types: ModuleType) -> None:
        import lcm

        self._lc = lcm.LCM(provider)
        self._msg = _lcm_message(types)

    def send(self) -> None:
        msg = self._msg
        msg.t_send_ns = time.monotonic_ns()
        self._lc.publish(CHANNEL, msg.encode())

    def dropped(self) -> int:
        return 0

    def close(self) -> None:
        del self._lc  # the binding has no close(); the handle goes with the object


class _LcmReceiver:
    def __init__(self, provider: str, types: ModuleType, on_message: OnMessage) -> None:
        import lcm

        decode = types.obstacle_list_t.decode

        def handle(_channel: str, data: bytes) -> None:
            on_message(decode(data).t_send_ns)

        self._lc = lcm.LCM(provider)
        self._lc.subscribe(CHANNEL, handle)

    def pump(self, timeout_s: float) -> int:
        # Whole milliseconds, rounded down so it never waits longer than asked. 0 is a true
        # non-blocking poll in lcm 1.5.3: idle, handle_timeout(0) returns 0 in about 1 us.
        return 1 if self._lc.handle_timeout(int(timeout_s * 1000)) > 0 else 0

    def close(self) -> None:
        del self._lc


@dataclass(frozen=True)
class Lcm:
    provider: str
    types: ModuleType
    name: str = "LCM (Python binding)"

    def wire_bytes(self) -> int:
        # LCM's small-message datagram: 8 B header, channel name and NUL, then the encoded type.
        return 8 + len(CHANNEL) + 1 + len(_lcm_message(self.types).encode())

    def sender(self) -> Sender:
        return _LcmSender(self.provider, self.types)

    def receiver(self, on_message: OnMessage) -> Receiver:
        return _LcmReceiver(self.provider, self.types, on_message)


# -- rascal Bus -------------------------------------------------------------------------------


def _open_bus(url: str, source_id: int, keyring: Keyring | None) -> Bus:
    return Bus.open(url, source_id=source_id, clock=MonotonicClock(), keyring=keyring, signing=keyring is not None)


class _RascalSender:
    def __init__(self, url: str, keyring: Keyring | None) -> None:
        self._bus = _open_bus(url, PUBLISHER_ID, keyring)

    def send(self) -> None:
        self._bus.publish(CHANNEL, OBSTACLES)

    def dropped(self) -> int:
        return getattr(self._bus.transport, "send_drops", 0)

    def close(self) -> None:
        self._bus.close()


class _RascalReceiver:
    def __init__(self, url: str, keyring: Keyring | None, on_message: OnMessage) -> None:
        def handle(_msg: ObstacleList, envelope: Envelope) -> None:
            on_message(envelope.t_pub_ns)

        self._bus = _open_bus(url, SUBSCRIBER_ID, keyring)
        self._bus.subscribe(CHANNEL, handle)

    def pump(self, timeout_s: float) -> int:
        return self._bus.poll(timeout_s)

    def close(self) -> None:
        self._bus.close()


@dataclass(frozen=True)
class Rascal:
    """``keyring=None`` is the bus's explicit unsigned mode."""

    url: str
    keyring: Keyring | None
    name: str = "rascal Bus"

    def wire_bytes(self) -> int:
        bus = _open_bus("mem://bench-size", PUBLISHER_ID, self.keyring)
        try:
            return len(bus.codec.encode(CHANNEL.encode("ascii"), OBSTACLES, PUBLISHER_ID, 0, 0, 0))
        finally:
            bus.close()

    def sender(self) -> Sender:
        return _RascalSender(self.url, self.keyring)

    def receiver(self, on_message: OnMessage) -> Receiver:
        return _RascalReceiver(self.url, self.keyring, on_message)
