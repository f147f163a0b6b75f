"""Reading a recording back: its raw messages with channel and times, its metadata, and the
sequence check (every message the recorder's bus accepted is in the file, per stream).

Files are read linearly in file order, which is arrival order; a file whose recorder was
killed (no summary, maybe a cut chunk) is read up to its last whole record.
"""

from __future__ import annotations

import re
import struct
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, NamedTuple

from mcap.exceptions import EndOfFile, McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader
from zstandard import ZstdError

from protocol.codec import HEADER, HEADER_BYTES, MAGIC, body_span, decode_body
from protocol.errors import ProtocolError
from protocol.replay import ReplayGuard
from rascal.record_schema import RAW_ENCODING
from rascal.recording import END_METADATA, RUN_METADATA


class RecordingError(ValueError):
    """A file that is not a readable rascal recording; the message names the file and the problem."""


class Datagram(NamedTuple):
    """One recorded message: header fields, the recorder's receive time, the signed bytes."""

    channel: str
    source_id: int
    seq: int
    t_meas_ns: int
    t_pub_ns: int
    log_time_ns: int
    type_id: int
    data: bytes


@dataclass
class Scan:
    """What a linear pass learnt besides the messages."""

    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    truncated: bool = False


class _WholeReads:
    """File reads that are all or nothing: a record cut off by a killed recorder reads as the
    end of the file instead of as a short buffer somewhere inside the mcap reader."""

    def __init__(self, stream: IO[bytes]) -> None:
        self._stream = stream

    def read(self, size: int = -1) -> bytes:
        data = self._stream.read(size)
        if size > 0 and len(data) < size:
            raise EndOfFile()
        return data


def _records(path: Path, scan: Scan) -> Iterator[Channel | Message | Metadata]:
    try:
        stream = path.open("rb")
    except OSError as exc:
        raise RecordingError(f"{path}: {exc.strerror or exc}") from None
    with stream:
        records = 0
        try:
            for record in StreamReader(_WholeReads(stream)).records:  # type: ignore[arg-type]
                records += 1
                if isinstance(record, Metadata):
                    scan.metadata[record.name] = dict(record.metadata)
                if isinstance(record, Channel | Message | Metadata):
                    yield record
        except EndOfFile:
            if not records:
                raise RecordingError(f"{path}: empty, or cut before its MCAP header") from None
            scan.truncated = True  # the recorder did not finish: read what it wrote
        except (McapError, ZstdError, struct.error, ValueError) as exc:
            raise RecordingError(f"{path}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None


def iter_datagrams(
    path: str | Path, channels: str | re.Pattern[str] | None = None, scan: Scan | None = None
) -> Iterator[Datagram]:
    """The raw messages of a recording in arrival order, optionally only channels matching the
    regular expression ``channels`` (whole name). ``scan`` collects metadata and truncation."""
    path = Path(path)
    pattern = re.compile(channels) if isinstance(channels, str) else channels
    scan = scan if scan is not None else Scan()
    raw: dict[int, bool] = {}  # MCAP channel id -> wanted raw channel
    for record in _records(path, scan):
        if isinstance(record, Channel):
            wanted = record.message_encoding == RAW_ENCODING
            raw[record.id] = wanted and (pattern is None or pattern.fullmatch(record.topic) is not None)
        elif isinstance(record, Message) and raw.get(record.channel_id):
            yield _datagram(path, record)


def _datagram(path: Path, record: Message) -> Datagram:
    data = record.data
    if len(data) < HEADER_BYTES or data[:2] != MAGIC:
        raise RecordingError(f"{path}: a raw message at log time {record.log_time} is not a rascal message")
    (_magic, _version, _flags, type_id, source_id, _key, channel_len, _r, seq, t_meas_ns, t_pub_ns) = (
        HEADER.unpack_from(data)
    )
    channel = data[HEADER_BYTES : HEADER_BYTES + channel_len].decode("ascii", errors="replace")
    return Datagram(channel, source_id, seq, t_meas_ns, t_pub_ns, record.log_time, type_id, bytes(data))


def decode(datagram: Datagram) -> Any:
    """The typed message a recorded datagram carries; ProtocolError if its body does not decode.
    The tag is not checked again: the recorder wrote only what its bus had authenticated."""
    return decode_body(datagram.type_id, body_of(datagram.data), datagram.source_id)


def body_of(data: bytes) -> memoryview:
    """The body of a whole recorded message: after the header and channel name, before the
    signature and tag."""
    start, end = body_span(data)
    return memoryview(data)[start:end]


def read_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """Metadata records by name (``run``, ``recording``): from the index of a finished file,
    else by reading the file through."""
    path = Path(path)
    try:
        stream = path.open("rb")
    except OSError as exc:
        raise RecordingError(f"{path}: {exc.strerror or exc}") from None
    with stream:
        try:
            reader = make_reader(stream)
            if reader.get_summary() is not None:
                return {record.name: dict(record.metadata) for record in reader.iter_metadata()}
        except (McapError, ZstdError, struct.error, ValueError, OSError):
            pass  # no intact footer (the recorder was killed): read the file through instead
    scan = Scan()
    for _ in _records(path, scan):
        pass
    return scan.metadata


# -- the sequence check -------------------------------------------------------------------------


@dataclass
class StreamSequence:
    """One (source, channel) stream of a recording."""

    source_id: int
    channel: str
    messages: int = 0
    first_seq: int = 0
    last_seq: int = 0
    gaps: int = 0  # messages missing between the recorded ones, counted as the bus counts loss
    duplicates: int = 0


@dataclass
class SequenceReport:
    streams: dict[tuple[int, str], StreamSequence]
    recorded: Counter[str]  # messages in the file per channel
    received: dict[str, int] | None  # what the recorder's bus accepted per channel (None: not finished)
    lost: dict[str, int] | None  # what it counted as lost per channel
    truncated: bool

    def gaps_by_channel(self) -> Counter[str]:
        gaps: Counter[str] = Counter()
        for stream in self.streams.values():
            gaps[stream.channel] += stream.gaps
        return gaps

    def problems(self) -> list[str]:
        """Every disagreement between the file and the bus's own counts; empty when consistent."""
        problems = [
            f"{s.channel} from source {s.source_id}: {s.duplicates} duplicate message(s)"
            for s in self.streams.values()
            if s.duplicates
        ]
        if self.received is None or self.lost is None:
            return [*problems, "no end-of-recording counts: the recorder did not finish the file"]
        gaps = self.gaps_by_channel()
        for channel in sorted(set(self.recorded) | set(self.received)):
            if self.recorded[channel] != self.received.get(channel, 0):
                problems.append(
                    f"{channel}: {self.recorded[channel]} recorded, {self.received.get(channel, 0)} received"
                )
            if gaps[channel] != self.lost.get(channel, 0):
                problems.append(
                    f"{channel}: {gaps[channel]} missing sequence number(s), the bus lost {self.lost.get(channel, 0)}"
                )
        return problems

    @property
    def ok(self) -> bool:
        return not self.problems()


class SequenceChecker:
    """Per (source, channel), the sequence numbers of a recording with no gaps beyond what the
    recorder's bus counted as lost, and every accepted message recorded.

    Gaps are counted by the bus's own replay window (``protocol.replay``) fed in arrival order,
    so reordering, late fills and a restarted publisher's jump count exactly as they did live.
    """

    def __init__(self) -> None:
        self._guard = ReplayGuard()
        self.streams: dict[tuple[int, str], StreamSequence] = {}
        self.recorded: Counter[str] = Counter()

    def add(self, datagram: Datagram) -> None:
        key = (datagram.source_id, datagram.channel)
        stream = self.streams.get(key)
        if stream is None:
            stream = self.streams[key] = StreamSequence(datagram.source_id, datagram.channel, first_seq=datagram.seq)
        stream.messages += 1
        stream.last_seq = max(stream.last_seq, datagram.seq)
        self.recorded[datagram.channel] += 1
        try:
            stream.gaps += self._guard.check(key[0], key[1], datagram.seq, datagram.t_pub_ns, None)
        except ProtocolError:
            stream.duplicates += 1

    def report(self, scan: Scan) -> SequenceReport:
        """The result, compared with the end-of-recording counts ``scan`` found."""
        end = scan.metadata.get(END_METADATA)
        received = _counts(end, "received/") if end is not None else None
        lost = _counts(end, "lost/") if end is not None else None
        return SequenceReport(self.streams, self.recorded, received, lost, scan.truncated)


def check_sequences(path: str | Path) -> SequenceReport:
    """Read a recording through and check its sequence numbers (see :class:`SequenceChecker`)."""
    scan = Scan()
    checker = SequenceChecker()
    for datagram in iter_datagrams(path, scan=scan):
        checker.add(datagram)
    return checker.report(scan)


def _counts(metadata: dict[str, str], prefix: str) -> dict[str, int]:
    return {key.removeprefix(prefix): int(value) for key, value in metadata.items() if key.startswith(prefix)}


__all__ = [
    "END_METADATA",
    "RUN_METADATA",
    "Datagram",
    "RecordingError",
    "Scan",
    "SequenceChecker",
    "SequenceReport",
    "StreamSequence",
    "check_sequences",
    "decode",
    "iter_datagrams",
    "read_metadata",
]
