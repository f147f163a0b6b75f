"""Shared test material for the RDDF tests: where the real files live, and synthetic courses.

The real files belong to their authors and are read in place, never copied into the project.
"""

from __future__ import annotations

from collections.abc import Sequence

import pymap3d
import pytest

from brain.rddf import Waypoint
from tests.conftest import ROOT

REAL_RDDF_DIR = ROOT.parent / "shared" / "data" / "rddf"
REAL_RDDF_FILES = sorted(p for p in REAL_RDDF_DIR.iterdir() if p.is_file()) if REAL_RDDF_DIR.is_dir() else []
ABSENT_REASON = f"the real RDDF files are not at {REAL_RDDF_DIR}"

ORIGIN_LAT_DEG = 37.5427
ORIGIN_LON_DEG = -122.0570


def real_rddf_params() -> list[object]:
    """One pytest parameter per real file, or a single skipped one naming where they were looked for."""
    if not REAL_RDDF_FILES:
        return [pytest.param(None, id="absent", marks=pytest.mark.skip(reason=ABSENT_REASON))]
    return [pytest.param(path, id=path.name) for path in REAL_RDDF_FILES]


def waypoints_at(
    points_m: Sequence[tuple[float, float]],
    offset_ft: float | Sequence[float] = 12.0,
    speed_mph: float | Sequence[float] = 25.0,
) -> list[Waypoint]:
    """Waypoints placed at east/north metres from a fixed origin (the first point should be (0, 0))."""
    count = len(points_m)
    offsets = [offset_ft] * count if isinstance(offset_ft, float | int) else list(offset_ft)
    speeds = [speed_mph] * count if isinstance(speed_mph, float | int) else list(speed_mph)
    waypoints = []
    for number, ((east, north), offset, speed) in enumerate(zip(points_m, offsets, speeds, strict=True), start=1):
        lat, lon, _ = pymap3d.enu2geodetic(east, north, 0.0, ORIGIN_LAT_DEG, ORIGIN_LON_DEG, 0.0)
        waypoints.append(Waypoint(number, float(lat), float(lon), float(offset), float(speed)))
    return waypoints


def rddf_text(waypoints: Sequence[Waypoint]) -> str:
    """The waypoints as a plain five-field RDDF."""
    return "".join(
        f"{w.number},{w.lat_deg:.9f},{w.lon_deg:.9f},{w.lateral_offset_ft:g},{w.speed_limit_mph:g}\n" for w in waypoints
    )
