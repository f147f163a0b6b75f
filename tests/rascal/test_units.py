"""systemd units: `rascal deploy units` output passes `systemd-analyze verify` with nothing on
stderr, and a real module started the way a unit starts it (`rascal deploy exec`) tells the
service manager READY=1, then WATCHDOG=1 with every heartbeat, from the PID systemd started."""

from __future__ import annotations

import os
import shutil
import socket
import struct
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from rascal.deployment import load_deployment
from rascal.sdnotify import Notifier
from rascal.units import write_units
from tests.conftest import ROOT

SYSTEMD_ANALYZE = shutil.which("systemd-analyze") or "/usr/bin/systemd-analyze"
RASCAL = Path(sys.executable).with_name("rascal")
THREE_HOSTS = ROOT / "deploy" / "vehicle-3hosts.toml"


def _verify(*units: Path) -> subprocess.CompletedProcess[str]:
    command = [SYSTEMD_ANALYZE, "verify", *map(str, units)]
    return subprocess.run(command, capture_output=True, text=True, timeout=120)


def test_units_of_every_host_pass_systemd_analyze_verify(tmp_path: Path) -> None:
    if not Path(SYSTEMD_ANALYZE).exists():
        pytest.skip("systemd-analyze is not installed, so the generated units cannot be verified here")
    assert RASCAL.exists(), "the units run this environment's rascal command"
    deployment = load_deployment(THREE_HOSTS)
    written = write_units(deployment, tmp_path, RASCAL)
    assert set(written) == {"sensors", "brainbox", "drive"}
    for host, files in written.items():
        host_dir = tmp_path / host
        labels = [spec.label for spec in deployment.on_host(host)]
        target = (host_dir / f"rascal-{host}.target").read_text()
        assert f"Wants={' '.join(f'rascal@{label}.service' for label in labels)}\n" in target
        assert len(files) == 3 + len(labels)
        template = (host_dir / "rascal@.service").read_text()
        for line in ("Type=notify", "Restart=on-failure", "RestartSec=1", "WatchdogSec=3", f"ExecStart={RASCAL} "):
            assert line in template
        assert "@" not in template.replace("rascal@", "").replace("%i", "")  # every field filled in
        env = (host_dir / "rascal.env").read_text()
        assert f'RASCAL_DEPLOYMENT="{THREE_HOSTS}"' in env and f'RASCAL_BUS_URL="{deployment.bus_on(host)}"' in env
        # The target pulls in every instance with its drop-in; each instance verifies on its own too.
        result = _verify(
            host_dir / f"rascal-{host}.target", *(host_dir / f"rascal@{label}.service" for label in labels)
        )
        assert result.returncode == 0 and result.stderr == "", f"{host}: {result.stderr}"
    drop_in = (tmp_path / "sensors" / "rascal@lidar_h_left.service.d" / "deployment.conf").read_text()
    assert "WatchdogSec=3000ms" in drop_in and "Nice=0" in drop_in


def test_a_broken_unit_does_not_verify(tmp_path: Path) -> None:
    """The check above can fail: a unit systemd cannot use makes it complain on stderr."""
    if not Path(SYSTEMD_ANALYZE).exists():
        pytest.skip("systemd-analyze is not installed, so the generated units cannot be verified here")
    write_units(load_deployment(THREE_HOSTS), tmp_path, tmp_path / "no-such-rascal")
    result = _verify(tmp_path / "drive" / "rascal@control.service")
    assert "no-such-rascal" in result.stderr


def test_bad_requests_get_clear_errors(tmp_path: Path) -> None:
    deployment = load_deployment(THREE_HOSTS)
    with pytest.raises(ValueError, match="absolute path"):
        write_units(deployment, tmp_path, Path("bin/rascal"))
    odd = tmp_path / "odd.toml"
    odd.write_text(
        '[deployment]\nbus = "udpm://239.255.1.2:7700?ttl=0"\n[modules."time service"]\nmodule = "time_service"\n'
    )
    with pytest.raises(ValueError, match="'time service' cannot name a systemd unit"):
        write_units(load_deployment(odd), tmp_path, RASCAL)
    result = subprocess.run(
        [str(RASCAL), "deploy", "exec", str(THREE_HOSTS), "nonesuch"], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2 and "no module 'nonesuch'" in result.stderr


def test_notifier_is_silent_without_systemd_and_tolerates_a_gone_manager() -> None:
    assert not Notifier({}).notify(READY="1")
    gone = Notifier({"NOTIFY_SOCKET": f"@rascal-gone-{uuid.uuid4().hex}"})
    assert gone.enabled and not gone.notify(WATCHDOG="1") and gone.failures == 1


def _receive(sock: socket.socket, deadline: float) -> tuple[dict[str, str], int]:
    """One notification: its fields and the sender's PID (as systemd learns it, SCM_CREDENTIALS)."""
    sock.settimeout(max(0.01, deadline - time.monotonic()))
    data, ancillary, _flags, _addr = sock.recvmsg(4096, socket.CMSG_SPACE(struct.calcsize("3i")))
    pid = next(struct.unpack("3i", item[2])[0] for item in ancillary if item[1] == socket.SCM_CREDENTIALS)
    fields = dict(line.split("=", 1) for line in data.decode().splitlines())
    return fields, pid


@pytest.mark.slow
def test_a_module_under_deploy_exec_notifies_ready_then_the_watchdog(
    tmp_path: Path, bus_url: str, key_file: Path
) -> None:
    deployment = tmp_path / "one.toml"
    deployment.write_text(
        f'[deployment]\nname = "one"\nbus = "{bus_url}"\nkey_file = "{key_file}"\n[modules.time_service]\n'
    )
    name = f"rascal-test-{uuid.uuid4().hex}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name)  # the abstract namespace, as NOTIFY_SOCKET=@NAME names it
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
        log = (tmp_path / "module.log").open("wb")
        env = {**os.environ, "NOTIFY_SOCKET": f"@{name}"}
        child = subprocess.Popen(
            [str(RASCAL), "deploy", "exec", str(deployment), "time_service"], stdout=log, stderr=log, env=env
        )
        try:
            deadline = time.monotonic() + 60.0
            received: list[dict[str, str]] = []
            while sum("WATCHDOG" in fields for fields in received) < 3:
                try:
                    fields, pid = _receive(sock, deadline)
                except TimeoutError:
                    pytest.fail(f"notifications so far: {received}; log: {(tmp_path / 'module.log').read_text()}")
                assert pid == child.pid, "systemd only hears the main PID (NotifyAccess=main): exec, not fork"
                received.append(fields)
            assert received[0].get("READY") == "1" and "time_service" in received[0]["STATUS"]
            assert all(fields.get("WATCHDOG") == "1" for fields in received[1:])
            child.terminate()
            child.wait(timeout=10)
            fields, _pid = _receive(sock, time.monotonic() + 5.0)
            while "STOPPING" not in fields:
                fields, _pid = _receive(sock, time.monotonic() + 5.0)
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
            log.close()
