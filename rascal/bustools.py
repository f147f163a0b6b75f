"""`rascal bus list | echo | hz | pub` and `rascal time status`: look at the live bus.

In a terminal they draw live tables (rich); piped, they print plain lines, one per update, so
their output can be grepped and tested. Every tool stops by itself after ``--duration``.
"""

from __future__ import annotations

import difflib
import itertools
import json
import math
import random
import statistics
import sys
import time
import typing
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import msgpack
from rich.console import Console
from rich.live import Live
from rich.table import Table

from protocol import channels
from protocol.auth import Keyring
from protocol.codec import Opened, decode_body, unpack_body
from protocol.errors import ProtocolError
from protocol.messages import ModuleStatus
from protocol.schema import info_for_class, info_for_id, registered
from rascal.bus import Bus, ChannelStats
from rascal.clock import SharedClock
from rascal.timeclient import TimeClient
from rascal.timesync import SyncState

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


def run_for(bus: Bus, time_client: TimeClient, duration_s: float, every_s: float, tick: Callable[[], None]) -> None:
    """Poll the bus for ``duration_s``, asking the time master every 100 ms (unless the bus is
    receive-only: the far end of a bridge hears, in its own time) and calling ``tick`` every
    ``every_s``."""
    start = time.monotonic()
    next_tick = start + every_s
    next_sync = start if bus.transport.can_send else math.inf
    while (now := time.monotonic()) < start + duration_s:
        if now >= next_sync:
            time_client.request()
            next_sync = now + 0.1
        if now >= next_tick:
            tick()
            next_tick += every_s
        bus.poll(min(next_tick, next_sync, start + duration_s) - time.monotonic())


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


def bus_list(url: str | None, duration_s: float, console: Console) -> dict[str, ChannelStats]:
    """Discover every channel on the bus for ``duration_s``; return its statistics."""
    bus, time_client = tool_bus(url)
    bus.subscribe_raw(lambda *_: None)

    def render() -> Table:
        return channel_table(bus, bus.clock.now_ns())

    with display(console, render) as refresh:
        run_for(bus, time_client, duration_s, 0.5, refresh)
    if not console.is_terminal:
        console.print(render())
    bus.close()
    return bus.stats


def channel_table(bus: Bus, now_ns: int) -> Table:
    table = Table(title="channels", box=None)
    for column in ("channel", "type", "sources", "msgs", "rate Hz", "avg B", "lost", "latency p50 us"):
        table.add_column(column, justify="left" if column in ("channel", "type", "sources") else "right")
    for name, stats in sorted(bus.stats.items()):
        latencies = sorted(stats.latencies_ns)
        p50 = latencies[len(latencies) // 2] / 1e3 if latencies else float("nan")
        try:
            type_name = info_for_id(stats.type_id).cls.__name__
        except ProtocolError:
            type_name = f"#{stats.type_id}"  # a type newer than this tool
        table.add_row(
            name,
            type_name,
            ",".join(map(str, sorted(stats.sources))),
            str(stats.messages),
            f"{stats.rate_hz(now_ns):.1f}",
            f"{stats.bytes / max(stats.messages, 1):.0f}",
            str(stats.lost),
            f"{p50:.0f}",
        )
    return table


# -- bus echo ---------------------------------------------------------------------------------


def bus_echo(url: str | None, channel: str, duration_s: float, count: int | None, console: Console) -> int:
    """Print each message on ``channel`` as one JSON line; return how many were printed."""
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
    deadline = time.monotonic() + duration_s
    while time.monotonic() < deadline and (count is None or printed < count):
        run_for(bus, time_client, min(0.2, deadline - time.monotonic()), 1.0, lambda: None)
    bus.close()
    return printed


# -- bus hz -----------------------------------------------------------------------------------


def bus_hz(
    url: str | None, channel: str, duration_s: float, window_s: float, console: Console
) -> list[dict[str, float]]:
    """Every ``window_s``: rate, interval statistics, loss and latency of ``channel``."""
    declared_channel(channel)
    bus, time_client = tool_bus(url)
    bus.subscribe_raw(lambda *_: None)
    rows: list[dict[str, float]] = []

    def measure() -> None:
        now = bus.clock.now_ns()
        stats = bus.stats.get(channel)
        recent = [t for t in stats.arrivals_ns if t >= now - int(window_s * 1e9)] if stats else []
        intervals = [(b - a) / 1e6 for a, b in itertools.pairwise(recent)]
        latencies = sorted(list(stats.latencies_ns)[-len(recent) :]) if stats and recent else []
        row = {
            "rate_hz": stats.rate_hz(now, int(window_s * 1e9)) if stats else 0.0,
            "min_ms": min(intervals, default=float("nan")),
            "max_ms": max(intervals, default=float("nan")),
            "std_ms": statistics.pstdev(intervals) if len(intervals) > 1 else float("nan"),
            "lost": float(stats.lost if stats else 0),
            "latency_p50_us": latencies[len(latencies) // 2] / 1e3 if latencies else float("nan"),
        }
        rows.append(row)
        line = (
            f"{channel}: rate {row['rate_hz']:.2f} Hz  interval min {row['min_ms']:.2f} max {row['max_ms']:.2f} "
            f"std {row['std_ms']:.2f} ms  lost {row['lost']:.0f}  latency p50 {row['latency_p50_us']:.0f} us"
        )
        emit(console, line)

    run_for(bus, time_client, duration_s, window_s, measure)
    bus.close()
    return rows


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
