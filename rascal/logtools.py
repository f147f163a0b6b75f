"""`rascal log info | echo | play RUN.mcap`: look at a recording and put it back on the bus.

    rascal log info RUN.mcap [--strict]                  channels, counts, rates, sources, gaps, rejects
    rascal log echo RUN.mcap [--channels REGEX] [--count N]   messages as JSON lines
    rascal log play RUN.mcap [--speed S] [--channels REGEX] [--bus URL] [--exact]
    rascal log record [-o FILE] [--duration S] [CHANNEL ...]   the live bus into MCAP until Ctrl-C

Recordings are made by rascal/recording.py (``rascal run``'s recorder process, or ``log
record`` here with its RecordingWriter); play's design is in rascal/logplay.py.
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import socket
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.table import Table

from protocol.codec import Opened
from protocol.errors import ProtocolError
from rascal.bustools import (
    declared_channel,
    make_console,
    reporting_errors,
    run_for,
    to_jsonable,
    tool_bus,
    type_name,
)
from rascal.logread import (
    END_METADATA,
    RUN_METADATA,
    Datagram,
    RecordingError,
    Scan,
    SequenceChecker,
    SequenceReport,
    decode,
    iter_datagrams,
)

if TYPE_CHECKING:
    from rascal.recording import RecordingWriter


@dataclass
class ChannelSummary:
    type_id: int
    messages: int = 0
    bytes: int = 0
    first_ns: int = 0
    last_ns: int = 0
    sources: set[int] = field(default_factory=set)

    def rate_hz(self) -> float:
        span = (self.last_ns - self.first_ns) / 1e9
        return (self.messages - 1) / span if self.messages > 1 and span > 0 else 0.0


@dataclass
class LogSummary:
    path: Path
    channels: dict[str, ChannelSummary]
    metadata: dict[str, dict[str, str]]
    sequences: SequenceReport
    truncated: bool

    @property
    def messages(self) -> int:
        return sum(channel.messages for channel in self.channels.values())

    @property
    def start_ns(self) -> int:
        return min((channel.first_ns for channel in self.channels.values()), default=0)

    @property
    def end_ns(self) -> int:
        return max((channel.last_ns for channel in self.channels.values()), default=0)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9

    def rejected(self) -> dict[str, int]:
        """Datagrams the recorder's bus rejected, by ``source/reason``."""
        end = self.metadata.get(END_METADATA, {})
        return {key.removeprefix("rejected/"): int(value) for key, value in end.items() if key.startswith("rejected/")}


def summarize(path: str | Path) -> LogSummary:
    """One pass over a recording: per-channel statistics and the sequence check."""
    scan = Scan()
    checker = SequenceChecker()
    channels: dict[str, ChannelSummary] = {}
    for datagram in iter_datagrams(path, scan=scan):
        checker.add(datagram)
        summary = channels.get(datagram.channel)
        if summary is None:
            summary = channels[datagram.channel] = ChannelSummary(datagram.type_id, first_ns=datagram.log_time_ns)
        summary.messages += 1
        summary.bytes += len(datagram.data)
        summary.first_ns = min(summary.first_ns, datagram.log_time_ns)
        summary.last_ns = max(summary.last_ns, datagram.log_time_ns)
        summary.sources.add(datagram.source_id)
    return LogSummary(Path(path), channels, scan.metadata, checker.report(scan), scan.truncated)


def _time_text(t_ns: int) -> str:
    return datetime.fromtimestamp(t_ns / 1e9, UTC).isoformat(timespec="milliseconds")


def print_summary(summary: LogSummary, console: Console) -> None:
    state = "cut short: the recorder did not finish it" if summary.truncated else "finished"
    console.print(f"recording: {summary.path} ({state})", markup=False, highlight=False)
    if summary.channels:
        console.print(
            f"duration: {summary.duration_s:.3f} s, {_time_text(summary.start_ns)} to {_time_text(summary.end_ns)}",
            markup=False,
            highlight=False,
        )
    console.print(f"messages: {summary.messages}", markup=False, highlight=False)
    for name, label in ((RUN_METADATA, "run"), (END_METADATA, "at close")):
        items = summary.metadata.get(name, {})
        if name == END_METADATA:  # the per-channel and per-reason counts are in the tables
            items = {key: value for key, value in items.items() if "/" not in key}
        if items:
            text = "  ".join(f"{key}={value}" for key, value in sorted(items.items()))
            console.print(f"{label}: {text}", markup=False, highlight=False)
    gaps = summary.sequences.gaps_by_channel()
    lost = summary.sequences.lost or {}
    table = Table(title="channels", box=None)
    for column in ("channel", "type", "sources", "msgs", "rate Hz", "avg B", "gaps", "lost (bus)"):
        table.add_column(column, justify="left" if column in ("channel", "type", "sources") else "right")
    for name, channel in sorted(summary.channels.items()):
        table.add_row(
            name,
            type_name(channel.type_id),
            ",".join(map(str, sorted(channel.sources))),
            str(channel.messages),
            f"{channel.rate_hz():.1f}",
            f"{channel.bytes / channel.messages:.0f}",
            str(gaps[name]),
            str(lost[name]) if name in lost else "-",
        )
    console.print(table)
    rejected = summary.rejected()
    if rejected:
        text = "  ".join(f"{key}={count}" for key, count in sorted(rejected.items()))
        console.print(f"rejected by the bus (source/reason): {text}", markup=False, highlight=False)
    problems = summary.sequences.problems()
    if problems:
        console.print("sequence check: " + "; ".join(problems), markup=False, highlight=False)
    else:
        console.print(
            "sequence check: OK (every accepted message recorded, gaps = what the bus lost)",
            markup=False,
            highlight=False,
        )


def echo_lines(path: str | Path, channels: str | None, count: int | None) -> Iterator[str]:
    """JSON lines of a recording's messages, in the shape of ``rascal bus echo`` plus the times."""
    datagrams = iter_datagrams(path, channels)
    for datagram in datagrams if count is None else itertools.islice(datagrams, count):
        yield json.dumps(
            {
                "channel": datagram.channel,
                "source": datagram.source_id,
                "seq": datagram.seq,
                "t_meas_ns": datagram.t_meas_ns,
                "t_pub_ns": datagram.t_pub_ns,
                "log_time_ns": datagram.log_time_ns,
                "age_ms": round((datagram.log_time_ns - datagram.t_meas_ns) / 1e6, 3),
                "msg": _body_json(datagram),
            }
        )


def _body_json(datagram: Datagram) -> Any:
    try:
        return to_jsonable(decode(datagram))
    except ProtocolError as exc:
        return {"undecodable": str(exc)}


# -- command line ---------------------------------------------------------------------------------


def add_log_commands(commands: Any) -> None:
    """Register ``log info``, ``log echo`` and ``log play`` on the `rascal` command's subparsers."""
    log = commands.add_parser("log", help="recordings (MCAP): record, summarise, print, play back onto the bus")
    tools = log.add_subparsers(dest="tool", required=True)
    info = tools.add_parser("info", help="channels, counts, rates, duration, sources, sequence gaps, rejects")
    info.add_argument("file", type=Path, help="recording (.mcap)")
    info.add_argument("--strict", action="store_true", help="exit with status 1 if the sequence check fails")
    info.set_defaults(handler=_info)
    echo = tools.add_parser("echo", help="messages as JSON lines")
    echo.add_argument("file", type=Path, help="recording (.mcap)")
    echo.add_argument("--channels", type=_regex, help="regular expression the whole channel name must match")
    echo.add_argument("--count", type=_positive_int, help="stop after this many")
    echo.set_defaults(handler=_echo)
    play = tools.add_parser("play", help="republish onto the bus with the recorded timing (restamped, re-signed)")
    play.add_argument("file", type=Path, help="recording (.mcap)")
    play.add_argument("--speed", type=float, default=1.0, help="time scale: 2 is twice as fast, 0 as fast as possible")
    play.add_argument("--channels", type=_regex, help="channels to play (whole-name regex; default all but TIME_SYNC)")
    play.add_argument("--exact", action="store_true", help="send the recorded bytes unchanged (replay-attack tests)")
    play.add_argument("--sync-wait", type=float, default=1.0, help="seconds to wait for the time master first")
    play.set_defaults(handler=_play)
    record = tools.add_parser("record", help="record the live bus into MCAP until Ctrl-C (or --duration)")
    record.add_argument("channels", nargs="*", help="channels to record (default: every channel)")
    record.add_argument("-o", "--output", type=Path, help="MCAP file to write (default: record-DATE-TIME.mcap here)")
    record.add_argument("--duration", type=float, help="seconds to record (default: until Ctrl-C)")
    record.set_defaults(handler=_record)


def _regex(text: str) -> str:
    try:
        re.compile(text)
    except re.error as exc:
        raise argparse.ArgumentTypeError(f"bad regular expression {text!r}: {exc}") from None
    return text


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} is not positive")
    return value


def _reporting(handler: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """A file that is not a readable recording is a clear one-line error and status 2."""

    def run(args: argparse.Namespace) -> int:
        try:
            return handler(args)
        except RecordingError as exc:
            print(f"rascal log {args.tool}: {exc}", file=sys.stderr)
            return 2

    return run


@_reporting
def _info(args: argparse.Namespace) -> int:
    summary = summarize(args.file)
    print_summary(summary, make_console())
    return 1 if args.strict and summary.sequences.problems() else 0


@_reporting
def _echo(args: argparse.Namespace) -> int:
    try:
        for line in echo_lines(args.file, args.channels, args.count):
            print(line, flush=True)
    except BrokenPipeError:
        sys.stderr.close()  # `| head`: the reader went away, which is fine
    return 0


@_reporting
def _play(args: argparse.Namespace) -> int:
    from rascal.logplay import Player

    if not args.speed >= 0:
        print(f"rascal log play: --speed must be 0 or positive, not {args.speed}", file=sys.stderr)
        return 2
    bus, time_client = tool_bus(args.bus)
    try:
        player = Player(bus, time_client, speed=args.speed, channels=args.channels, exact=args.exact)
        synced = player.sync(args.sync_wait)
        result = player.play(iter_datagrams(args.file))
    finally:
        bus.close()
    clock = "synchronised" if synced else "unsynchronised (no time master answered)"
    print(
        f"played {result.total} messages on {len(result.sent)} channels in {result.duration_s:.2f} s "
        f"({result.recorded_span_s:.2f} s recorded, speed {args.speed:g}, {clock}); "
        f"at most {result.max_late_s * 1e3:.1f} ms behind schedule"
    )
    if result.skipped:
        print("left out: " + ", ".join(f"{name} ({count})" for name, count in sorted(result.skipped.items())))
    return 0


@reporting_errors
def _record(args: argparse.Namespace) -> int:
    wanted = [declared_channel(channel) for channel in args.channels]
    output = args.output or Path(datetime.now().strftime("record-%Y%m%d-%H%M%S.mcap"))
    print(f"recording {', '.join(wanted) or 'every channel'} into {output} (Ctrl-C ends it)", flush=True)
    writer = record(args.bus, output, wanted, args.duration)
    print(f"recorded {writer.messages} messages ({writer.bytes / 1e6:.1f} MB) into {writer.path}")
    return 0


def record(url: str | None, output: Path, wanted: list[str], duration_s: float | None) -> RecordingWriter:
    """Record what the bus accepts on ``wanted`` channels (empty: all) until ``duration_s`` or
    Ctrl-C, with the recorder's writer (rascal/recording.py); the file is finished either way."""
    from rascal.recording import RecordingWriter, bus_counts, describe_transport  # 0.4 s: only when recording

    bus, time_client = tool_bus(url)
    try:
        run_info = {
            "bus": describe_transport(bus.transport),
            "host": socket.gethostname(),
            "started_at": datetime.now().astimezone().isoformat(timespec="seconds"),
            "recorder_source_id": str(bus.source_id),
            "started_ns": str(bus.clock.now_ns()),
            "channels": ",".join(wanted) or "all",
        }
        writer = RecordingWriter(output, run_info)
        try:
            bus.subscribe_raw(lambda opened, data, recv_ns: _keep(writer, wanted, opened, data, recv_ns))
            run_for(bus, time_client, duration_s, 1.0, writer.flush)
        finally:
            writer.close(_counts_of(bus_counts(bus, writer), wanted))
    finally:
        bus.close()
    return writer


def _keep(writer: RecordingWriter, wanted: list[str], opened: Opened, data: bytes, recv_ns: int) -> None:
    if not wanted or opened.channel in wanted:
        writer.write(opened, data, recv_ns)


def _counts_of(counts: dict[str, str], wanted: list[str]) -> dict[str, str]:
    """The end-of-recording counts of the recorded channels only: ``log info``'s sequence check
    compares them with the file."""
    if not wanted:
        return counts
    return {
        key: value
        for key, value in counts.items()
        if not key.startswith(("received/", "lost/")) or key.partition("/")[2] in wanted
    }


def main(argv: list[str] | None = None) -> int:
    """`rascal log ...` on its own: ``main(["info", "RUN.mcap"])``."""
    from rascal.cli import main as rascal_main  # the one parser, with the global options

    return rascal_main(["log", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
