"""A throwaway network namespace with only loopback, for benchmarks that must not touch a NIC.

LCM sends multicast along the default route; inside a fresh namespace the only interface is
``lo`` and multicast is routed to it, so every contender stays on this host by construction.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

IP_TIMEOUT_S = 10.0
RMEM_MAX = Path("/proc/sys/net/core/rmem_max")
TERM_GRACE_S = 5.0


class NamespaceError(RuntimeError):
    """The namespace could not be set up; the message says which step failed."""


def unavailable_reason() -> str | None:
    """Why this process cannot create a namespace, or None when it can try."""
    if os.geteuid() != 0:
        return "not root"
    if shutil.which("ip") is None:
        return "no `ip` command"
    return None


@contextmanager
def loopback_namespace(name: str) -> Iterator[str]:
    """A new namespace with ``lo`` up and 224.0.0.0/4 routed to it; deleted on exit."""
    _ip("netns", "add", name)
    try:
        _ip("netns", "exec", name, "ip", "link", "set", "lo", "up")
        _ip("netns", "exec", name, "ip", "route", "add", "224.0.0.0/4", "dev", "lo")
        yield name
    finally:
        subprocess.run(["ip", "netns", "delete", name], capture_output=True, timeout=IP_TIMEOUT_S, check=False)


def run_in_namespace(name: str, argv: Sequence[str], timeout_s: float, cwd: Path) -> int:
    """Run ``argv`` inside the namespace; its whole process group is stopped if it overruns."""
    # Own session: the command and every child it forks share one process group we can signal.
    proc = subprocess.Popen(["ip", "netns", "exec", name, *argv], cwd=cwd, start_new_session=True)
    try:
        return proc.wait(timeout_s)
    finally:
        _stop_group(proc)


def raise_rmem_max(value: int) -> str:
    """Try to raise this namespace's receive-buffer cap; say what happened (kernels differ)."""
    try:
        before = int(RMEM_MAX.read_text())
    except OSError as exc:
        return f"net.core.rmem_max unreadable ({exc.strerror})"
    if before >= value:
        return f"net.core.rmem_max {before}"
    try:
        RMEM_MAX.write_text(f"{value}\n")
    except OSError as exc:
        return f"net.core.rmem_max stays {before} (raising it to {value} refused: {exc.strerror})"
    return f"net.core.rmem_max raised {before} -> {value}"


def _ip(*args: str) -> None:
    result = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=IP_TIMEOUT_S, check=False)
    if result.returncode != 0:
        raise NamespaceError(f"`ip {' '.join(args)}` failed: {result.stderr.strip()}")


def _stop_group(proc: subprocess.Popen[bytes]) -> None:
    for sig in (signal.SIGTERM, signal.SIGKILL):
        if proc.poll() is not None:
            return
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(TERM_GRACE_S)
        except subprocess.TimeoutExpired:
            continue
