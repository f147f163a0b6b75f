"""ZeroMQ bridge: chosen channels over TCP to a subscriber multicast cannot reach.

The bridge forwards whole authenticated messages (reassembled, still signed), so the far end
verifies them end to end with the deployment key: open it with ``Bus.open("zmq://HOST:PORT")``.
Frames are ``[channel + b"\\0", message]``; the NUL makes ZeroMQ's prefix subscription exact.
"""

from __future__ import annotations

import re
import time

import zmq

from protocol.codec import Opened
from rascal.bustools import tool_bus

DEFAULT_ENDPOINT = "tcp://127.0.0.1:7700"
MAX_SUBSCRIPTION_BYTES = 1024  # what a subscriber sends is a channel name (and a short handshake)


class Bridge:
    """Forwards every accepted message whose channel matches ``pattern`` to a ZeroMQ PUB socket."""

    def __init__(self, url: str | None, endpoint: str, pattern: str) -> None:
        self.pattern = re.compile(pattern)
        self.bus, self.time_client = tool_bus(url)
        self._socket = zmq.Context.instance().socket(zmq.PUB)
        self._socket.setsockopt(zmq.LINGER, 0)
        self._socket.setsockopt(zmq.MAXMSGSIZE, MAX_SUBSCRIPTION_BYTES)  # a bigger one drops that subscriber
        self._socket.bind(endpoint)
        self.forwarded = 0
        self.bus.subscribe_raw(self._forward)

    def _forward(self, opened: Opened, data: bytes, recv_ns: int) -> None:
        if self.pattern.fullmatch(opened.channel):
            self._socket.send_multipart([opened.channel.encode("ascii") + b"\0", data])
            self.forwarded += 1

    def run(self, duration_s: float) -> None:
        deadline = time.monotonic() + duration_s
        next_sync = 0.0
        while (now := time.monotonic()) < deadline:
            if now >= next_sync:
                self.time_client.request()
                next_sync = now + 0.1
            self.bus.poll(min(0.1, deadline - now))

    def close(self) -> None:
        self._socket.close()
        self.bus.close()
