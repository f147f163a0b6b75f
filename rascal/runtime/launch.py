"""Command line of every module: ``python -m modules.NAME`` and ``rascal module NAME``."""

from __future__ import annotations

import argparse
import importlib
import sys
import tomllib
from pathlib import Path
from typing import Any

from protocol.auth import KeyFileError, default_keyring, load_keyring
from protocol.transport import UrlError
from rascal.runtime.bus import Bus
from rascal.runtime.config import ConfigError, build_config, describe, merge_values, parse_assignments
from rascal.runtime.module import Module, Runtime, make_clock
from rascal.runtime.ports import interface_table


def module_class(name: str) -> type[Module]:
    """The Module subclass of ``modules.<name>`` (each package exports it as ``MODULE``)."""
    try:
        package = importlib.import_module(f"modules.{name}")
    except ModuleNotFoundError:
        raise SystemExit(f"no module named {name!r} under modules/") from None
    if not hasattr(package, "MODULE"):
        raise SystemExit(f"modules.{name} is a library, not a runnable module")
    module: type[Module] = package.MODULE
    return module


def argument_parser(cls: type[Module]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=f"rascal module {cls.name}", description=(cls.__doc__ or "").strip())
    parser.add_argument("--bus", help="bus URL (default: $RASCAL_BUS_URL or loopback multicast)")
    parser.add_argument("--source-id", type=int, default=cls.default_source_id, help="this process's source id")
    parser.add_argument("--key-file", type=Path, help="deployment key file (default: $RASCAL_KEY_FILE or per-user)")
    parser.add_argument("--unsigned", action="store_true", help="send and accept unsigned messages (explicit opt-out)")
    parser.add_argument("--config", type=Path, help=f"TOML file; keys at top level or in a [{cls.name}] table")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override one config key")
    parser.add_argument("--print-config", action="store_true", help="print the effective configuration and exit")
    parser.add_argument("--interface", action="store_true", help="print what it reads and writes (its README table)")
    parser.add_argument("--duration", type=float, help="exit after this many seconds")
    parser.add_argument("--restarts", type=int, default=0, help="restart count, reported in heartbeats")
    parser.add_argument("--clock-offset-ms", type=float, default=0.0, help="fault injection: skew the local clock")
    parser.add_argument("--clock-drift-ppm", type=float, default=0.0, help="fault injection: local clock drift")
    return parser


def load_module_config(cls: type[Module], config_file: Path | None, assignments: list[str]) -> Any:
    values: dict[str, Any] = {}
    where = "config"
    if config_file is not None:
        try:
            doc = tomllib.loads(config_file.read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"{config_file}: {exc}") from exc
        values = doc.get(cls.name, doc)
        where = f"{config_file}" + (f" [{cls.name}]" if cls.name in doc else "")
    values = merge_values(values, parse_assignments(cls.Config, assignments))
    return build_config(cls.Config, values, where)


def run_module(cls: type[Module], argv: list[str] | None = None) -> None:
    args = argument_parser(cls).parse_args(argv)
    if args.interface:
        print(interface_table(cls.interface))
        return
    try:
        config = load_module_config(cls, args.config, args.set)
        if args.print_config:
            print(describe(cls.Config, config))
            return
        keyring = None if args.unsigned else (load_keyring(args.key_file) if args.key_file else default_keyring())
        time_master = getattr(cls, "time_master", False)
        clock = make_clock(time_master, args.clock_offset_ms, args.clock_drift_ppm)
        bus = Bus.open(args.bus, source_id=args.source_id, clock=clock, keyring=keyring, signing=not args.unsigned)
    except (ConfigError, KeyFileError, UrlError) as exc:
        print(f"{cls.name}: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    runtime = Runtime(bus, clock, time_master=time_master, restarts=args.restarts)
    runtime.run(cls(config, runtime), args.duration)
