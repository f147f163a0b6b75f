"""The `rascal` command."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from importlib.metadata import version
from pathlib import Path
from typing import Any, NamedTuple

from modules.sim.generate import add_scenario_commands
from protocol.auth import DEFAULT_KEY_FILE, Keyring, write_keyring
from rascal.bustools import make_console, reporting_errors
from rascal.logtools import add_log_commands
from rascal.rddf_cli import add_rddf_commands
from rascal.report import add_report_command
from rascal.units import add_deploy_commands


class Delegated(NamedTuple):
    target: str  # its module, whose main(argv) parses the rest
    help: str
    takes_bus: bool  # whether a --bus can mean anything to it


# Commands with their own argument parsers: `rascal WORDS ...` hands the rest to MODULE.main.
DELEGATED_TOOLS: dict[tuple[str, ...], Delegated] = {
    ("run",): Delegated("rascal.run", "run a deployment's modules here, supervised, until the course is done", False),
    ("ins", "accuracy"): Delegated(
        "modules.sim.nav.accuracy", "replay a scenario through the navigation filters", False
    ),
    ("esvs", "eval"): Delegated("modules.esvs.evaluate", "stereo accuracy on a pair with ground truth", False),
    ("spoof",): Delegated("rascal.spoof", "hostile datagrams for fault testing (bounded, loopback only)", True),
    ("view",): Delegated("rascal.view.cli", "a live bird's-eye view of the bus (or a recording) in the browser", True),
}
# The global options reach every tool and module as the environment they take their defaults from.
GLOBAL_ENVIRONMENT = {"bus": "RASCAL_BUS_URL", "global_key_file": "RASCAL_KEY_FILE"}
# Module processes that live outside modules/.
RASCAL_MODULES = {"recorder": "rascal.recording"}


class RascalParser(argparse.ArgumentParser):
    """Every parser of the `rascal` command, so every subcommand at every level, takes the global
    options: before the verb or after it. A subcommand's own option of the same name wins
    (``deploy units --key-file`` is the key file on the hosts)."""

    def __init__(self, *args: Any, top: bool = False, **kwargs: Any) -> None:
        kwargs.setdefault("conflict_handler", "resolve")
        super().__init__(*args, **kwargs)
        # Below the top an absent option must not overwrite the value given before the verb.
        default = None if top else argparse.SUPPRESS
        group = self.add_argument_group("global options")
        group.add_argument(
            "--bus", default=default, metavar="URL", help="bus URL (default: $RASCAL_BUS_URL or loopback multicast)"
        )
        group.add_argument(
            "--key-file",
            "--key",
            dest="global_key_file",
            metavar="PATH",
            type=Path,
            default=default,
            help="deployment key file (default: $RASCAL_KEY_FILE or ~/.config/rascal/bus.key)",
        )


def global_options() -> RascalParser:
    """The global options alone, to take them out of a delegated tool's arguments."""
    return RascalParser(top=True, prog="rascal", add_help=False, allow_abbrev=False)


@contextmanager
def exported(options: argparse.Namespace) -> Iterator[None]:
    """The global options given, as the environment, for the command's time (main() is also
    called in-process, by tests)."""
    given = {
        name: str(getattr(options, dest))
        for dest, name in GLOBAL_ENVIRONMENT.items()
        if getattr(options, dest, None) is not None
    }
    saved = {name: os.environ.get(name) for name in given}
    os.environ.update(given)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    options, rest = global_options().parse_known_args(argv)
    if rest[:1] == ["module"]:
        return _module(rest[1:], options)
    for words in (tuple(rest[:2]), tuple(rest[:1])):
        if words in DELEGATED_TOOLS:
            return _delegate(words, rest[len(words) :], options)
    args = build_parser().parse_args(argv)
    with exported(args):
        try:
            return int(args.handler(args))
        except KeyboardInterrupt:
            return 130


def _module(argv: list[str], options: argparse.Namespace) -> int:
    """Everything after the module name belongs to the module's own parser."""
    from rascal.runtime.launch import module_class, run_module

    if not argv:
        print("usage: rascal module NAME [--help | module options]", file=sys.stderr)
        return 2
    with exported(options):
        if argv[0] in RASCAL_MODULES:
            return int(importlib.import_module(RASCAL_MODULES[argv[0]]).main(argv[1:]))
        run_module(module_class(argv[0]), argv[1:])
    return 0


def _delegate(words: tuple[str, ...], argv: list[str], options: argparse.Namespace) -> int:
    tool = DELEGATED_TOOLS[words]
    if options.bus is not None and not tool.takes_bus:
        reason = "the deployment file names the bus" if words == ("run",) else "it does not use the bus"
        print(f"rascal {' '.join(words)}: --bus does not apply: {reason}", file=sys.stderr)
        return 2
    with exported(options):
        return int(importlib.import_module(tool.target).main(argv))


def build_parser() -> argparse.ArgumentParser:
    parser = RascalParser(prog="rascal", description="RASCAL-style autonomy stack: bus, modules, tools", top=True)
    parser.add_argument("--version", action="version", version=f"rascal {version('rascal')}")
    commands = parser.add_subparsers(dest="command", required=True)

    commands.add_parser("module", help="run one module process: rascal module NAME [options]")
    groups: dict[str, argparse._SubParsersAction] = {}
    for words, tool in DELEGATED_TOOLS.items():
        if len(words) == 1:
            commands.add_parser(words[0], help=f"{tool.help} (rascal {words[0]} --help)")
            continue
        group, name = words
        if group not in groups:
            groups[group] = commands.add_parser(group, help=f"{group} tools").add_subparsers(dest="tool", required=True)
        groups[group].add_parser(name, help=f"{tool.help} (rascal {group} {name} --help)")

    demo = commands.add_parser(
        "demo", help="the whole stack drives the default scenario from start to finish (rascal run, localhost)"
    )
    demo.set_defaults(handler=_demo)

    keygen = commands.add_parser(
        "keygen", help="write a new deployment key file (mode 600): MAC key and signing master"
    )
    keygen.add_argument("path", type=Path, nargs="?", default=DEFAULT_KEY_FILE)
    keygen.add_argument("--force", action="store_true", help="replace an existing file")
    keygen.set_defaults(handler=_keygen)

    bus = commands.add_parser("bus", help="look at and talk to the live bus").add_subparsers(dest="tool", required=True)
    listing = bus.add_parser("list", help="channels on the bus with rate, size, loss, latency")
    listing.add_argument("--duration", type=float, default=3.0, help="seconds to listen")
    listing.add_argument("--json", action="store_true", help="one JSON document instead of the table")
    listing.set_defaults(handler=_bus_list)
    info = bus.add_parser("info", help="a channel's type, port and publishers with their rates")
    info.add_argument("channel")
    info.add_argument("--duration", type=float, default=3.0, help="seconds to listen for publishers")
    info.add_argument("--json", action="store_true", help="one JSON document")
    info.set_defaults(handler=_bus_info)
    echo = bus.add_parser("echo", help="print messages of a channel as JSON lines, until Ctrl-C")
    echo.add_argument("channel")
    echo.add_argument("--count", type=int, help="stop after this many")
    echo.add_argument("--duration", type=float, help="seconds to listen at most (default: until Ctrl-C)")
    echo.set_defaults(handler=_bus_echo)
    hz = bus.add_parser("hz", help="rate, interval jitter, loss and latency of a channel, until Ctrl-C")
    hz.add_argument("channel")
    hz.add_argument("--window", type=float, default=1.0, help="seconds per report")
    hz.add_argument("--duration", type=float, help="seconds to run (default: until Ctrl-C)")
    hz.add_argument("--json", action="store_true", help="each report as a JSON line")
    hz.set_defaults(handler=_bus_hz)
    pub = bus.add_parser("pub", help="publish a message given as JSON (object or array)")
    pub.add_argument("channel")
    pub.add_argument("json")
    pub.add_argument("--type", help="message type name, for channels not declared in protocol.channels")
    pub.add_argument("--rate", type=float, default=10.0, help="messages per second")
    pub.add_argument("--count", type=int, default=1, help="how many to send")
    pub.set_defaults(handler=_bus_pub)
    bridge = bus.add_parser("bridge", help="forward channels over ZeroMQ/TCP (far end: --bus zmq://HOST:PORT)")
    bridge.add_argument("--bind", default="tcp://127.0.0.1:7700", help="ZeroMQ endpoint to publish on")
    bridge.add_argument("--channels", default=".*", help="regular expression of channels to forward")
    bridge.add_argument("--duration", type=float, default=3600.0, help="seconds to run")
    bridge.set_defaults(handler=_bus_bridge)

    for name, help_text in (
        ("stop", "e-stop the vehicle: control brakes and holds until it restarts, then until resume"),
        ("pause", "pause the vehicle: control brakes and holds until resume"),
        ("resume", "let control drive again after a pause (or an e-stop from before it restarted)"),
    ):
        order = commands.add_parser(name, help=f"{help_text}; repeated until control obeys")
        order.add_argument("--reason", default=f"operator {name}", help="recorded with the order")
        order.add_argument("--timeout", type=float, default=5.0, help="seconds to keep ordering before giving up")
        order.add_argument(
            "--deployment",
            type=Path,
            help="the running deployment: trust time-sync replies only from its time service (command authority)",
        )
        order.set_defaults(handler=_operator_order)

    time_ = commands.add_parser("time", help="shared time").add_subparsers(dest="tool", required=True)
    status = time_.add_parser("status", help="this node's sync to the master and every module's clock state")
    status.add_argument("--duration", type=float, default=2.0, help="seconds to synchronise and listen")
    status.set_defaults(handler=_time_status)

    interface = commands.add_parser("interface", help="message types: fields, units, enums, fingerprints")
    types = interface.add_subparsers(dest="tool", required=True)
    types.add_parser("list", help="every message type with its id, fingerprint and channels").set_defaults(
        handler=_interface_list
    )
    show = types.add_parser("show", help="a message type's fields with types, units and enum names")
    show.add_argument("type", help="message type (e.g. ObstacleList) or a channel that carries it")
    show.add_argument("--json", action="store_true", help="one JSON document")
    show.set_defaults(handler=_interface_show)

    add_rddf_commands(commands, _rddf_plot)
    add_scenario_commands(commands)
    add_log_commands(commands)
    add_deploy_commands(commands)
    add_report_command(commands)
    return parser


def _demo(args: argparse.Namespace) -> int:
    from rascal.demo import run_demo

    return run_demo()


def _rddf_plot(args: argparse.Namespace) -> int:
    from rascal.rddf_plot import plot_command  # here: matplotlib takes half a second to import

    return plot_command(args)


def _keygen(args: argparse.Namespace) -> int:
    try:
        write_keyring(args.path, Keyring.generate(), overwrite=args.force)
    except FileExistsError:
        print(f"{args.path} exists; use --force to replace it", file=sys.stderr)
        return 1
    print(f"wrote {args.path}")
    return 0


@reporting_errors
def _bus_list(args: argparse.Namespace) -> int:
    from rascal.bustools import bus_list

    bus_list(args.bus, args.duration, make_console(), args.json)
    return 0


@reporting_errors
def _bus_info(args: argparse.Namespace) -> int:
    from rascal.bustools import bus_info

    bus_info(args.bus, args.channel, args.duration, make_console(), args.json)
    return 0


@reporting_errors
def _bus_echo(args: argparse.Namespace) -> int:
    from rascal.bustools import bus_echo

    bus_echo(args.bus, args.channel, args.duration, args.count, make_console())
    return 0


@reporting_errors
def _bus_hz(args: argparse.Namespace) -> int:
    from rascal.bustools import bus_hz

    bus_hz(args.bus, args.channel, args.duration, args.window, make_console(), args.json)
    return 0


@reporting_errors
def _bus_pub(args: argparse.Namespace) -> int:
    from rascal.bustools import bus_pub

    sent = bus_pub(args.bus, args.channel, args.json, args.type, args.rate, args.count)
    print(f"published {sent} on {args.channel}")
    return 0


def _interface_list(args: argparse.Namespace) -> int:
    from rascal.interface import list_lines, list_rows

    print("\n".join(list_lines(list_rows())))
    return 0


@reporting_errors
def _interface_show(args: argparse.Namespace) -> int:
    from rascal.bustools import json_text
    from rascal.interface import describe, find_type, show_lines

    described = describe(find_type(args.type))
    print(json_text(described) if args.json else "\n".join(show_lines(described)))
    return 0


def _operator_order(args: argparse.Namespace) -> int:
    from protocol.messages import StopMode
    from rascal.operator_stop import describe, give_order

    mode = {"stop": StopMode.ESTOP, "pause": StopMode.PAUSE, "resume": StopMode.RUN}[args.command]
    from rascal.runtime.deployment import DeploymentError, load_deployment

    try:
        authority = load_deployment(args.deployment).authority if args.deployment else None
    except DeploymentError as exc:
        print(f"rascal {args.command}: {exc}", file=sys.stderr)
        return 2
    result = give_order(args.bus, mode, args.reason, args.timeout, authority=authority)
    print(describe(mode, result), file=sys.stdout if result.confirmed else sys.stderr)
    return 0 if result.confirmed else 1


def _bus_bridge(args: argparse.Namespace) -> int:
    from rascal.bridge import Bridge

    bridge = Bridge(args.bus, args.bind, args.channels)
    try:
        bridge.run(args.duration)
    except KeyboardInterrupt:
        pass
    finally:
        bridge.close()
    print(f"forwarded {bridge.forwarded} messages")
    return 0


@reporting_errors
def _time_status(args: argparse.Namespace) -> int:
    from rascal.bustools import time_status

    time_status(args.bus, args.duration, make_console())
    return 0


if __name__ == "__main__":
    sys.exit(main())
