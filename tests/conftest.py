"""Shared fixtures: a private bus (own port range) and a private key file per test."""

from __future__ import annotations

import os
import random
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from protocol.auth import Keyring, write_keyring
from protocol.channels import DEFAULT_PORT_SPAN

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def key_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A fresh deployment key, also exported to child processes through RASCAL_KEY_FILE."""
    path = tmp_path / "bus.key"
    write_keyring(path, Keyring.generate())
    monkeypatch.setenv("RASCAL_KEY_FILE", str(path))
    return path


def random_port(step: int = DEFAULT_PORT_SPAN) -> int:
    """A random port (a multiple of ``step``, with ``step`` ports free after it) below the range
    the kernel hands out to sockets that bind none: an ephemeral port of any sender can then
    never hold a port a test binds (seen: a module failing with 'Address already in use')."""
    try:
        first_ephemeral = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        first_ephemeral = 32768  # Linux's default
    return random.randrange(20000, max(first_ephemeral - 256, 20000 + step), step)


@pytest.fixture
def bus_url(monkeypatch: pytest.MonkeyPatch) -> str:
    """A loopback multicast bus on a random port range, so tests never hear each other."""
    port = random_port()
    url = f"udpm://239.255.{random.randint(0, 255)}.{random.randint(1, 254)}:{port}?ttl=0"
    monkeypatch.setenv("RASCAL_BUS_URL", url)
    return url


class Processes:
    """Child processes started by a test, always stopped at its end."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.children: dict[str, subprocess.Popen[bytes]] = {}

    def module(self, name: str, *args: str, label: str | None = None) -> subprocess.Popen[bytes]:
        label = label or name
        log = (self.log_dir / f"{label}.log").open("wb")
        child = subprocess.Popen(
            [sys.executable, "-m", f"modules.{name}", *args], stdout=log, stderr=subprocess.STDOUT, cwd=ROOT
        )
        self.children[label] = child
        return child

    def log(self, label: str) -> str:
        return (self.log_dir / f"{label}.log").read_text()

    def stop_all(self) -> None:
        for child in self.children.values():
            if child.poll() is None:
                child.terminate()
        deadline = time.monotonic() + 5
        for child in self.children.values():
            try:
                child.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()


@pytest.fixture
def processes(tmp_path: Path) -> Iterator[Processes]:
    procs = Processes(tmp_path)
    try:
        yield procs
    finally:
        procs.stop_all()


def env_with(**extra: str) -> dict[str, str]:
    return {**os.environ, **extra}
