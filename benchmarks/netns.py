"""Throwaway network namespaces: one with only loopback, or several hosts on a private bridge.

LCM sends multicast along the default route; inside a fresh namespace the only interface is
``lo`` and multicast is routed to it, so every contender stays on this host by construction.
Bridged hosts stand in for the vehicle's computers (tests/integration/test_three_hosts.py): each
host namespace has one veth to a bridge in a fourth, "switch" namespace, so nothing is added to
the root namespace and a host's link can be cut at the switch like a pulled cable.
"""

from __future__ import annotations

import ctypes
import os
import secrets
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

IP_TIMEOUT_S = 10.0
RMEM_MAX = Path("/proc/sys/net/core/rmem_max")
TERM_GRACE_S = 5.0
CLONE_NEWNET = 0x40000000
HOST_LINK = "eth0"  # every host's one interface (names are per namespace)
LINK_UP_TIMEOUT_S = 10.0


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
        _delete_namespace(name)


@dataclass(frozen=True)
class BridgedHosts:
    """Hosts (name -> namespace, address) on one bridge in the ``switch`` namespace."""

    switch: str
    namespaces: dict[str, str]
    addresses: dict[str, str]

    def command(self, host: str, argv: Sequence[str]) -> list[str]:
        """``argv`` run inside ``host``'s namespace (``ip netns exec`` execs it: same pid)."""
        return ["ip", "netns", "exec", self.namespaces[host], *argv]

    def cut(self, host: str) -> None:
        """Unplug ``host`` at the switch: its port goes down, its own interface loses carrier."""
        _ip("-n", self.switch, "link", "set", _port(host), "down")

    def reconnect(self, host: str) -> None:
        """Plug ``host`` back in; returns once both ends pass traffic again."""
        _ip("-n", self.switch, "link", "set", _port(host), "up")
        _wait_up(self.switch, _port(host))
        _wait_up(self.namespaces[host], HOST_LINK)

    @contextmanager
    def entered(self, host: str) -> Iterator[None]:
        """This thread in ``host``'s network namespace: sockets made meanwhile stay there."""
        with open("/proc/thread-self/ns/net", "rb") as home, open(f"/run/netns/{self.namespaces[host]}", "rb") as ns:
            _setns(ns.fileno())
            try:
                yield
            finally:
                _setns(home.fileno())


@contextmanager
def bridged_hosts(names: Sequence[str], subnet: str = "10.77.0") -> Iterator[BridgedHosts]:
    """Namespaces for ``names`` at ``subnet``.1, .2, ... /24 on one bridge; all deleted on exit.

    Namespace names carry a random suffix, so concurrent runs never share one.
    """
    if not 0 < len(names) < 250:
        raise ValueError(f"1..249 hosts, not {len(names)}")
    tag = secrets.token_hex(3)
    switch = f"rascal-{tag}-switch"
    hosts = BridgedHosts(
        switch,
        {name: f"rascal-{tag}-{name}" for name in names},
        {name: f"{subnet}.{i + 1}" for i, name in enumerate(names)},
    )
    with ExitStack() as cleanup:
        for namespace in (switch, *hosts.namespaces.values()):
            _ip("netns", "add", namespace)
            cleanup.callback(_delete_namespace, namespace)
        _ip("-n", switch, "link", "add", "br0", "type", "bridge", "mcast_snooping", "0")
        _ip("-n", switch, "link", "set", "br0", "up")
        for name, namespace in hosts.namespaces.items():
            port = _port(name)
            _ip("-n", switch, "link", "add", port, "type", "veth", "peer", "name", HOST_LINK, "netns", namespace)
            _ip("-n", switch, "link", "set", port, "master", "br0", "up")
            _ip("-n", namespace, "addr", "add", f"{hosts.addresses[name]}/24", "dev", HOST_LINK)
            _ip("-n", namespace, "link", "set", HOST_LINK, "up")
            _ip("-n", namespace, "link", "set", "lo", "up")
        for name, namespace in hosts.namespaces.items():
            _wait_up(switch, _port(name))
            _wait_up(namespace, HOST_LINK)
        yield hosts


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


def _port(host: str) -> str:
    return f"p-{host}"[:15]  # the switch's end of host's link (IFNAMSIZ)


def _wait_up(namespace: str, device: str) -> None:
    """Until ``device`` is operationally up: the kernel activates a link that got its carrier
    (its queue starts passing packets) in a work item, later still on a loaded machine."""
    deadline = time.monotonic() + LINK_UP_TIMEOUT_S
    while True:
        shown = subprocess.run(
            ["ip", "-n", namespace, "-o", "link", "show", "dev", device],
            capture_output=True,
            text=True,
            timeout=IP_TIMEOUT_S,
            check=False,
        )
        if " state UP " in shown.stdout:
            return
        if time.monotonic() > deadline:
            raise NamespaceError(
                f"{device} in {namespace} not up after {LINK_UP_TIMEOUT_S:.0f} s: {shown.stdout.strip()}"
            )
        time.sleep(0.05)


def _delete_namespace(name: str) -> None:
    subprocess.run(["ip", "netns", "delete", name], capture_output=True, timeout=IP_TIMEOUT_S, check=False)


def _setns(fd: int) -> None:
    # os.setns arrives in Python 3.12; until then libc's.
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.setns(fd, CLONE_NEWNET) != 0:
        raise NamespaceError(f"setns failed: {os.strerror(ctypes.get_errno())}")


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
