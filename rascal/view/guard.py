"""Who may talk to the view's servers, and how many at once.

Any web site the operator visits can make the browser connect to a loopback port: over HTTP by
pointing its own DNS name at 127.0.0.1 (DNS rebinding: the page then reads our answers as its
own), or with a WebSocket, which same-origin rules do not cover at all. So a request's Host, and a
WebSocket's Origin, must name this machine in a way no other site can; each server caps its
threads, and a peer that stalls for ``timeout_s`` (reading or being written to) is dropped.
"""

from __future__ import annotations

import ipaddress
import secrets
import selectors
import socket
import socketserver
import sys
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

MAX_CONNECTIONS = 32
TIMEOUT_S = 10.0
MAX_HEAD_BYTES = 16 * 1024
APP_ORIGINS = frozenset({"https://app.foxglove.dev"})  # Foxglove's web app opens its socket from there
REFUSED = b"HTTP/1.1 403 Forbidden\r\nContent-Type: text/plain\r\nContent-Length: %d\r\nConnection: close\r\n\r\n%s"


@dataclass(frozen=True)
class Access:
    """The names, beside IP literals and ``localhost``, this machine may be reached by."""

    names: frozenset[str] = frozenset()

    @classmethod
    def of(cls, host: str, extra: Iterable[str] = ()) -> Access:
        """The address served on (if a name) and the operator's ``--allow-host`` names."""
        return cls(frozenset(name.lower() for name in (host, *extra) if name))

    def host_ok(self, authority: str | None) -> bool:
        """A Host that is an IP literal, ``localhost`` or a listed name, on any port. A rebinding
        page's Host is its own DNS name; a page can send an IP only from that IP's own origin.
        The port is not checked: an ``ssh -L`` tunnel changes it, and adds no rebinding risk."""
        name = _hostname(authority)
        return name is not None and (name == "localhost" or name in self.names or _is_ip(name))

    def origin_ok(self, origin: str | None) -> bool:
        """No Origin (not a browser), a local app's (``file://``...), Foxglove's web app, or a web
        page on a host :meth:`host_ok` accepts. ``null`` (a sandboxed frame of any site) is not."""
        if origin is None:
            return True
        parts = urlsplit(origin)
        if parts.scheme in ("http", "https"):
            return origin in APP_ORIGINS or self.host_ok(parts.netloc)
        return bool(parts.scheme)


def _hostname(authority: str | None) -> str | None:
    """The lower-case host of a ``host[:port]`` header, IPv6 without brackets; None if malformed."""
    if not authority or any(c in authority for c in "@/\\?# \t"):
        return None
    try:
        parts = urlsplit("//" + authority)
        _ = parts.port  # a port that is no number raises
    except ValueError:
        return None
    return parts.hostname or None


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


class Refusals:
    """Connections refused, by reason: the first of each reason is logged, later ones only counted."""

    def __init__(self, who: str) -> None:
        self.who = who
        self.counts: dict[str, int] = {}
        self._lock = threading.Lock()

    def add(self, reason: str, detail: str) -> None:
        with self._lock:
            count = self.counts[reason] = self.counts.get(reason, 0) + 1
        if count == 1:
            print(f"{self.who}: refused {detail}; more such are counted, not logged", file=sys.stderr, flush=True)

    def snapshot(self) -> dict[str, int]:
        """The counts, copied under the lock (handler threads add to them)."""
        with self._lock:
            return dict(self.counts)


class CappedThreads(socketserver.ThreadingMixIn):
    """One daemon thread per connection, at most ``max_connections``: one over the cap is closed at once."""

    daemon_threads = True

    def __init__(self, address: tuple[str, int], handler: Any, max_connections: int, refusals: Refusals) -> None:
        self.max_connections = max_connections
        self.slots = threading.BoundedSemaphore(max_connections)
        self.refusals = refusals
        super().__init__(address, handler)  # type: ignore[call-arg]  # the server class mixed in takes these

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self.slots.acquire(blocking=False):
            self.refusals.add("busy", f"a connection over the cap of {self.max_connections} at once")
            self.shutdown_request(request)  # type: ignore[attr-defined]
            return
        try:
            super().process_request(request, client_address)
        except BaseException:  # no thread started (the process is out of them): its slot is free
            self.slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.slots.release()


class _TCPServer(CappedThreads, socketserver.TCPServer):
    allow_reuse_address = True


class WebSocketGuard:
    """Listens on ``host:port`` for a WebSocket server that cannot check Host and Origin itself
    (foxglove-sdk's): checks each handshake, then relays the connection to ``upstream``, which
    should listen where no web page can guess (see :func:`unguessable_loopback`)."""

    def __init__(
        self,
        host: str,
        port: int,
        upstream: tuple[str, int],
        access: Access,
        max_connections: int = MAX_CONNECTIONS,
        timeout_s: float = TIMEOUT_S,
    ) -> None:
        self.refusals = Refusals("viewer (Foxglove)")
        attrs = {"upstream": upstream, "access": access, "timeout_s": timeout_s, "refusals": self.refusals}
        handler = type("Handler", (_GuardHandler,), attrs)
        self.server = _TCPServer((host, port), handler, max_connections, self.refusals)
        self.port: int = self.server.server_address[1]
        self._thread = threading.Thread(target=self.server.serve_forever, name="view-ws-guard", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self._thread.join(timeout=5)


class _GuardHandler(socketserver.BaseRequestHandler):
    upstream: tuple[str, int]
    access: Access
    timeout_s: float
    refusals: Refusals

    def handle(self) -> None:
        client: socket.socket = self.request
        client.settimeout(self.timeout_s)
        try:
            head = _read_head(client, time.monotonic() + self.timeout_s)
            headers = _headers(head)
            host, origin = headers.get("host", [None]), headers.get("origin", [None])
            if len(host) != 1 or not self.access.host_ok(host[0]):
                self._refuse(client, "host", f"a WebSocket for Host {host}", b"Host not allowed (see --allow-host)\n")
            elif len(origin) != 1 or not self.access.origin_ok(origin[0]):
                self._refuse(client, "origin", f"a WebSocket from Origin {origin}", b"Origin not allowed\n")
            else:
                with socket.create_connection(self.upstream, timeout=self.timeout_s) as upstream:
                    upstream.sendall(head)
                    _relay(client, upstream)
        except (OSError, ValueError):
            return  # a peer that stalled, went away or sent no HTTP head

    def _refuse(self, client: socket.socket, reason: str, detail: str, text: bytes) -> None:
        self.refusals.add(reason, detail)
        client.sendall(REFUSED % (len(text), text))


def _read_head(sock: socket.socket, deadline: float) -> bytes:
    """The request head (and whatever followed it), by ``deadline``: a trickling peer gets no longer."""
    head = b""
    while b"\r\n\r\n" not in head:
        if len(head) > MAX_HEAD_BYTES or time.monotonic() > deadline:
            raise ValueError("no request head")
        chunk = sock.recv(4096)
        if not chunk:
            raise ValueError("closed before its request head")
        head += chunk
    return head


def _headers(head: bytes) -> dict[str, list[str]]:
    """Header values by lower-case name (a list: a repeated Host or Origin is refused)."""
    headers: dict[str, list[str]] = {}
    for line in head.split(b"\r\n\r\n", 1)[0].decode("latin-1").split("\r\n")[1:]:
        name, _, value = line.partition(":")
        headers.setdefault(name.strip().lower(), []).append(value.strip())
    return headers


def _relay(a: socket.socket, b: socket.socket) -> None:
    """Copy bytes both ways until either side closes; a send stalled for the socket timeout (a
    peer that stopped reading) raises and ends it."""
    peer = {a: b, b: a}
    with selectors.DefaultSelector() as selector:
        for sock in peer:
            selector.register(sock, selectors.EVENT_READ)
        while True:
            for key, _ in selector.select():
                data = key.fileobj.recv(65536)  # type: ignore[union-attr]
                if not data:
                    return
                peer[key.fileobj].sendall(data)  # type: ignore[index]


def unguessable_loopback() -> str:
    """A random 127/8 address (Linux routes all of it to loopback): with an ephemeral port, past
    what a web page could scan for, so only the guard (and local processes) reach what is there."""
    return f"127.{secrets.randbelow(256)}.{secrets.randbelow(256)}.{1 + secrets.randbelow(254)}"
