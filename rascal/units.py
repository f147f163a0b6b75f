"""``rascal deploy units DEPLOY -o DIR`` and ``rascal deploy exec DEPLOY LABEL``: a deployment
run by systemd instead of ``rascal run``.

For each host of the deployment, ``DIR/HOST/`` gets what that machine installs
(deploy/systemd/README.md says how):

* ``rascal@.service``: the template every module runs as (``Type=notify``, ``WatchdogSec``,
  ``Restart=on-failure``), from ``deploy/systemd/rascal@.service.in``;
* ``rascal@LABEL.service.d/deployment.conf`` per module on the host: its watchdog timeout (the
  deployment's ``heartbeat_timeout_s``, as ``rascal run`` uses it) and nice level;
* ``rascal-HOST.target``, wanting ``rascal@LABEL.service`` for each module on the host;
* ``rascal.env``, the environment file of the units: the deployment file, bus URL and key file.

The units name no module settings: ``rascal deploy exec`` reads them from the deployment file
when the unit starts and replaces itself with the module process (same PID, so the module's own
READY=1 and WATCHDOG=1 reach systemd from the main process).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import sys
from pathlib import Path
from typing import Any

from rascal.deployment import Deployment, DeploymentError, load_deployment
from rascal.sdnotify import NOTIFY_SOCKET_ENV
from rascal.supervisor import module_command, module_environment

ROOT = Path(__file__).resolve().parents[1]
TEMPLATES = ROOT / "deploy" / "systemd"
DEFAULT_ENV_FILE = Path("/etc/rascal/rascal.env")
DEFAULT_KEY_FILE = Path("/etc/rascal/bus.key")
_FIELD = re.compile(r"@([A-Z_]+)@")
_UNIT_NAME = re.compile(r"[A-Za-z0-9_.:-]+")  # what systemd allows in a unit (instance) name
_ENV_VALUE = re.compile(r"[^\n\"\\$`]*")  # what an EnvironmentFile value may hold in double quotes


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
) -> dict[str, list[Path]]:
    """Write every host's units under ``out_dir/HOST/``; returns the files written per host."""
    for path, what in ((rascal, "--rascal"), (env_file, "--env-file")):
        if not path.is_absolute():
            raise ValueError(f"{what} {path}: systemd needs an absolute path")
    key = deployment.key_file or key_file or DEFAULT_KEY_FILE
    written: dict[str, list[Path]] = {}
    for host in deployment.hosts:
        specs = deployment.on_host(host)
        if not specs:
            continue
        env = {
            "RASCAL_DEPLOYMENT": str(deployment.path.resolve()),
            "RASCAL_BUS_URL": deployment.bus_on(host),  # what this host's modules use (its own interface)
            "RASCAL_KEY_FILE": str(key),
        }
        for name, value in env.items():
            if _ENV_VALUE.fullmatch(value) is None:
                raise ValueError(f"{name}={value!r}: quotes, backslashes, $ and backquotes cannot go in rascal.env")
        for name, what in ((host, "host"), *((spec.label, "module label") for spec in specs)):
            if _UNIT_NAME.fullmatch(name) is None:
                raise ValueError(f"{deployment.path}: {what} {name!r} cannot name a systemd unit (A-Z a-z 0-9 _ . : -)")
        fields = {
            "DEPLOYMENT": deployment.name,
            "HOST": host,
            "ROOT": str(ROOT),
            "RASCAL": str(rascal),
            "ENV_FILE": str(env_file),
            "INSTANCES": " ".join(f"rascal@{spec.label}.service" for spec in specs),
        }
        host_dir = out_dir / host
        if host_dir.exists():
            shutil.rmtree(host_dir)  # a module gone from the deployment must not keep its drop-in
        host_dir.mkdir(parents=True)
        files = [
            _write(host_dir / "rascal@.service", _fill(TEMPLATES / "rascal@.service.in", fields)),
            _write(host_dir / f"rascal-{host}.target", _fill(TEMPLATES / "rascal-HOST.target.in", fields)),
            _write(
                host_dir / "rascal.env",
                f"# Environment of the rascal units on host {host} (install as {env_file}).\n"
                + "".join(f'{name}="{value}"\n' for name, value in env.items()),
            ),
        ]
        for spec in specs:
            files.append(
                _write(
                    host_dir / f"rascal@{spec.label}.service.d" / "deployment.conf",
                    f"# From {deployment.path.name}: [modules.{spec.label}]\n"
                    f"[Unit]\nDescription=rascal {spec.label} (modules.{spec.module}, source {spec.source_id}, "
                    f"host {host})\n\n"
                    f"[Service]\nWatchdogSec={round(spec.heartbeat_timeout_s * 1000)}ms\nNice={spec.nice}\n",
                )
            )
        written[host] = files
    return written


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


def _fill(template: Path, fields: dict[str, str]) -> str:
    text = template.read_text(encoding="utf-8")
    missing = sorted(set(_FIELD.findall(text)) - set(fields))
    if missing:
        raise ValueError(f"{template}: no value for {missing}")
    return _FIELD.sub(lambda match: fields[match.group(1)], text)


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def _units(args: argparse.Namespace) -> int:
    beside = Path(sys.executable).with_name("rascal")  # this environment's (the venv's) command
    rascal = args.rascal or (beside if beside.exists() else Path(shutil.which("rascal") or "rascal"))
    try:
        deployment = load_deployment(args.deployment)
        written = write_units(deployment, args.output, rascal.absolute(), args.env_file, args.key_file)
    except (DeploymentError, ValueError, OSError) as exc:
        print(f"rascal deploy units: {exc}", file=sys.stderr)
        return 2
    for host, files in written.items():
        print(f"{host}: {len(files) - 3} modules -> {args.output / host}/ (rascal-{host}.target)")
    return 0


def _exec(args: argparse.Namespace) -> int:
    try:
        exec_module(load_deployment(args.deployment), args.label)
    except (DeploymentError, OSError) as exc:
        print(f"rascal deploy exec: {exc}", file=sys.stderr)
        return 2
    return 0  # not reached: the process is the module now
