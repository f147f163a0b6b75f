"""systemd units: `rascal deploy units` output passes `systemd-analyze verify` with nothing on
stderr and runs every module unprivileged in a sandbox; a hostile deployment file is refused in
one line and nothing outside `-o` is touched; and a real module started the way a unit starts it
(`rascal deploy exec`) tells the service manager READY=1, then WATCHDOG=1 with every heartbeat,
from the PID systemd started."""

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

from rascal.cli import main
from rascal.runtime.deployment import DeploymentError, load_deployment
from rascal.runtime.sdnotify import Notifier
from rascal.units import write_units
from tests.conftest import ROOT

SYSTEMD_ANALYZE = shutil.which("systemd-analyze") or "/usr/bin/systemd-analyze"
RASCAL = Path(sys.executable).with_name("rascal")
THREE_HOSTS = ROOT / "deploy" / "vehicle-3hosts.toml"
SANDBOX = (
    "User=rascal",
    "NoNewPrivileges=yes",
    "CapabilityBoundingSet=\n",
    "ProtectSystem=strict",
    "ProtectHome=read-only",
    "PrivateTmp=yes",
    "ProtectKernelTunables=yes",
    "ProtectKernelModules=yes",
    "ProtectControlGroups=yes",
    "RestrictAddressFamilies=AF_INET AF_INET6 AF_UNIX AF_NETLINK",
    "LockPersonality=yes",
)
ONE_HOST = '[deployment]\nbus = "udpm://239.255.1.2:7700?ttl=0"\n'


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
        assert len(files) == 4 + len(labels)
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


def test_modules_run_unprivileged_in_a_sandbox(tmp_path: Path) -> None:
    write_units(load_deployment(THREE_HOSTS), tmp_path, RASCAL)
    sandbox = (tmp_path / "sensors" / "rascal@.service.d" / "sandbox.conf").read_text()
    assert sandbox.startswith("# ") and "\n[Service]\n" in sandbox
    for line in SANDBOX:
        assert line in sandbox
    drop_ins = tmp_path / "sensors"
    # The ESVS asks for SCHED_FIFO (up to its round's priority 50): a limit, not a capability.
    assert "LimitRTPRIO=50\n" in (drop_ins / "rascal@esvs.service.d" / "deployment.conf").read_text()
    assert "RestrictRealtime=yes\n" in (drop_ins / "rascal@lidar_sweep.service.d" / "deployment.conf").read_text()
    write_units(load_deployment(THREE_HOSTS), tmp_path, RASCAL, user="robot")
    assert "\nUser=robot\n" in (tmp_path / "drive" / "rascal@.service.d" / "sandbox.conf").read_text()
    with pytest.raises(ValueError, match="--user 'robot\\\\nUser=root'"):
        write_units(load_deployment(THREE_HOSTS), tmp_path, RASCAL, user="robot\nUser=root")


def _tree(top: Path) -> dict[str, bytes | str]:
    """Every entry under ``top``: a file's bytes, a link's target, "dir" for a directory."""
    entries: dict[str, bytes | str] = {}
    for path in sorted(top.rglob("*")):
        name = str(path.relative_to(top))
        entries[name] = os.readlink(path) if path.is_symlink() else "dir" if path.is_dir() else path.read_bytes()
    return entries


@pytest.mark.parametrize(
    ("text", "refusal"),
    [
        (ONE_HOST + '[hosts.".."]\n[modules.time_service]\nhost = ".."\n', "hosts: '..'"),
        (ONE_HOST + '[hosts."../x"]\n[modules.time_service]\nhost = "../x"\n', "hosts: '../x'"),
        (ONE_HOST + '[hosts."/tmp/x"]\n[modules.time_service]\nhost = "/tmp/x"\n', "hosts: '/tmp/x'"),
        (ONE_HOST + 'name = "x\\n[Service]\\nUser=root"\n[modules.time_service]\n', "deployment.name: 'x\\n[Service]"),
        (
            ONE_HOST + '[modules."time_service\\nExecStartPre=/bin/sh"]\nmodule = "time_service"\n',
            "modules: 'time_service\\nExecStartPre=/bin/sh'",
        ),
        (
            '[deployment]\nbus = "mem://x\\nRASCAL_KEY_FILE=/tmp/k"\n[modules.time_service]\n',
            "deployment.bus: 'mem://x\\nRASCAL_KEY_FILE=/tmp/k' cannot go in rascal.env",
        ),
    ],
    ids=["dotdot-host", "slash-host", "absolute-host", "newline-name", "newline-label", "newline-bus"],
)
def test_a_hostile_deployment_is_refused_in_one_line_and_nothing_is_touched(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, refusal: str
) -> None:
    parent = tmp_path / "parent"
    out = parent / "units"
    (out / "x").mkdir(parents=True)
    (parent / "keep.txt").write_text("not rascal's")
    (out / "x" / "keep.txt").write_text("not rascal's either")
    before = _tree(parent)
    hostile = tmp_path / "hostile.toml"
    hostile.write_text(text)
    assert main(["deploy", "units", str(hostile), "-o", str(out), "--rascal", str(RASCAL)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"rascal deploy units: {hostile}: {refusal}"), err
    assert _tree(parent) == before


def test_only_files_it_wrote_are_replaced_or_removed_and_no_link_is_followed(tmp_path: Path) -> None:
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "rascal.env").write_text("outside")
    out = tmp_path / "units"
    gone, kept = out / "drive" / "rascal@gone.service.d", out / "drive" / "rascal@mixed.service.d"
    for drop_in in (gone, kept):
        drop_in.mkdir(parents=True)
        (drop_in / "deployment.conf").write_text("stale")
    (kept / "override.conf").write_text("the admin's")
    (out / "drive" / "notes.txt").write_text("the admin's")
    (out / "drive" / "rascal.env").symlink_to(outside / "rascal.env")
    (out / "sensors").symlink_to(outside, target_is_directory=True)
    with pytest.raises(OSError, match="sensors: not a plain directory"):
        write_units(load_deployment(THREE_HOSTS), out, RASCAL)
    (out / "sensors").unlink()
    (out / "drive" / "rascal@control.service.d").symlink_to(outside, target_is_directory=True)
    with pytest.raises(OSError, match=r"rascal@control\.service\.d: not a plain directory"):
        write_units(load_deployment(THREE_HOSTS), out, RASCAL)
    assert _tree(outside) == {"rascal.env": b"outside"}
    (out / "drive" / "rascal@control.service.d").unlink()
    write_units(load_deployment(THREE_HOSTS), out, RASCAL)
    assert _tree(outside) == {"rascal.env": b"outside"}
    assert not gone.exists() and _tree(kept) == {"override.conf": b"the admin's"}
    assert (out / "drive" / "notes.txt").read_text() == "the admin's"
    assert (
        not (out / "drive" / "rascal.env").is_symlink()
        and "RASCAL_BUS_URL" in (out / "drive" / "rascal.env").read_text()
    )


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
    with pytest.raises(DeploymentError, match="modules: 'time service' cannot be a module label"):
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
