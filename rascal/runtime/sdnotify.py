"""systemd's service notification (sd_notify): READY=1 once a module runs, WATCHDOG=1 with each
heartbeat, so a ``Type=notify`` unit with ``WatchdogSec`` restarts a module that hangs.

The protocol is one datagram of ``KEY=VALUE`` lines to the AF_UNIX socket named by
``$NOTIFY_SOCKET`` (a leading ``@`` means the abstract namespace). Outside systemd the variable
is unset and every call does nothing. A failed send is counted, never raised: losing the
service manager must not take the module down with it.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping

NOTIFY_SOCKET_ENV = "NOTIFY_SOCKET"
MAX_STATUS_CHARS = 200


class Notifier:
    """Sends notifications to the socket in ``$NOTIFY_SOCKET`` (or none, when it is unset)."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        address = (os.environ if environ is None else environ).get(NOTIFY_SOCKET_ENV, "")
        self.address = "\0" + address[1:] if address.startswith("@") else address
        self.failures = 0
        self._socket: socket.socket | None = None
        if self.address:
            self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        return self._socket is not None

    def notify(self, **fields: str) -> bool:
        """Send ``READY="1"``, ``WATCHDOG="1"``, ``STATUS="..."``... as one datagram."""
        if self._socket is None:
            return False
        text = "\n".join(f"{key}={_one_line(value)}" for key, value in fields.items())
        try:
            self._socket.sendto(text.encode("utf-8", errors="replace"), self.address)
        except OSError:
            self.failures += 1
            return False
        return True

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None


def _one_line(value: str) -> str:
    return value.replace("\n", " ")[:MAX_STATUS_CHARS]
