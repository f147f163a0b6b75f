"""The `rascal` command."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable
from importlib.metadata import version
from pathlib import Path

from brain.rddf_cli import add_rddf_commands
from modules.sim.generate import add_scenario_commands
from protocol.auth import DEFAULT_KEY_FILE, Keyring, write_keyring
from rascal.bustools import make_console
from rascal.logtools import add_log_commands
from rascal.report import add_report_command
from rascal.units import add_deploy_commands

# Commands with their own argument parsers: `rascal WORDS ...` hands the rest to MODULE.main.
DELEGATED_TOOLS: dict[tuple[str, ...], tuple[str, str]] = {
    ("run",): ("rascal.run", "run a deployment's modules here, supervised, until the course is done"),
    ("ins", "accuracy"): ("modules.nav_sensors.accuracy", "replay a scenario through the navigation filters"),
    ("esvs", "eval"): ("modules.esvs.evaluate", "stereo accuracy on a pair with ground truth"),
    ("spoof",): ("rascal.spoof", "hostile datagrams for fault testing (bounded, loopback only)"),
    ("view",): ("rascal.view.cli", "a live bird's-eye view of the bus (or a recording) in the browser"),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["module"]:
        # Everything after the module name belongs to the module's own parser.
        from rascal.launch import module_class, run_module

        if len(argv) < 2:
            print("usage: rascal module NAME [--help | module options]", file=sys.stderr)
            return 2
        run_module(module_class(argv[1]), argv[2:])
        return 0
    for words in (tuple(argv[:2]), tuple(argv[:1])):
        if words in DELEGATED_TOOLS:
            target, _ = DELEGATED_TOOLS[words]
            return int(importlib.import_module(target).main(argv[len(words) :]))
    args = build_parser().parse_args(argv)
    return args.handler(args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rascal", description="RASCAL-style autonomy stack: bus, modules, tools")
    parser.add_argument("--version", action="version", version=f"rascal {version('rascal')}")
    parser.add_argument("--bus", help="bus URL (default: $RASCAL_BUS_URL or loopback multicast)")
    commands = parser.add_subparsers(dest="command", required=True)

    commands.add_parser("module", help="run one module process: rascal module NAME [options]")
    groups: dict[str, argparse._SubParsersAction] = {}
    for words, (_, help_text) in DELEGATED_TOOLS.items():
        if len(words) == 1:
            commands.add_parser(words[0], help=f"{help_text} (rascal {words[0]} --help)")
            continue
        group, tool = words
        if group not in groups:
            groups[group] = commands.add_parser(group, help=f"{group} tools").add_subparsers(dest="tool", required=True)
        groups[group].add_parser(tool, help=f"{help_text} (rascal {group} {tool} --help)")

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
    listing.set_defaults(handler=_bus_list)
    echo = bus.add_parser("echo", help="print messages of a channel as JSON lines")
    echo.add_argument("channel")
    echo.add_argument("--count", type=int, help="stop after this many")
    echo.add_argument("--duration", type=float, default=10.0, help="seconds to listen at most")
    echo.set_defaults(handler=_bus_echo)
    hz = bus.add_parser("hz", help="rate, interval jitter, loss and latency of a channel")
    hz.add_argument("channel")
    hz.add_argument("--window", type=float, default=1.0, help="seconds per report")
    hz.add_argument("--duration", type=float, default=5.0, help="seconds to run")
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

    add_rddf_commands(commands)
    add_scenario_commands(commands)
    add_log_commands(commands)
    add_deploy_commands(commands)
    add_report_command(commands)
    return parser


def _demo(args: argparse.Namespace) -> int:
    from rascal.demo import run_demo

    return run_demo()


def _keygen(args: argparse.Namespace) -> int:
    try:
        write_keyring(args.path, Keyring.generate(), overwrite=args.force)
    except FileExistsError:
        print(f"{args.path} exists; use --force to replace it", file=sys.stderr)
        return 1
    print(f"wrote {args.path}")
    return 0


def _one_line_errors(args: argparse.Namespace, tool: Callable[[], object]) -> int:
    """Run a bus or time tool: exit 0, or for bad input (bus URL, key file, channel, JSON) one
    line and exit 2."""
    try:
        tool()
        return 0
    except (ValueError, OSError) as exc:  # UrlError and KeyFileError are ValueErrors
        print(f"rascal {args.command} {args.tool}: {exc}", file=sys.stderr)
        return 2


def _bus_list(args: argparse.Namespace) -> int:
    from rascal.bustools import bus_list

    return _one_line_errors(args, lambda: bus_list(args.bus, args.duration, make_console()))


def _bus_echo(args: argparse.Namespace) -> int:
    from rascal.bustools import bus_echo

    return _one_line_errors(args, lambda: bus_echo(args.bus, args.channel, args.duration, args.count, make_console()))


def _bus_hz(args: argparse.Namespace) -> int:
    from rascal.bustools import bus_hz

    return _one_line_errors(args, lambda: bus_hz(args.bus, args.channel, args.duration, args.window, make_console()))


def _bus_pub(args: argparse.Namespace) -> int:
    from rascal.bustools import bus_pub

    def publish() -> None:
        sent = bus_pub(args.bus, args.channel, args.json, args.type, args.rate, args.count)
        print(f"published {sent} on {args.channel}")

    return _one_line_errors(args, publish)


def _operator_order(args: argparse.Namespace) -> int:
    from protocol.messages import StopMode
    from rascal.operator_stop import describe, give_order

    mode = {"stop": StopMode.ESTOP, "pause": StopMode.PAUSE, "resume": StopMode.RUN}[args.command]
    from rascal.deployment import DeploymentError, load_deployment

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


def _time_status(args: argparse.Namespace) -> int:
    from rascal.bustools import time_status

    return _one_line_errors(args, lambda: time_status(args.bus, args.duration, make_console()))


if __name__ == "__main__":
    sys.exit(main())
