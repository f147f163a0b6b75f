"""The page's transport: a stdlib HTTP server with Server-Sent Events, off the bus loop.

The bus loop only ever calls :meth:`FrameHub.publish`: it serialises a topic once and swaps it in
under a lock, never touching a socket. Each browser gets its own thread that waits for a newer
version of any topic and sends the *latest* payload of each changed topic; versions a slow client
missed are skipped, never queued, so a client can fall behind by at most one frame per topic.
Requests must name this machine in their Host (see rascal.view.guard); threads are capped and a
client stalled for ``timeout_s``, reading or being written to, is dropped.
"""

from __future__ import annotations

import json
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, HTTPServer
from importlib import resources
from typing import Any

from rascal.view.guard import MAX_CONNECTIONS, TIMEOUT_S, Access, CappedThreads, Refusals

KEEPALIVE_S = 10.0
STATIC_FILES = {"/": ("index.html", "text/html; charset=utf-8"), "/view.js": ("view.js", "text/javascript")}
_dumps = json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode


class ViewServerError(RuntimeError):
    """The view cannot be served where asked (the port is taken, the address is not ours...)."""


class FrameHub:
    """Latest payload and version of each topic, and a condition the client threads wait on."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._topics: dict[str, tuple[int, bytes]] = {}
        self._closed = False
        self.published = 0

    def publish(self, topic: str, value: Any) -> None:
        """Replace ``topic``'s payload (JSON-serialisable; NaN and infinity are refused)."""
        payload = _dumps(value).encode()
        with self._cond:
            version = self._topics.get(topic, (0, b""))[0] + 1
            self._topics[topic] = (version, payload)
            self.published += 1
            self._cond.notify_all()

    def latest(self, topic: str) -> bytes | None:
        with self._cond:
            entry = self._topics.get(topic)
        return entry[1] if entry else None

    def wait_newer(self, seen: dict[str, int], timeout_s: float) -> list[tuple[str, bytes]] | None:
        """Topics newer than ``seen`` (which is updated), waiting up to ``timeout_s`` for one;
        None once the hub is closed."""
        with self._cond:
            self._cond.wait_for(lambda: self._closed or self._changed(seen), timeout_s)
            if self._closed:
                return None
            fresh = [(topic, version, payload) for topic, (version, payload) in self._topics.items()
                     if seen.get(topic, 0) < version]  # fmt: skip
        for topic, version, _ in fresh:
            seen[topic] = version
        return [(topic, payload) for topic, _, payload in fresh]

    def _changed(self, seen: dict[str, int]) -> bool:
        return any(seen.get(topic, 0) < version for topic, (version, _) in self._topics.items())

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


class ViewServer:
    """Serves the page, its script, ``/events`` (SSE) and ``/state.json`` (every topic, once)."""

    def __init__(
        self,
        hub: FrameHub,
        host: str = "127.0.0.1",
        port: int = 8090,
        access: Access | None = None,
        max_connections: int = MAX_CONNECTIONS,
        timeout_s: float = TIMEOUT_S,
    ) -> None:
        """``access``: the names the page may be reached by (default: ``host`` and loopback)."""
        self.hub = hub
        self.refusals = Refusals("viewer")
        attrs = {"hub": hub, "access": access or Access.of(host), "refusals": self.refusals, "timeout": timeout_s}
        handler = type("Handler", (_Handler,), attrs)
        try:
            self.httpd = _HTTPServer((host, port), handler, max_connections, self.refusals)
        except OSError as exc:
            raise ViewServerError(f"cannot serve the view on {host}:{port}: {exc.strerror or exc}") from None
        self._thread = threading.Thread(target=self.httpd.serve_forever, name="view-http", daemon=True)

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        return f"http://{host}:{port}/"

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self.hub.close()
        self.httpd.shutdown()
        self.httpd.server_close()
        self._thread.join(timeout=5)


class _HTTPServer(CappedThreads, HTTPServer):
    pass


class _Handler(BaseHTTPRequestHandler):
    hub: FrameHub
    access: Access
    refusals: Refusals
    protocol_version = "HTTP/1.1"

    def do_GET(self) -> None:
        path = self.path.split("?", 1)[0]
        hosts = self.headers.get_all("Host") or []
        if len(hosts) != 1 or not self.access.host_ok(hosts[0]):
            self.refusals.add("host", f"a request for Host {hosts} (DNS rebinding? else see --allow-host)")
            self.close_connection = True
            self._send(b"Host not allowed (see --allow-host)\n", "text/plain", HTTPStatus.FORBIDDEN)
        elif path == "/events":
            self._events()
        elif path == "/state.json":
            topics = {t: self.hub.latest(t) for t in ("course", "map", "scene", "trail", "health")}
            body = b"{" + b",".join(b'"%s":%s' % (t.encode(), p or b"null") for t, p in topics.items()) + b"}"
            self._send(body, "application/json")
        elif path in STATIC_FILES:
            name, content_type = STATIC_FILES[path]
            self._send(resources.files("rascal.view").joinpath("static", name).read_bytes(), content_type)
        else:
            self.send_error(HTTPStatus.NOT_FOUND)

    def _send(self, body: bytes, content_type: str, status: HTTPStatus = HTTPStatus.OK) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _events(self) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        seen: dict[str, int] = {}
        try:
            while (fresh := self.hub.wait_newer(seen, KEEPALIVE_S)) is not None:
                chunks = [b"event: %s\ndata: %s\n\n" % (topic.encode(), payload) for topic, payload in fresh]
                self.wfile.write(b"".join(chunks) or b": keepalive\n\n")
                self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            return  # the page went away

    def log_message(self, format: str, *args: Any) -> None:
        """Quiet: a page polling would fill the module's log."""
