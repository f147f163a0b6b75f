"""How the stack's modules are told their course: an RDDF file and, optionally, the ENU origin.

The stack sees what a team was handed on race morning, the RDDF, and nothing of the simulated
world. Every module that works in the local ENU frame (navigation, brain, control) takes the
same two settings, so they agree on the frame: ``course`` (an RDDF path) and ``origin``
("lat,lon" or "lat,lon,alt"; empty means the first waypoint, as for the simulator).
"""

from __future__ import annotations

import math
from pathlib import Path

from brain.corridor import Course, GeodeticOrigin

DEFAULT_COURSE = Path(__file__).resolve().parents[1] / "deploy" / "scenarios" / "mojave.rddf"


def parse_origin(text: str) -> GeodeticOrigin | None:
    """``"lat,lon[,alt]"`` in degrees and metres; an empty string is None (first waypoint)."""
    if not text.strip():
        return None
    parts = [part.strip() for part in text.split(",")]
    try:
        values = [float(part) for part in parts]
    except ValueError:
        raise ValueError(f"origin: expected 'lat,lon' or 'lat,lon,alt' in degrees and metres, got {text!r}") from None
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
        raise ValueError(f"origin: expected 'lat,lon' or 'lat,lon,alt' in degrees and metres, got {text!r}")
    if not (-90.0 <= values[0] <= 90.0 and -180.0 <= values[1] <= 180.0):
        raise ValueError(f"origin: latitude {values[0]} or longitude {values[1]} out of range")
    return GeodeticOrigin(*values)


def load_course(rddf: str | Path, origin: str = "") -> Course:
    """The course from an RDDF file, in the frame of ``origin`` (see parse_origin)."""
    return Course.from_file(rddf, parse_origin(origin))
