"""The only socket code: datagram transports chosen by URL (LCM style).

    udpm://239.255.76.67:7667?ttl=0                 multicast on this host (loopback), default
    udpm://239.255.76.67:7667?ttl=1&iface=10.0.0.5  multicast on the vehicle LAN via that NIC
    ...&peers=10.0.0.7,10.0.0.8                      also unicast every datagram to these hosts
    mem://NAME                                       in-process hub, for unit tests
    zmq://HOST:PORT                                  receive-only: a ZeroMQ bridge's subscriber end

``RASCAL_BUS_URL`` overrides the default. Each channel maps to port ``PORT + crc32(channel) % span``
(see protocol.channels) so the kernel drops channels nobody on this host subscribed to.
Transports never block longer than asked: modules wait in :meth:`Transport.receive` until their next deadline.
"""

from __future__ import annotations

import ipaddress
import itertools
import math
import os
import select
import socket
import struct
import threading
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from urllib.parse import SplitResult, parse_qs, urlsplit

from protocol.channels import DEFAULT_PORT_SPAN, port_offset

DEFAULT_URL = "udpm://239.255.76.67:7667?ttl=0"
RECV_BUFFER_BYTES = 8 * 1024 * 1024
MAX_UDP_BYTES = 65535
IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)  # Linux; absent from Python's socket
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux

# deliver(datagram) or, from sockets with kernel timestamps, deliver(datagram, realtime_ns).
Deliver = Callable[..., None]
_TIMESPEC = struct.Struct("qq")
_TIMESTAMP_SPACE = socket.CMSG_SPACE(_TIMESPEC.size)


def default_url() -> str:
    return os.environ.get("RASCAL_BUS_URL", DEFAULT_URL)


class Transport(ABC):
    """Moves whole datagrams. No parsing, no clock: that is the bus's job."""

    can_send = True  # False for a receive-only end (send raises)

    @abstractmethod
    def send(self, channel: str, datagram: bytes) -> None: ...

    @abstractmethod
    def listen(self, channel: str, kernel_timestamps: bool = False, wake: bool = True) -> None:
        """Start receiving datagrams of ``channel`` (and whatever shares its port). With
        ``kernel_timestamps``, datagrams come with the kernel's CLOCK_REALTIME arrival time
        where the transport can tell it (time sync needs it: wake-up latency is asymmetric).
        ``wake=False``: arrivals on it do not end a :meth:`receive` wait; they are handed over
        when the wait ends anyway (for values read only by periodic work). Asking again with
        ``wake=True`` makes it wake."""

    @abstractmethod
    def listen_all(self, wake: bool = True) -> None:
        """Receive every channel: for bus tools that discover what is on the bus (``wake`` as
        for :meth:`listen`: a recorder need not wake for each datagram)."""

    @abstractmethod
    def receive(self, deliver: Deliver, timeout_s: float, budget: int) -> int:
        """Wait up to ``timeout_s`` for datagrams, then hand up to ``budget`` of those waiting to
        ``deliver``; return how many. ``timeout_s=0`` never blocks."""

    @abstractmethod
    def close(self) -> None:
        """Release sockets."""


@dataclass(frozen=True)
class UdpConfig:
    group: str
    base_port: int
    ttl: int = 0
    iface: str = "127.0.0.1"
    span: int = DEFAULT_PORT_SPAN
    peers: tuple[str, ...] = field(default_factory=tuple)

    def port(self, channel: str) -> int:
        return self.base_port + port_offset(channel, self.span)


class UdpMulticastTransport(Transport):
    """UDP multicast (plus optional unicast peers), one receive socket per port in use."""

    def __init__(self, config: UdpConfig) -> None:
        self.config = config
        self._tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, config.ttl)
        self._tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(config.iface))
        self._tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        self._tx.setblocking(False)
        self._rx: dict[int, socket.socket] = {}
        self._by_fd: dict[int, socket.socket] = {}
        self._timestamped: set[int] = set()
        self._epoll = select.epoll()
        self._waking: set[int] = set()  # fds whose datagrams end a wait
        self._idle = select.epoll()  # the others: read after each wait, those that have datagrams
        self._destinations: dict[str, tuple[tuple[str, int], ...]] = {}
        self.send_drops = 0

    def send(self, channel: str, datagram: bytes) -> None:
        targets = self._destinations.get(channel)
        if targets is None:
            port = self.config.port(channel)
            targets = ((self.config.group, port), *((peer, port) for peer in self.config.peers))
            self._destinations[channel] = targets
        for target in targets:
            try:
                self._tx.sendto(datagram, target)
            except BlockingIOError:
                # The socket send buffer is full: UDP semantics, the datagram is lost; counted.
                self.send_drops += 1

    def listen(self, channel: str, kernel_timestamps: bool = False, wake: bool = True) -> None:
        self._listen_port(self.config.port(channel), kernel_timestamps, wake)

    def listen_all(self, wake: bool = True) -> None:
        for offset in range(self.config.span):
            self._listen_port(self.config.base_port + offset, False, wake)

    def _listen_port(self, port: int, kernel_timestamps: bool, wake: bool) -> None:
        rx = self._open_port(port, wake)
        # A socket read only after a wait has its datagrams' arrival times from the kernel, so
        # late reading does not add to their measured latency.
        if (kernel_timestamps or rx.fileno() not in self._waking) and rx.fileno() not in self._timestamped:
            rx.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            self._timestamped.add(rx.fileno())

    def _open_port(self, port: int, wake: bool) -> socket.socket:
        rx = self._rx.get(port)
        if rx is None:
            rx = self._new_socket(port)
            (self._epoll if wake else self._idle).register(rx.fileno(), select.EPOLLIN)
            if wake:
                self._waking.add(rx.fileno())
        elif wake and rx.fileno() not in self._waking:
            self._idle.unregister(rx.fileno())
            self._epoll.register(rx.fileno(), select.EPOLLIN)
            self._waking.add(rx.fileno())
        return rx

    def _new_socket(self, port: int) -> socket.socket:
        rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        _grow_receive_buffer(rx)
        # Bound to the group, a socket gets only this bus's multicast; unicast peers need the
        # wildcard address to be reachable.
        rx.bind(("" if self.config.peers else self.config.group, port))
        membership = socket.inet_aton(self.config.group) + socket.inet_aton(self.config.iface)
        rx.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
        # Linux otherwise delivers every group joined by any socket on this port to a wildcard
        # bound socket; we want only our own group.
        rx.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)
        rx.setblocking(False)
        self._rx[port] = rx
        self._by_fd[rx.fileno()] = rx
        return rx

    def receive(self, deliver: Deliver, timeout_s: float, budget: int) -> int:
        # Wait first, then read only the sockets that are ready: an empty non-blocking recv
        # costs an exception (~2 us), which matters at 1 kHz and at 80 k msg/s alike.
        handled = 0
        ready = self._epoll.poll(max(timeout_s, 0.0))
        for fd, _events in itertools.chain(ready, self._idle.poll(0)):
            if fd in self._timestamped:
                handled += self._receive_timestamped(self._by_fd[fd], deliver, budget - handled)
                continue
            recv = self._by_fd[fd].recv
            while handled < budget:
                try:
                    datagram = recv(MAX_UDP_BYTES)
                except BlockingIOError:
                    break
                handled += 1
                deliver(datagram)
        return handled

    @staticmethod
    def _receive_timestamped(rx: socket.socket, deliver: Deliver, budget: int) -> int:
        handled = 0
        while handled < budget:
            try:
                datagram, ancillary, _flags, _addr = rx.recvmsg(MAX_UDP_BYTES, _TIMESTAMP_SPACE)
            except BlockingIOError:
                break
            handled += 1
            for level, kind, data in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
                    seconds, nanoseconds = _TIMESPEC.unpack_from(data)
                    deliver(datagram, seconds * 1_000_000_000 + nanoseconds)
                    break
            else:
                deliver(datagram)
        return handled

    def close(self) -> None:
        self._epoll.close()
        self._idle.close()
        for rx in self._rx.values():
            rx.close()
        self._rx.clear()
        self._tx.close()


def _grow_receive_buffer(sock: socket.socket) -> None:
    """Ask for a large receive buffer; as root, past net.core.rmem_max (bursts of 80 k msg/s)."""
    force = getattr(socket, "SO_RCVBUFFORCE", None)
    if force is not None and os.geteuid() == 0:
        try:
            sock.setsockopt(socket.SOL_SOCKET, force, RECV_BUFFER_BYTES)
            return
        except PermissionError:
            pass  # in a user namespace without CAP_NET_ADMIN
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECV_BUFFER_BYTES)


class _MemHub:
    def __init__(self) -> None:
        self.members: list[MemTransport] = []


_HUBS: dict[str, _MemHub] = {}


class MemTransport(Transport):
    """In-process transport: every member of the same ``mem://NAME`` hub receives every
    datagram of the channels it listens to (including its own, as with multicast loop)."""

    def __init__(self, name: str) -> None:
        self._hub = _HUBS.setdefault(name, _MemHub())
        self._hub.members.append(self)
        self._channels: set[str] = set()
        self._all = False
        self._queue: deque[bytes] = deque()
        self._arrived = threading.Condition()

    def send(self, channel: str, datagram: bytes) -> None:
        for member in self._hub.members:
            if member._all or channel in member._channels:
                with member._arrived:
                    member._queue.append(datagram)
                    member._arrived.notify()

    def listen(self, channel: str, kernel_timestamps: bool = False, wake: bool = True) -> None:
        self._channels.add(channel)

    def listen_all(self, wake: bool = True) -> None:
        self._all = True

    def receive(self, deliver: Deliver, timeout_s: float, budget: int) -> int:
        """Like a socket: wait up to ``timeout_s`` for a datagram (from another thread) when none
        is queued, rather than return at once and have a caller's loop spin."""
        handled = 0
        queue = self._queue
        if not queue and timeout_s > 0:
            with self._arrived:
                self._arrived.wait_for(lambda: bool(queue), timeout_s)
        while queue and handled < budget:
            deliver(queue.popleft())
            handled += 1
        return handled

    def close(self) -> None:
        if self in self._hub.members:
            self._hub.members.remove(self)


class ZmqSubscriberTransport(Transport):
    """Receive-only end of the ZeroMQ bridge: whole signed messages over TCP, one per frame."""

    can_send = False

    def __init__(self, endpoint: str) -> None:
        import zmq  # imported here: only bridge users pay for it

        from protocol.codec import DEFAULT_MAX_MESSAGE_BYTES

        self._zmq = zmq
        self._socket: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.SUB)
        self._socket.setsockopt(zmq.LINGER, 0)
        # A frame over the bus's largest message (no bridge sends one): libzmq hangs up on that peer, for
        # good, rather than take it in.
        self._socket.setsockopt(zmq.MAXMSGSIZE, DEFAULT_MAX_MESSAGE_BYTES)
        self._socket.connect(endpoint)
        self._poller = zmq.Poller()
        self._poller.register(self._socket, zmq.POLLIN)

    def send(self, channel: str, datagram: bytes) -> None:
        raise RuntimeError("a zmq:// bus is receive-only; publish on the vehicle bus")

    def listen(self, channel: str, kernel_timestamps: bool = False, wake: bool = True) -> None:
        self._socket.setsockopt(self._zmq.SUBSCRIBE, channel.encode("ascii") + b"\0")

    def listen_all(self, wake: bool = True) -> None:
        self._socket.setsockopt(self._zmq.SUBSCRIBE, b"")

    def receive(self, deliver: Deliver, timeout_s: float, budget: int) -> int:
        handled = 0
        if not self._poller.poll(math.ceil(max(timeout_s, 0.0) * 1000)):
            return 0
        while handled < budget:
            try:
                _topic, message = self._socket.recv_multipart(self._zmq.NOBLOCK)
            except self._zmq.Again:
                break
            except ValueError:
                continue  # a frame count other than two: not from our bridge
            handled += 1
            deliver(message)
        return handled

    def close(self) -> None:
        self._socket.close()


class UrlError(ValueError):
    """A bus URL that cannot be used; the message says which part."""


def open_transport(url: str | None = None) -> Transport:
    """Build the transport a URL names (``None``: ``$RASCAL_BUS_URL`` or the default).

    A ``faults=RULES`` option, else ``$RASCAL_FAULTS``, puts protocol.faults' link faults on the
    receive side (in a URL, write ``+`` in a rule as ``%2B``)."""
    from protocol import faults  # imports this module

    url = url or default_url()
    parts = urlsplit(url)
    query = {key: values[-1] for key, values in parse_qs(parts.query, keep_blank_values=True).items()}
    rules = query.pop("faults", None)
    where = f"{url}: faults"
    if rules is None:
        rules, where = os.environ.get(faults.FAULTS_ENV, ""), f"${faults.FAULTS_ENV}"
    transport = _open(url, parts, query)
    return faults.wrap(transport, rules, where) if rules.strip() else transport


def _open(url: str, parts: SplitResult, query: dict[str, str]) -> Transport:
    scheme = parts.scheme
    if scheme == "mem":
        return MemTransport(parts.netloc or parts.path or "default")
    if scheme == "zmq":
        return ZmqSubscriberTransport(f"tcp://{parts.netloc}")
    if scheme != "udpm":
        raise UrlError(f"{url}: unknown scheme {scheme!r}; use udpm://, mem:// or zmq://")
    try:
        port = parts.port
    except ValueError as exc:  # urllib's "Port out of range 0-65535", naming neither URL nor port
        raise UrlError(f"{url}: {exc}") from None
    return UdpMulticastTransport(_udp_config(url, parts.hostname, port, query))


def _udp_config(url: str, host: str | None, port: int | None, query: dict[str, str]) -> UdpConfig:
    known = {"ttl", "iface", "span", "peers"}
    unknown = set(query) - known
    if unknown:
        raise UrlError(f"{url}: unknown option(s) {sorted(unknown)}; known: {sorted(known)}")
    if host is None or port is None:
        raise UrlError(f"{url}: expected udpm://GROUP:PORT")
    try:
        multicast = ipaddress.IPv4Address(host).is_multicast
    except ValueError:
        multicast = False
    if not multicast:
        raise UrlError(f"{url}: {host} is not an IPv4 multicast group (224.0.0.0/4)")
    ttl = _int_option(url, query, "ttl", 0, 0, 32)
    span = _int_option(url, query, "span", DEFAULT_PORT_SPAN, 1, 1024)
    if port + span > 65536:
        raise UrlError(f"{url}: ports {port}..{port + span - 1} exceed 65535")
    iface = query.get("iface")
    if iface is None:
        if ttl > 0:
            # Never let the default route pick a NIC: off-host traffic is always a deliberate choice.
            raise UrlError(f"{url}: ttl={ttl} leaves this host; name the interface address with iface=")
        iface = "127.0.0.1"
    peers = tuple(peer for peer in query.get("peers", "").split(",") if peer)
    return UdpConfig(host, port, ttl, iface, span, peers)


def _int_option(url: str, query: dict[str, str], name: str, default: int, low: int, high: int) -> int:
    text = query.get(name)
    if text is None:
        return default
    if not text.isdigit() or not low <= int(text) <= high:
        raise UrlError(f"{url}: {name}={text!r} must be an integer {low}..{high}")
    return int(text)
