"""``rascal deploy units DEPLOY -o DIR`` and ``rascal deploy exec DEPLOY LABEL``: a deployment
run by systemd instead of ``rascal run``.

For each host of the deployment, ``DIR/HOST/`` gets what that machine installs
(deploy/systemd/README.md says how):

* ``rascal@.service``: the template every module runs as (``Type=notify``, ``WatchdogSec``,
  ``Restart=on-failure``), from ``deploy/systemd/rascal@.service.in``;
* ``rascal@.service.d/sandbox.conf``: every module runs as ``User=`` (``--user``, default
  ``rascal``, who must own the key file) in a read-only, sandboxed system;
* ``rascal@LABEL.service.d/deployment.conf`` per module on the host: its watchdog timeout (the
  deployment's ``heartbeat_timeout_s``, as ``rascal run`` uses it), nice level and real-time limit;
* ``rascal-HOST.target``, wanting ``rascal@LABEL.service`` for each module on the host;
* ``rascal.env``, the environment file of the units: the deployment file, bus URL and key file.

A deployment file is not trusted: every host, label and name that becomes a path or unit text is
checked before anything is written, and nothing outside ``DIR`` is written, removed or followed.

The units name no module settings: ``rascal deploy exec`` reads them from the deployment file
when the unit starts and replaces itself with the module process (same PID, so the module's own
READY=1 and WATCHDOG=1 reach systemd from the main process).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import re
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from rascal.runtime.config import build_config, parse_assignments
from rascal.runtime.deployment import (
    SAFE_NAME,
    SAFE_NAME_RULE,
    Deployment,
    DeploymentError,
    ModuleSpec,
    load_deployment,
)
from rascal.runtime.launch import module_class
from rascal.runtime.sdnotify import NOTIFY_SOCKET_ENV
from rascal.supervisor import module_command, module_environment

ROOT = Path(__file__).resolve().parents[1]
TEMPLATES = ROOT / "deploy" / "systemd"
DEFAULT_ENV_FILE = Path("/etc/rascal/rascal.env")
DEFAULT_KEY_FILE = Path("/etc/rascal/bus.key")
DEFAULT_USER = "rascal"
DROP_IN = "deployment.conf"
_FIELD = re.compile(r"@([A-Z_]+)@")
_USER = re.compile(r"[A-Za-z_][A-Za-z0-9_-]{0,31}")
# Paths written into unit files: nothing systemd reads as a specifier (%), quote, escape,
# separator or line continuation.
_UNIT_PATH = re.compile(r"/[A-Za-z0-9_./+,@~-]*")
_ENV_VALUE = re.compile(r"[^\x00-\x1f\x7f\"\\$`]*")  # what an EnvironmentFile value may hold in double quotes
_STALE_DROP_IN = re.compile(r"rascal@(.+)\.service\.d")
_DIRECTORY = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW
# The modules need IPv4/6 (the bus), AF_UNIX (sd_notify, the ESVS fork server) and AF_NETLINK
# (interface addresses). No PrivateDevices=/PrivateIPC=: the camera's frame ring in /dev/shm is
# shared with the ESVS service. Modules log to the journal; the one file any writes is control's
# stop order, kept across restarts in the state directory (/var/lib/rascal, $STATE_DIRECTORY).
_SANDBOX = """\
StateDirectory=rascal
StateDirectoryMode=0700
NoNewPrivileges=yes
CapabilityBoundingSet=
ProtectSystem=strict
ProtectHome=read-only
PrivateTmp=yes
ProtectKernelTunables=yes
ProtectKernelModules=yes
ProtectKernelLogs=yes
ProtectControlGroups=yes
ProtectHostname=yes
RestrictAddressFamilies=AF_INET AF_INET6 AF_UNIX AF_NETLINK
RestrictNamespaces=yes
RestrictSUIDSGID=yes
LockPersonality=yes
SystemCallArchitectures=native
"""


def add_deploy_commands(commands: Any) -> None:
    """Register ``deploy units`` and ``deploy exec`` on the `rascal` command's subparsers."""
    deploy = commands.add_parser("deploy", help="run a deployment under systemd: unit files, module start")
    tools = deploy.add_subparsers(dest="tool", required=True)
    units = tools.add_parser("units", help="write each host's systemd units (rascal@.service, rascal-HOST.target)")
    units.add_argument("deployment", type=Path, help="deployment TOML")
    units.add_argument("-o", "--output", type=Path, required=True, help="directory to write DIR/HOST/... into")
    units.add_argument("--rascal", type=Path, help="the rascal command the units run (default: this one)")
    units.add_argument(
        "--env-file", type=Path, default=DEFAULT_ENV_FILE, help="where each host installs rascal.env (%(default)s)"
    )
    units.add_argument(
        "--key-file",
        type=Path,
        help=f"key file on the hosts, when the deployment names none (default: {DEFAULT_KEY_FILE})",
    )
    units.add_argument("--user", default=DEFAULT_USER, help="the system user the modules run as (%(default)s)")
    units.set_defaults(handler=_units)
    run = tools.add_parser("exec", help="become one module process of a deployment (what rascal@LABEL runs)")
    run.add_argument("deployment", type=Path, help="deployment TOML")
    run.add_argument("label", help="the module's label ([modules.LABEL])")
    run.set_defaults(handler=_exec)


def write_units(
    deployment: Deployment,
    out_dir: Path,
    rascal: Path,
    env_file: Path = DEFAULT_ENV_FILE,
    key_file: Path | None = None,
    user: str = DEFAULT_USER,
) -> dict[str, list[Path]]:
    """Write every host's units under ``out_dir/HOST/``; returns the files written per host.
    Everything is checked before anything is written: a refused deployment leaves ``out_dir`` as it was."""
    _check_names(deployment)
    if _USER.fullmatch(user) is None:
        raise ValueError(f"--user {user!r}: expected a user name (letter or _, then up to 31 of A-Z a-z 0-9 _ -)")
    if deployment.key_file is not None:
        key = _unit_path(deployment.key_file, f"{deployment.path}: deployment.key_file", DeploymentError)
    else:
        key = _unit_path(key_file or DEFAULT_KEY_FILE, "--key-file")
    fields = {
        "DEPLOYMENT": deployment.name,
        "ROOT": _unit_path(ROOT, "the checkout"),
        "RASCAL": _unit_path(rascal, "--rascal"),
        "ENV_FILE": _unit_path(env_file, "--env-file"),
    }
    sandbox = _sandbox(user)
    hosts = {host: _host_files(deployment, host, fields, key, sandbox) for host in deployment.hosts}
    out_dir.mkdir(parents=True, exist_ok=True)
    top = os.open(out_dir, os.O_RDONLY | os.O_DIRECTORY)  # -o itself is the caller's choice, link or not
    try:
        return {host: _write_host(top, out_dir / host, files) for host, files in hosts.items() if files}
    finally:
        os.close(top)


def exec_module(deployment: Deployment, label: str) -> None:
    """Replace this process with module ``label`` of ``deployment`` (its settings, bus and key)."""
    try:
        spec = deployment.spec(label)
    except KeyError:
        labels = sorted(spec.label for spec in deployment.modules)
        raise DeploymentError(f"{deployment.path}: no module {label!r}; modules: {labels}") from None
    command = module_command(deployment, spec)
    env = module_environment(deployment, dict(os.environ))
    if NOTIFY_SOCKET_ENV in os.environ:  # the module becomes systemd's main process: it notifies
        env[NOTIFY_SOCKET_ENV] = os.environ[NOTIFY_SOCKET_ENV]
    sys.stdout.flush()
    os.chdir(ROOT)  # modules run from the repository root, as under rascal run
    os.execve(command[0], command, env)


# -- what is written ---------------------------------------------------------------------------


def _host_files(deployment: Deployment, host: str, fields: dict[str, str], key: str, sandbox: str) -> dict[str, str]:
    """Name (relative to ``DIR/HOST/``) -> text of every file of ``host``; none without modules."""
    specs = deployment.on_host(host)
    if not specs:
        return {}
    fields = {**fields, "HOST": host, "INSTANCES": " ".join(f"rascal@{spec.label}.service" for spec in specs)}
    files = {
        "rascal@.service": _fill(TEMPLATES / "rascal@.service.in", fields),
        "rascal@.service.d/sandbox.conf": sandbox,
        f"rascal-{host}.target": _fill(TEMPLATES / "rascal-HOST.target.in", fields),
        "rascal.env": _environment_file(deployment, host, key, fields["ENV_FILE"]),
    }
    return files | {f"rascal@{spec.label}.service.d/{DROP_IN}": _drop_in(deployment, spec) for spec in specs}


def _sandbox(user: str) -> str:
    return (
        "# Written by `rascal deploy units`: every module runs unprivileged, in a sandbox.\n"
        f"# The key file must be {user}'s own, mode 600 (protocol/auth.py refuses any other).\n"
        f"[Service]\nUser={user}\n{_SANDBOX}"
    )


def _environment_file(deployment: Deployment, host: str, key: str, env_file: str) -> str:
    env = {  # name -> (value, where it comes from)
        "RASCAL_DEPLOYMENT": (str(deployment.path.resolve()), "the deployment file's path"),
        "RASCAL_BUS_URL": (deployment.bus_on(host), "deployment.bus"),  # this host's (its own interface)
        "RASCAL_KEY_FILE": (key, "the key file"),
    }
    for name, (value, where) in env.items():
        if _ENV_VALUE.fullmatch(value) is None:
            raise DeploymentError(
                f"{deployment.path}: {where}: {value!r} cannot go in rascal.env as {name}"
                " (no control characters, quotes, backslashes, $ or backquotes)"
            )
    return f"# Environment of the rascal units on host {host} (install as {env_file}).\n" + "".join(
        f'{name}="{value}"\n' for name, (value, _where) in env.items()
    )


def _drop_in(deployment: Deployment, spec: ModuleSpec) -> str:
    return (
        f"# From deployment {deployment.name}: [modules.{spec.label}]\n"
        f"[Unit]\nDescription=rascal {spec.label} (modules.{spec.module}, source {spec.source_id}, "
        f"host {spec.host})\n\n"
        f"[Service]\nWatchdogSec={round(spec.heartbeat_timeout_s * 1000)}ms\nNice={spec.nice}\n{_realtime(spec)}"
    )


def _realtime(spec: ModuleSpec) -> str:
    """A module that asks for SCHED_FIFO (the ESVS, ``sched = "fifo"``) may use up to its highest
    ``*_priority`` through RLIMIT_RTPRIO, without a capability; the others get none."""
    config_class = module_class(spec.module).Config
    names = [f.name for f in dataclasses.fields(config_class)]  # type: ignore[arg-type]
    if "sched" not in names:
        return "RestrictRealtime=yes\n"
    assignments = [f"{key}={value}" for key, value in spec.settings.items()]
    config: Any = build_config(config_class, parse_assignments(config_class, assignments))
    if config.sched != "fifo":
        return "RestrictRealtime=yes\n"
    return f"LimitRTPRIO={max(getattr(config, name) for name in names if name.endswith('_priority'))}\n"


def _fill(template: Path, fields: dict[str, str]) -> str:
    text = template.read_text(encoding="utf-8")
    missing = sorted(set(_FIELD.findall(text)) - set(fields))
    if missing:
        raise ValueError(f"{template}: no value for {missing}")
    return _FIELD.sub(lambda match: fields[match.group(1)], text)


# -- checks ------------------------------------------------------------------------------------


def _check_names(deployment: Deployment) -> None:
    """Refuse, naming the file, field and value, any name that would leave the output directory
    or put more than a name into a unit."""
    _check_name(deployment, "deployment.name", deployment.name)
    for host in deployment.hosts:
        _check_name(deployment, "hosts", host)
    for spec in deployment.modules:
        _check_name(deployment, "modules", spec.label)
        _check_name(deployment, f"modules.{spec.label}.module", spec.module)


def _check_name(deployment: Deployment, where: str, value: str) -> None:
    if SAFE_NAME.fullmatch(value) is None:
        problem = f"{value!r} cannot name a unit or directory ({SAFE_NAME_RULE})"
        raise DeploymentError(f"{deployment.path}: {where}: {problem}")


def _unit_path(path: Path, what: str, error: type[ValueError] = ValueError) -> str:
    text = str(path)
    if _UNIT_PATH.fullmatch(text) is None:
        raise error(f"{what} {text!r}: systemd needs an absolute path, here of A-Z a-z 0-9 _ . / + , @ ~ - only")
    return text


# -- writing inside DIR only -------------------------------------------------------------------
# Through directory descriptors opened with O_NOFOLLOW: whatever DIR holds (symbolic links
# included), nothing outside it is written, removed or followed.


def _write_host(top: int, host_dir: Path, files: dict[str, str]) -> list[Path]:
    with _directory(top, host_dir.name, host_dir) as host_fd:
        _remove_stale_drop_ins(host_fd, {name.split("/")[0] for name in files})
        for name, text in files.items():
            folder, _, base = name.rpartition("/")
            if not folder:
                _replace(host_fd, base, text)
                continue
            with _directory(host_fd, folder, host_dir / folder) as folder_fd:
                _replace(folder_fd, base, text)
    return [host_dir / name for name in files]


@contextlib.contextmanager
def _directory(parent: int, name: str, shown: Path) -> Iterator[int]:
    """Directory ``name`` of ``parent``, made if missing; a symbolic link or a file is refused."""
    with contextlib.suppress(FileExistsError):
        os.mkdir(name, 0o755, dir_fd=parent)
    try:
        fd = os.open(name, _DIRECTORY, dir_fd=parent)
    except OSError as exc:
        raise OSError(f"{shown}: not a plain directory ({exc.strerror}); nothing is written through it") from None
    try:
        yield fd
    finally:
        os.close(fd)


def _replace(directory: int, name: str, text: str) -> None:
    """(Re)write ``name``: the old entry, a symbolic link included, is unlinked, never followed."""
    with contextlib.suppress(FileNotFoundError):
        os.unlink(name, dir_fd=directory)
    fd = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644, dir_fd=directory)  # O_EXCL: no link followed
    with os.fdopen(fd, "w", encoding="utf-8") as out:
        out.write(text)


def _remove_stale_drop_ins(host_fd: int, keep: set[str]) -> None:
    """A module gone from the host must not keep its drop-in: remove the deployment.conf this
    command wrote for it, and its directory if that empties it; nothing else."""
    with os.scandir(host_fd) as entries:
        stale = [
            entry.name
            for entry in entries
            if _STALE_DROP_IN.fullmatch(entry.name) and entry.name not in keep and entry.is_dir(follow_symlinks=False)
        ]
    for name in stale:
        with _directory(host_fd, name, Path(name)) as drop_in, contextlib.suppress(FileNotFoundError):
            os.unlink(DROP_IN, dir_fd=drop_in)
        with contextlib.suppress(OSError):  # not empty: the rest is not ours
            os.rmdir(name, dir_fd=host_fd)


# -- commands ----------------------------------------------------------------------------------


def _units(args: argparse.Namespace) -> int:
    beside = Path(sys.executable).with_name("rascal")  # this environment's (the venv's) command
    rascal = args.rascal or (beside if beside.exists() else Path(shutil.which("rascal") or "rascal"))
    try:
        deployment = load_deployment(args.deployment)
        written = write_units(deployment, args.output, rascal.absolute(), args.env_file, args.key_file, args.user)
    except (DeploymentError, ValueError, OSError) as exc:
        print(f"rascal deploy units: {exc}", file=sys.stderr)
        return 2
    for host in written:
        modules = len(deployment.on_host(host))
        print(f"{host}: {modules} modules -> {args.output / host}/ (rascal-{host}.target)")
    return 0


def _exec(args: argparse.Namespace) -> int:
    try:
        exec_module(load_deployment(args.deployment), args.label)
    except (DeploymentError, OSError) as exc:
        print(f"rascal deploy exec: {exc}", file=sys.stderr)
        return 2
    return 0  # not reached: the process is the module now
