"""`rascal bus list | echo | hz | pub` and `rascal time status`: look at the live bus.

In a terminal they draw live tables (rich); piped, they print plain lines, one per update, so
their output can be grepped and tested; ``--json`` prints JSON instead. ``echo`` and ``hz`` run
until Ctrl-C (or ``--duration`` / ``--count``), which ends them as a normal exit; ``list`` and
``info`` listen for ``--duration``.
"""

from __future__ import annotations

import argparse
import difflib
import itertools
import json
import math
import os
import random
import statistics
import sys
import time
import typing
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from typing import Any

import msgpack
from rich.console import Console
from rich.live import Live
from rich.table import Table

from protocol import channels
from protocol.auth import Keyring
from protocol.authority import GOVERNED
from protocol.codec import Opened, decode_body, unpack_body
from protocol.errors import ProtocolError
from protocol.messages import ModuleStatus
from protocol.schema import info_for_class, info_for_id, registered
from rascal.runtime.bus import Bus, ChannelStats
from rascal.runtime.clock import SharedClock
from rascal.runtime.timeclient import TimeClient
from rascal.runtime.timesync import SyncState

# Below protocol.authority.OPERATOR_SOURCE_ID (0xFFF0): a tool never takes the operator's id.
TOOL_SOURCE_IDS = (0xF000, 0xFFEF)


def tool_bus(
    url: str | None, *, signing: bool = True, keyring: Keyring | None = None, source_id: int | None = None
) -> tuple[Bus, TimeClient]:
    """A short-lived node for a tool, synced to the master: ``source_id``, else a random one in
    the tools' range; ``keyring``, else the deployment's."""
    clock = SharedClock()
    source_id = source_id or random.randint(*TOOL_SOURCE_IDS)
    bus = Bus.open(url, source_id=source_id, clock=clock, keyring=keyring, signing=signing)
    return bus, TimeClient(bus, clock)


def run_for(
    bus: Bus,
    time_client: TimeClient,
    duration_s: float | None,
    every_s: float,
    tick: Callable[[], None],
    done: Callable[[], bool] = lambda: False,
) -> None:
    """Poll the bus for ``duration_s`` (None: until Ctrl-C) or until ``done()``, asking the time
    master every 100 ms (unless the bus is receive-only: the far end of a bridge hears, in its
    own time) and calling ``tick`` every ``every_s``. Ctrl-C ends it as a normal end."""
    start = time.monotonic()
    end = math.inf if duration_s is None else start + duration_s
    next_tick = start + every_s
    next_sync = start if bus.transport.can_send else math.inf
    try:
        while (now := time.monotonic()) < end and not done():
            if now >= next_sync:
                time_client.request()
                next_sync = now + 0.1
            if now >= next_tick:
                tick()
                next_tick += every_s
            bus.poll(min(next_tick, next_sync, end) - time.monotonic())
    except KeyboardInterrupt:
        pass  # the user's way to end a tool that runs until stopped


def reporting_errors(handler: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """A bus tool's command: bad input (bus URL, key file, channel, JSON, output file) is one
    line and exit 2; Ctrl-C, or a reader that went away (``| head``), is a normal end."""

    def run(args: argparse.Namespace) -> int:
        try:
            return handler(args)
        except KeyboardInterrupt:
            return 0
        except BrokenPipeError:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
            return 0
        except (ValueError, OSError) as exc:  # UrlError and KeyFileError are ValueErrors
            print(f"rascal {args.command} {args.tool}: {exc}", file=sys.stderr)
            return 2

    return run


def declared_channel(channel: str) -> str:
    """``channel`` if protocol.channels declares it; else ValueError naming the nearest ones."""
    if channel in channels.CHANNEL_TYPES:
        return channel
    near = difflib.get_close_matches(channel.upper(), channels.CHANNEL_TYPES, n=3, cutoff=0.5)
    hint = f"did you mean {', '.join(near)}?" if near else f"declared: {', '.join(sorted(channels.CHANNEL_TYPES))}"
    raise ValueError(f"unknown channel {channel!r}; {hint}")


def to_jsonable(value: Any) -> Any:
    if hasattr(value, "_asdict"):
        return {key: to_jsonable(item) for key, item in value._asdict().items()}
    if isinstance(value, tuple):
        return [to_jsonable(item) for item in value]
    if isinstance(value, bytes):
        return value.hex()
    return value


def from_jsonable(tp: Any, value: Any) -> Any:
    """JSON (object with field names, or array in field order) -> typed message."""
    if hasattr(tp, "_fields"):
        hints = typing.get_type_hints(tp)
        if isinstance(value, dict):
            unknown = set(value) - set(tp._fields)
            if unknown:
                raise ValueError(f"{tp.__name__} has no field(s) {sorted(unknown)}; fields: {list(tp._fields)}")
            return tp(**{key: from_jsonable(hints[key], item) for key, item in value.items()})
        return tp(*(from_jsonable(hints[name], item) for name, item in zip(tp._fields, value, strict=False)))
    if typing.get_origin(tp) is tuple:
        (item_type, _ellipsis) = typing.get_args(tp)
        return tuple(from_jsonable(item_type, item) for item in value)
    if tp is float:
        return float(value)
    return value


@contextmanager
def display(console: Console, render: Callable[[], Table]) -> Iterator[Callable[[], None]]:
    """Yield a refresh function: a live table in a terminal, printed plain lines when piped."""
    if console.is_terminal:
        with Live(render(), console=console, auto_refresh=False) as live:
            yield lambda: live.update(render(), refresh=True)
    else:
        yield lambda: None


def make_console() -> Console:
    """Rich in a terminal; piped, wide enough that tables are never truncated, and no colour."""
    if sys.stdout.isatty():
        return Console()
    return Console(width=200, no_color=True, highlight=False)


def emit(console: Console, line: str) -> None:
    """One output line: through rich in a terminal, plain and flushed when piped."""
    if console.is_terminal:
        console.print(line, markup=False, highlight=False)
    else:
        print(line, flush=True)


# -- bus list ---------------------------------------------------------------------------------


def bus_list(url: str | None, duration_s: float, console: Console, as_json: bool = False) -> dict[str, ChannelStats]:
    """Discover every channel on the bus for ``duration_s``; return its statistics."""
    bus, time_client = tool_bus(url)
    bus.subscribe_raw(lambda *_: None)

    def render() -> Table:
        return channel_table(channel_rows(bus.stats, bus.clock.now_ns()))

    try:
        with display(console, render) if not as_json else nullcontext(lambda: None) as refresh:
            run_for(bus, time_client, duration_s, 0.5, refresh)
        rows = channel_rows(bus.stats, bus.clock.now_ns())
        if as_json:
            emit(console, json_text({"channels": rows}))
        elif not console.is_terminal:
            console.print(channel_table(rows))
    finally:
        bus.close()
    return bus.stats


def type_name(type_id: int) -> str:
    try:
        return info_for_id(type_id).cls.__name__
    except ProtocolError:
        return f"#{type_id}"  # a type newer than this tool


def stats_row(stats: ChannelStats, now_ns: int, window_ns: int = 2_000_000_000) -> dict[str, Any]:
    """What the tools show of one channel (or one publisher of it)."""
    latencies = sorted(stats.latencies_ns)
    return {
        "messages": stats.messages,
        "rate_hz": round(stats.rate_hz(now_ns, window_ns), 3),
        "avg_bytes": round(stats.bytes / max(stats.messages, 1)),
        "lost": stats.lost,
        "latency_p50_us": round(latencies[len(latencies) // 2] / 1e3, 1) if latencies else None,
    }


def channel_rows(all_stats: dict[str, ChannelStats], now_ns: int) -> list[dict[str, Any]]:
    return [
        {
            "channel": name,
            "type": type_name(stats.type_id),
            "sources": sorted(stats.sources),
            **stats_row(stats, now_ns),
        }
        for name, stats in sorted(all_stats.items())
    ]


def channel_table(rows: list[dict[str, Any]]) -> Table:
    table = Table(title="channels", box=None)
    for column in ("channel", "type", "sources", "msgs", "rate Hz", "avg B", "lost", "latency p50 us"):
        table.add_column(column, justify="left" if column in ("channel", "type", "sources") else "right")
    for row in rows:
        table.add_row(
            row["channel"],
            row["type"],
            ",".join(map(str, row["sources"])),
            str(row["messages"]),
            f"{row['rate_hz']:.1f}",
            str(row["avg_bytes"]),
            str(row["lost"]),
            "-" if row["latency_p50_us"] is None else f"{row['latency_p50_us']:.0f}",
        )
    return table


def json_text(value: Any) -> str:
    """The tools' --json output: where there is no data the value is null, never NaN (which is
    not JSON, and which strict readers refuse)."""
    return json.dumps(value, allow_nan=False)


# -- bus info ---------------------------------------------------------------------------------


def bus_info(url: str | None, channel: str, duration_s: float, console: Console, as_json: bool = False) -> dict:
    """A channel's declaration (type, fingerprint, port) and, from listening ``duration_s``, its
    publishers with their rates."""
    declared_channel(channel)
    info = info_for_class(channels.CHANNEL_TYPES[channel])
    bus, time_client = tool_bus(url)
    publishers: dict[int, ChannelStats] = {}

    def count(opened: Opened, data: bytes, recv_ns: int) -> None:
        if opened.channel == channel:
            stats = publishers.setdefault(opened.source_id, ChannelStats(type_id=opened.type_id))
            stats.messages += 1
            stats.bytes += len(data)
            stats.arrivals_ns.append(recv_ns)
            stats.latencies_ns.append(recv_ns - opened.t_pub_ns)

    bus.subscribe_raw(count)
    started = time.monotonic()
    try:
        run_for(bus, time_client, duration_s, duration_s, lambda: None)
        now, window_ns = bus.clock.now_ns(), int(max(time.monotonic() - started, 1e-3) * 1e9)
        lost = bus.stats[channel].lost if channel in bus.stats else 0
    finally:
        bus.close()
    report = {
        "channel": channel,
        "type": info.cls.__name__,
        "type_id": info.type_id,
        "fingerprint": info.fingerprint,
        "port_offset": channels.port_offset(channel),
        "command_authority": channel in GOVERNED,
        "listened_s": round(window_ns / 1e9, 3),
        "lost": lost,
        "publishers": [
            {"source": source, **stats_row(stats, now, window_ns)} for source, stats in sorted(publishers.items())
        ],
    }
    emit(console, json_text(report) if as_json else "\n".join(info_lines(report)))
    return report


def info_lines(report: dict[str, Any]) -> list[str]:
    lines = [
        f"channel: {report['channel']}",
        f"type: {report['type']} (type id {report['type_id']}, fingerprint {report['fingerprint']}; "
        f"fields: rascal interface show {report['type']})",
        f"port: bus base port + {report['port_offset']}",
        "rate and max age: not declared by the protocol (see the publishing module's README)",
    ]
    if report["command_authority"]:
        lines.append("command authority: accepted only signed by a source with authority on it")
    lines.append(f"publishers heard in {report['listened_s']:.1f} s: {len(report['publishers']) or 'none'}")
    lines += [
        f"  source {row['source']}: {row['rate_hz']:.2f} Hz, {row['messages']} msgs, avg {row['avg_bytes']} B, "
        f"latency p50 {row['latency_p50_us']} us"
        for row in report["publishers"]
    ]
    return [*lines, f"lost: {report['lost']}"]


# -- bus echo ---------------------------------------------------------------------------------


def bus_echo(url: str | None, channel: str, duration_s: float | None, count: int | None, console: Console) -> int:
    """Print each message on ``channel`` as one JSON line until ``count`` of them, ``duration_s``
    or Ctrl-C; return how many were printed."""
    declared_channel(channel)
    bus, time_client = tool_bus(url)
    printed = 0

    def show(opened: Opened, data: bytes, recv_ns: int) -> None:
        nonlocal printed
        if opened.channel != channel or (count is not None and printed >= count):
            return
        try:
            body = to_jsonable(decode_body(opened.type_id, opened.body, opened.source_id))
        except ProtocolError as exc:
            body = {"undecodable": str(exc)}
        header = {
            "source": opened.source_id,
            "seq": opened.seq,
            "t_meas_ns": opened.t_meas_ns,
            "age_ms": round((recv_ns - opened.t_meas_ns) / 1e6, 3),
        }
        emit(console, json.dumps({"channel": channel, **header, "msg": body}))
        printed += 1

    bus.subscribe_raw(show)
    try:
        run_for(bus, time_client, duration_s, 1.0, lambda: None, done=lambda: count is not None and printed >= count)
    finally:
        bus.close()
    return printed


# -- bus hz -----------------------------------------------------------------------------------


def bus_hz(
    url: str | None, channel: str, duration_s: float | None, window_s: float, console: Console, as_json: bool = False
) -> list[dict[str, Any]]:
    """Every ``window_s`` until ``duration_s`` or Ctrl-C: rate, interval statistics, loss and
    latency of ``channel`` (one JSON object a line with ``as_json``; no data is null)."""
    declared_channel(channel)
    if not window_s > 0:
        raise ValueError(f"--window must be positive, not {window_s}")
    bus, time_client = tool_bus(url)
    bus.subscribe_raw(lambda *_: None)
    rows: list[dict[str, Any]] = []

    def measure() -> None:
        row = window_row(bus.stats.get(channel), bus.clock.now_ns(), int(window_s * 1e9))
        rows.append(row)
        emit(console, json_text({"channel": channel, **row}) if as_json else hz_line(channel, row))

    try:
        run_for(bus, time_client, duration_s, window_s, measure)
    finally:
        bus.close()
    return rows


def window_row(stats: ChannelStats | None, now_ns: int, window_ns: int) -> dict[str, Any]:
    """One `bus hz` report over the last ``window_ns``; None where there is nothing to measure."""
    recent = [t for t in stats.arrivals_ns if t >= now_ns - window_ns] if stats else []
    intervals = [(b - a) / 1e6 for a, b in itertools.pairwise(recent)]
    latencies = sorted(list(stats.latencies_ns)[-len(recent) :]) if stats and recent else []
    return {
        "rate_hz": stats.rate_hz(now_ns, window_ns) if stats else 0.0,
        "min_ms": min(intervals, default=None),
        "max_ms": max(intervals, default=None),
        "std_ms": statistics.pstdev(intervals) if len(intervals) > 1 else None,
        "lost": stats.lost if stats else 0,
        "latency_p50_us": latencies[len(latencies) // 2] / 1e3 if latencies else None,
    }


def hz_line(channel: str, row: dict[str, Any]) -> str:
    def number(key: str, digits: int) -> str:
        return "-" if row[key] is None else f"{row[key]:.{digits}f}"

    return (
        f"{channel}: rate {row['rate_hz']:.2f} Hz  interval min {number('min_ms', 2)} max {number('max_ms', 2)} "
        f"std {number('std_ms', 2)} ms  lost {row['lost']}  latency p50 {number('latency_p50_us', 0)} us"
    )


# -- bus pub ----------------------------------------------------------------------------------


def bus_pub(url: str | None, channel: str, body_json: str, type_name: str | None, rate_hz: float, count: int) -> int:
    """Publish a message given as JSON ``count`` times at ``rate_hz``; return how many were sent."""
    msg_type = channels.CHANNEL_TYPES.get(channel)
    if type_name is not None:
        by_name = {info.cls.__name__: info.cls for info in registered()}
        if type_name not in by_name:
            raise ValueError(f"unknown message type {type_name!r}; known: {sorted(by_name)}")
        msg_type = by_name[type_name]
    if msg_type is None:
        raise ValueError(f"channel {channel!r} is not declared; pass --type")
    try:
        body = json.loads(body_json)
    except json.JSONDecodeError as exc:
        raise ValueError(f"the message is not JSON: {exc}") from None
    msg = checked(msg_type, from_jsonable(msg_type, body))
    bus, time_client = tool_bus(url)
    sent = 0

    def send() -> None:
        nonlocal sent
        if sent < count:
            bus.publish(channel, msg)
            sent += 1

    time_client.request()
    send()
    if count > 1:
        run_for(bus, time_client, (count - 1) / rate_hz + 0.05, 1.0 / rate_hz, send)
    bus.close()
    return sent


def checked(msg_type: type, msg: Any) -> Any:
    """``msg`` as every receiver will decode it; ValueError for what they would reject (a
    string where a number belongs, a missing field...), before anything is sent."""
    try:
        return info_for_class(msg_type).decode(unpack_body(msgpack.packb(msg, use_bin_type=True)))
    except ProtocolError as exc:
        raise ValueError(f"not a valid {msg_type.__name__}: {exc}") from None


# -- time status ------------------------------------------------------------------------------


def time_status(url: str | None, duration_s: float, console: Console) -> dict[str, ModuleStatus]:
    """Synchronise to the master for ``duration_s``, then show this node's estimate and every
    module's clock state from its heartbeat."""
    bus, time_client = tool_bus(url)
    nodes: dict[str, ModuleStatus] = {}
    bus.subscribe(channels.MODULE_STATUS, lambda status, _env: nodes.__setitem__(status.module, status))
    run_for(bus, time_client, duration_s, duration_s, lambda: None)
    clock = bus.clock
    assert isinstance(clock, SharedClock)
    own = clock.estimator.status(clock.local_ns())
    table = Table(title="shared time", box=None)
    for column in ("node", "state", "offset us", "error bound us", "drift ppm"):
        table.add_column(column, justify="left" if column in ("node", "state") else "right")
    table.add_row(
        "this tool",
        own.state.name,
        f"{own.offset_ns / 1e3:.1f}" if own.state is not SyncState.UNSYNCED else "-",
        f"{own.error_bound_ns / 1e3:.1f}" if own.state is not SyncState.UNSYNCED else "-",
        f"{own.drift_ppm:.2f}" if own.state is not SyncState.UNSYNCED else "-",
    )
    for name, status in sorted(nodes.items()):
        state = SyncState(status.clock_state).name if status.clock_state in iter(SyncState) else str(status.clock_state)
        table.add_row(
            name, state, f"{status.clock_offset_ns / 1e3:.1f}", f"{status.clock_error_bound_ns / 1e3:.1f}", ""
        )
    console.print(table)
    bus.close()
    return nodes
