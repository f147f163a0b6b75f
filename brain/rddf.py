"""DARPA Route Definition Data File (RDDF): strict, all-or-nothing parsing.

One waypoint per line, comma-separated::

    number, latitude_deg, longitude_deg, lateral_boundary_offset_ft, speed_limit_mph[, hour, minute, second]

Latitude and longitude are WGS84 decimal degrees. The offset and the speed limit of waypoint *i* apply
to the segment from waypoint *i* to waypoint *i + 1*; the corridor is twice the offset wide. The
optional phase-line time (DARPA-issued files) is ``####, ####, ####`` when unused. A speed limit of
0 mph marks the finish line, so only the last waypoint may have it.

Accepted alongside the format: padding (spaces, tabs) around fields, whole-line ``#`` comments, blank
lines, LF / CRLF / CR / CRCRLF line endings, no final newline, fractional offsets and speed limits,
numbering that starts anywhere and has gaps. Anything else raises `RddfError` naming the source, line
and field, and nothing is returned.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

BASE_FIELDS = ("number", "lat_deg", "lon_deg", "lateral_offset_ft", "speed_limit_mph")
PHASE_FIELDS = ("phase_hour", "phase_minute", "phase_second")
PHASE_EMPTY = "####"
MAX_LATERAL_OFFSET_FT = 5280.0  # DARPA's widest was 800 ft; a mile-wide half corridor means a broken file
MAX_SPEED_LIMIT_MPH = 100.0  # DARPA's highest limits were 50-60 mph

# Python's float() also takes "nan", "inf" and "1_000": none of those belong in an RDDF.
_DECIMAL = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")
_INTEGER = re.compile(r"[+-]?\d+")
# Editors and grep count CRCRLF (seen in a DARPA-issued file) as one line end; so do we.
_LINE_END = re.compile(r"\r*\n|\r")
_PHASE_RANGES = {"phase_hour": 23, "phase_minute": 59, "phase_second": 59}


class RddfError(ValueError):
    """An RDDF that cannot be used; the message names the source, line and field."""

    def __init__(self, source: str, message: str, line: int | None = None, field: str | None = None) -> None:
        self.source = source
        self.line = line
        self.field = field
        where = source if line is None else f"{source} line {line}"
        if field is not None:
            where += f", field '{field}'"
        super().__init__(f"{where}: {message}")


@dataclass(frozen=True)
class Waypoint:
    """One RDDF line; offset and speed limit govern the segment that starts here."""

    number: int
    lat_deg: float
    lon_deg: float
    lateral_offset_ft: float
    speed_limit_mph: float
    phase_line: tuple[int, int, int] | None = None  # (hour, minute, second) to be crossed by


def load_rddf(path: str | Path) -> list[Waypoint]:
    """Read and parse an RDDF file; errors are named after ``path`` as given."""
    source = str(path)
    data = Path(path).read_bytes()
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise RddfError(source, f"byte {data[exc.start]:#04x} is not text", line) from None
    return parse_rddf(text, source)


def parse_rddf(text: str, source: str) -> list[Waypoint]:
    """Parse RDDF text into waypoints, or raise `RddfError` for the first problem found."""
    parsed: list[tuple[int, Waypoint]] = []
    field_count: int | None = None
    for line_no, line in enumerate(_LINE_END.split(text), start=1):
        content = line.strip()
        if not content or content.startswith("#"):
            continue
        fields = [part.strip() for part in content.split(",")]
        field_count = _check_field_count(fields, field_count, source, line_no)
        waypoint = _parse_waypoint(fields, source, line_no)
        if parsed:
            _check_numbering(parsed[-1], waypoint, source, line_no)
        parsed.append((line_no, waypoint))
    _check_course(parsed, source)
    return [waypoint for _, waypoint in parsed]


def _check_field_count(fields: list[str], expected: int | None, source: str, line_no: int) -> int:
    count = len(fields)
    if count not in (len(BASE_FIELDS), len(BASE_FIELDS) + len(PHASE_FIELDS)):
        raise RddfError(
            source,
            f"expected 5 comma-separated fields ({', '.join(BASE_FIELDS)}) or 8 with a phase line, got {count}",
            line_no,
        )
    if expected is not None and count != expected:
        raise RddfError(source, f"{count} fields, but the lines before have {expected}", line_no)
    return count


def _parse_waypoint(fields: list[str], source: str, line_no: int) -> Waypoint:
    def number(index: int, low: float, high: float, low_open: bool = False) -> float:
        return _decimal(fields[index], BASE_FIELDS[index], low, high, low_open, source, line_no)

    return Waypoint(
        number=_integer(fields[0], "number", 0, None, source, line_no),
        lat_deg=number(1, -90.0, 90.0),
        lon_deg=number(2, -180.0, 180.0),
        lateral_offset_ft=number(3, 0.0, MAX_LATERAL_OFFSET_FT, low_open=True),
        speed_limit_mph=number(4, 0.0, MAX_SPEED_LIMIT_MPH),
        phase_line=_phase_line(fields[len(BASE_FIELDS) :], source, line_no),
    )


def _decimal(text: str, field: str, low: float, high: float, low_open: bool, source: str, line_no: int) -> float:
    if not _DECIMAL.fullmatch(text):
        raise RddfError(source, f"{text!r} is not a number", line_no, field)
    value = float(text)
    if value > high or value < low or (low_open and value == low):
        bounds = f"{'(' if low_open else '['}{low:g}, {high:g}]"
        raise RddfError(source, f"{text} is outside {bounds}", line_no, field)
    return value


def _integer(text: str, field: str, low: int, high: int | None, source: str, line_no: int) -> int:
    if not _INTEGER.fullmatch(text):
        raise RddfError(source, f"{text!r} is not a whole number", line_no, field)
    value = int(text)
    if value < low or (high is not None and value > high):
        bounds = f">= {low}" if high is None else f"within [{low}, {high}]"
        raise RddfError(source, f"{text} is not {bounds}", line_no, field)
    return value


def _phase_line(fields: list[str], source: str, line_no: int) -> tuple[int, int, int] | None:
    if not fields:
        return None
    # Check the set fields first, so a mistyped "###" is reported as itself.
    numbers = [
        _integer(text, field, 0, _PHASE_RANGES[field], source, line_no)
        for text, field in zip(fields, PHASE_FIELDS, strict=True)
        if text != PHASE_EMPTY
    ]
    if not numbers:
        return None
    if len(numbers) < len(PHASE_FIELDS):
        field = PHASE_FIELDS[fields.index(PHASE_EMPTY)]
        raise RddfError(source, f"{PHASE_EMPTY!r} beside a set phase-line time; give all three or none", line_no, field)
    hour, minute, second = numbers
    return hour, minute, second


def _check_numbering(previous: tuple[int, Waypoint], waypoint: Waypoint, source: str, line_no: int) -> None:
    previous_line, previous_waypoint = previous
    if waypoint.number == previous_waypoint.number:
        raise RddfError(source, f"waypoint {waypoint.number} repeats line {previous_line}", line_no, "number")
    if waypoint.number < previous_waypoint.number:
        message = f"waypoint {waypoint.number} comes after {previous_waypoint.number} (line {previous_line})"
        raise RddfError(source, f"{message}; numbers must increase", line_no, "number")


def _check_course(parsed: list[tuple[int, Waypoint]], source: str) -> None:
    if len(parsed) < 2:
        raise RddfError(source, f"{len(parsed)} waypoint(s); a course needs at least 2")
    for line_no, waypoint in parsed[:-1]:
        if waypoint.speed_limit_mph == 0.0:
            message = f"0 mph marks the finish, but waypoint {waypoint.number} is not the last"
            raise RddfError(source, message, line_no, "speed_limit_mph")
