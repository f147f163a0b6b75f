"""The recorder: every accepted message on the bus into one MCAP file, runnable as its own process.

    python -m rascal.recording --bus URL --out runs/X/run.mcap [--info KEY=VALUE ...] [--duration S]

What the file holds (MCAP, zstd chunks):

* per bus channel and message type, a **raw channel**: topic = the bus channel, message encoding
  ``rascal-v1``, no schema; each message is the whole signed message exactly as received
  (reassembled, tag included), so a replay is byte-exact. Channel metadata names the type id, the
  layout and its fingerprint. ``log_time`` = receive time (shared time), ``publish_time`` = the
  header's ``t_pub_ns``, ``sequence`` = the low 32 bits of the header's sequence (MCAP's field is
  32-bit; the full number is in the bytes).
* beside it, a **JSON channel** ``<CHANNEL>.json`` (encoding ``json``) with a JSON Schema
  (``jsonschema``) generated from the message declaration: Foxglove opens the file as it is.
  ``rascal run`` records raw only (``json_channels=false``: the JSON costs four times the raw
  write) and adds the JSON channels when the run has ended (rascal/record_twins.py).
  Messages whose body does not decode (a peer holding the key but sending a newer or broken
  layout) are kept raw only and counted.
* the **foxglove-schema channels** of rascal/record_foxglove.py (``/tf``, ``/rascal/pose``,
  ``/rascal/obstacles``, ``/rascal/path``, ``/rascal/corridor`` with ``--set course=RDDF``,
  ``/rascal/map``, ``/rascal/gps``), converted at a bounded rate, so Foxglove's 3D and Map panels
  draw the run (``foxglove=false`` leaves them out; ``rascal run`` does, and the rewrite after
  the run that adds the JSON channels makes them from the raw ones).
* metadata ``run`` at the start (what the caller passed with ``--info``, the bus, the host) and
  ``recording`` at the end: messages received and lost per channel as the bus counted them, and
  rejected datagrams per source and reason. ``rascal.logread.check_sequences`` compares the
  recorded sequence numbers with these counts.

The recorder sees exactly what its Bus accepts (``Bus.subscribe_raw``): a message rejected as a
replay, stale, forged or malformed is counted in ``recording``, never written. The chunk in
progress is written out every ``flush_period_s``, so a killed recorder loses at most that much
and the file stays readable up to its last chunk. An existing file is never overwritten: a
restarted recorder writes ``NAME.1.mcap``, ``NAME.2.mcap``...
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mcap.writer import CompressionType, Writer

from brain.course_config import load_course
from protocol.codec import Opened, unpack_body
from protocol.errors import ProtocolError
from protocol.messages import Severity
from protocol.schema import info_for_id
from protocol.transport import Transport
from rascal.record_foxglove import FoxgloveOptions, FoxgloveTap
from rascal.record_schema import (
    JSON_ENCODING,
    JSON_SCHEMA_ENCODING,
    JSON_TOPIC_SUFFIX,
    RAW_ENCODING,
    json_converter,
    known_type,
    message_schema_bytes,
    raw_channel_metadata,
)
from rascal.runtime.bus import Bus
from rascal.runtime.config import setting
from rascal.runtime.launch import run_module
from rascal.runtime.module import Module, Runtime

RECORDER_SOURCE_ID = 8
RUN_METADATA = "run"
END_METADATA = "recording"
PROFILE = "rascal"
LIBRARY = "rascal recorder"
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
DEFAULT_FOXGLOVE = FoxgloveOptions()
_SEQ32 = 0xFFFFFFFF
_dumps = json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode


class _Route:
    """Where one (bus channel, type) goes in the file."""

    __slots__ = ("decode", "json_id", "raw_id", "to_json")

    def __init__(
        self,
        raw_id: int,
        json_id: int,
        decode: Callable[[Any], Any] | None,
        to_json: Callable[[Any], Any] | None,
    ) -> None:
        self.raw_id = raw_id
        self.json_id = json_id  # 0: no JSON channel
        self.decode = decode
        self.to_json = to_json


class RecordingWriter:
    """Writes bus messages into one MCAP file. Sans-bus: feed it :meth:`write` from a raw
    subscription (or from anything else that yields opened messages) and :meth:`close` it."""

    def __init__(
        self,
        path: Path,
        run_info: dict[str, str],
        *,
        json_channels: bool = True,
        compression: str = "zstd",
        chunk_bytes: int = 1024 * 1024,
        foxglove: FoxgloveOptions | None = DEFAULT_FOXGLOVE,
    ) -> None:
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {sorted(COMPRESSIONS)}, not {compression!r}")
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path, self._file = _open_new(path)
        self.json_channels = json_channels
        self.writer = Writer(self._file, chunk_size=chunk_bytes, compression=COMPRESSIONS[compression])
        self.writer.start(profile=PROFILE, library=LIBRARY)
        self.writer.add_metadata(RUN_METADATA, run_info)
        self.foxglove = None if foxglove is None else FoxgloveTap(self.writer, foxglove)
        self._routes: dict[tuple[str, int], _Route] = {}
        self._schemas: dict[int, int] = {}  # type id -> MCAP schema id
        self.messages = 0
        self.bytes = 0
        self.undecodable = 0
        self.closed = False

    def write(self, opened: Opened, data: bytes, recv_ns: int) -> None:
        """One authenticated message, as the bus's raw handler hands it over."""
        route = self._routes.get((opened.channel, opened.type_id))
        if route is None:
            route = self._route(opened.channel, opened.type_id)
        publish_ns = opened.t_pub_ns if opened.t_pub_ns > 0 else 0
        sequence = opened.seq & _SEQ32
        add = self.writer.add_message
        add(route.raw_id, recv_ns, data, publish_ns, sequence)
        self.messages += 1
        self.bytes += len(data)
        if self.foxglove is not None:
            self.foxglove.feed(opened, recv_ns)
        if route.json_id:
            try:
                msg = route.decode(unpack_body(opened.body, opened.source_id))  # type: ignore[misc]
                body = _dumps(route.to_json(msg)).encode()  # type: ignore[misc]
            except (ProtocolError, ValueError):  # ValueError: a float the validator let through as non-finite
                self.undecodable += 1
                return
            add(route.json_id, recv_ns, body, publish_ns, sequence)

    def _route(self, channel: str, type_id: int) -> _Route:
        raw_id = self.writer.register_channel(channel, RAW_ENCODING, 0, raw_channel_metadata(type_id))
        json_id, decode, to_json = 0, None, None
        if self.json_channels and known_type(type_id):
            schema_id = self._schemas.get(type_id)
            if schema_id is None:
                name, document = message_schema_bytes(type_id)
                schema_id = self._schemas[type_id] = self.writer.register_schema(name, JSON_SCHEMA_ENCODING, document)
            json_id = self.writer.register_channel(
                channel + JSON_TOPIC_SUFFIX, JSON_ENCODING, schema_id, {"type_id": str(type_id)}
            )
            info = info_for_id(type_id)
            decode, to_json = info.decode, json_converter(info.cls)
        route = self._routes[(channel, type_id)] = _Route(raw_id, json_id, decode, to_json)
        return route

    def flush(self) -> None:
        """Write the chunk in progress to the file (bounds what a crash can lose)."""
        self.writer.flush()

    def close(self, end_info: dict[str, str]) -> None:
        """Add the end-of-recording metadata and the MCAP summary, then close the file."""
        if self.closed:
            return
        self.closed = True
        try:
            self.writer.add_metadata(END_METADATA, end_info)
            self.writer.finish()
        finally:
            self._file.close()


def _open_new(path: Path) -> tuple[Path, IO[bytes]]:
    """Open ``path`` for writing, or ``STEM.1.mcap``, ``STEM.2.mcap``... if it exists: a
    restarted recorder must not destroy the recording of its previous life."""
    candidate = path
    for index in range(1, 10_000):
        try:
            return candidate, candidate.open("xb")
        except FileExistsError:
            candidate = path.with_name(f"{path.stem}.{index}{path.suffix}")
    raise FileExistsError(f"{path}: no free file name beside it")


def bus_counts(bus: Bus, writer: RecordingWriter) -> dict[str, str]:
    """End-of-recording metadata: what this bus accepted, lost and rejected (MCAP metadata is
    string to string, so counts are decimal text under flat keys)."""
    info = {
        "ended_ns": str(bus.clock.now_ns()),
        "messages": str(writer.messages),
        "bytes": str(writer.bytes),
        "undecodable": str(writer.undecodable),
        "rejected": str(bus.rejected_total()),
    }
    for channel, stats in sorted(bus.stats.items()):
        info[f"received/{channel}"] = str(stats.messages)
        info[f"lost/{channel}"] = str(stats.lost)
    for (source_id, reason), count in sorted(bus.rejects.items(), key=lambda item: (str(item[0][0]), item[0][1])):
        info[f"rejected/{'unknown' if source_id is None else source_id}/{reason}"] = str(count)
    return info


@dataclass(frozen=True)
class RecorderConfig:
    out: str = setting("", "MCAP file to write (required); an existing one is kept and NAME.1.mcap written instead")
    info: tuple[str, ...] = setting((), "run information for the file's 'run' metadata, KEY=VALUE items")
    json_channels: bool = setting(True, "also write each message decoded as JSON with its JSON Schema (Foxglove)")
    compression: str = setting("zstd", "chunk compression: zstd, lz4 or none")
    chunk_kib: int = setting(1024, "uncompressed size at which a chunk is written")
    flush_period_s: float = setting(1.0, "write the chunk in progress at least this often (what a crash can lose)")
    foxglove: bool = setting(True, "also write foxglove-schema channels (3D scene, transform, map, GPS) for Foxglove")
    foxglove_hz: float = setting(10.0, "rate of the foxglove scene, transform, pose, path and GPS channels")
    foxglove_grid_period_s: float = setting(2.0, "period of the foxglove map Grid (the biggest message)")
    course: str = setting("", "RDDF file whose corridor goes into the foxglove scene (empty: no corridor)")
    origin: str = setting("", "ENU origin of the course, 'lat,lon[,alt]' (empty: its first waypoint)")


class Recorder(Module):
    """Record every accepted message on the bus into one MCAP file (--out FILE, --info KEY=VALUE)."""

    name = "recorder"
    default_source_id = RECORDER_SOURCE_ID
    Config = RecorderConfig

    def __init__(self, config: RecorderConfig, runtime: Runtime) -> None:
        super().__init__(config, runtime)
        self.writer: RecordingWriter | None = None
        self.failed = ""

    def on_start(self) -> None:
        config = self.config
        if not config.out:
            raise ValueError("recorder: no output file; pass --out FILE (or --set out=FILE)")
        if config.flush_period_s <= 0 or config.chunk_kib <= 0:
            raise ValueError("recorder: flush_period_s and chunk_kib must be positive")
        run_info = {
            "bus": describe_transport(self.bus.transport),
            "host": socket.gethostname(),
            "started_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "recorder_source_id": str(self.bus.source_id),
            "restarts": str(self.runtime.restarts),
            "started_ns": str(self.clock.now_ns()),
            **course_info(config.course, config.origin),
            **parse_info(config.info),
        }
        self.writer = RecordingWriter(
            Path(config.out),
            run_info,
            json_channels=config.json_channels,
            compression=config.compression,
            chunk_bytes=config.chunk_kib * 1024,
            foxglove=foxglove_options(config) if config.foxglove else None,
        )
        # Not woken by each of ~600 datagrams a second: they wait in the sockets (with their
        # kernel arrival times) until the loop's next task, at most the time request's 0.1 s.
        self.bus.subscribe_raw(self.on_message, wake=False)
        self.every(config.flush_period_s, self.flush, priority=-1)

    def on_message(self, opened: Opened, data: bytes, recv_ns: int) -> None:
        writer = self.writer
        if writer is None or self.failed:
            return
        try:
            writer.write(opened, data, recv_ns)
        except OSError as exc:
            self._fail(exc)

    def flush(self) -> None:
        if self.writer is not None and not self.failed:
            try:
                self.writer.flush()
            except OSError as exc:
                self._fail(exc)

    def _fail(self, exc: OSError) -> None:
        # A recorder that cannot write must say so and exit: the supervisor restarts it into a new file.
        self.failed = f"cannot write {self.config.out}: {exc}"
        self.report(Severity.CRITICAL, "recording_failed", self.failed)
        self.runtime.stop()

    def on_stop(self) -> None:
        if self.writer is not None:
            try:
                self.writer.close(bus_counts(self.bus, self.writer))
            except OSError as exc:
                print(f"recorder: closing {self.writer.path}: {exc}", file=sys.stderr)

    def status_detail(self) -> str:
        if self.failed:
            return self.failed
        if self.writer is None:
            return "not recording"
        return f"{self.writer.messages} messages, {self.writer.bytes / 1e6:.1f} MB into {self.writer.path}"


def foxglove_options(config: RecorderConfig) -> FoxgloveOptions:
    """The recorder's settings as the tap's options; a course that does not load is an error at start."""
    if not config.foxglove_hz > 0:
        raise ValueError("recorder: foxglove_hz must be positive")
    course = load_course(config.course, config.origin) if config.course else None
    return FoxgloveOptions(course, 1.0 / config.foxglove_hz, config.foxglove_grid_period_s)


def course_info(course: str, origin: str) -> dict[str, str]:
    """Run metadata naming the course, so the JSON twins rewrite draws the same corridor."""
    return {"course": str(Path(course).resolve()), "origin": origin} if course else {}


def describe_transport(transport: Transport) -> str:
    """The bus a recording was made on, e.g. ``UdpConfig(group='239.255.76.67', base_port=7667, ...)``."""
    config = getattr(transport, "config", None)
    return repr(config) if config is not None else type(transport).__name__


def parse_info(items: tuple[str, ...] | list[str]) -> dict[str, str]:
    """``["deployment=localhost", "scenario=mojave"]`` -> a dict; a clear error for anything else."""
    info: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"run information {item!r}: expected KEY=VALUE")
        info[key] = value
    return info


def main(argv: list[str] | None = None) -> int:
    """``python -m rascal.recording``: the module command line plus ``--out`` and ``--info``."""
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--out")
    parser.add_argument("--info", action="append", default=[])
    known, rest = parser.parse_known_args(sys.argv[1:] if argv is None else argv)
    try:
        parse_info(known.info)
    except ValueError as exc:
        print(f"recorder: {exc}", file=sys.stderr)
        return 2
    if any("," in item for item in known.info):
        print("recorder: --info values cannot contain commas", file=sys.stderr)
        return 2
    configured = any(arg.startswith("out=") or arg in ("--config", "--print-config", "-h", "--help") for arg in rest)
    if not known.out and not configured:
        print("recorder: no output file; pass --out FILE", file=sys.stderr)
        return 2
    extra = ["--set", "info=" + ",".join(known.info)] if known.info else []
    if known.out:
        extra += ["--set", f"out={known.out}"]
    run_module(Recorder, [*rest, *extra])
    return 0


if __name__ == "__main__":
    sys.exit(main())
