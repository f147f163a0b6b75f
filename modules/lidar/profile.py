"""Vertical lidar: the ground profile ahead of the vehicle, and the hazards in it.

A scanner mounted high and turned to sweep a vertical plane along the vehicle's heading sees the
ground ahead as one line of returns: RASCAL tracked the surface this way. Beams step by 0.5 deg
between the depression that meets flat ground ``near_m`` ahead and the one that meets it
``far_m`` ahead; on flat ground their footprints thin out with range (0.15 m apart at 5 m,
0.56 m at 10 m, 2.2 m at 20 m), which bounds how precisely an edge can be placed.

The profile's returns are simulated from the terrain model (modules/sim/lidar/profile.py,
modules/sim/terrain.py); ``detect_hazards`` finds the stretches that are not level ground.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from modules.sim.world import HazardKind
from protocol.messages import SurfaceProfile


@dataclass(frozen=True)
class VerticalMount:
    """A vertically scanning lidar: its position in the vehicle frame (it looks along +x) and
    the stretch of flat ground its beams cover."""

    x_m: float
    y_m: float
    z_m: float = 1.6
    near_m: float = 3.0  # flat-ground distance ahead of the sensor of the steepest beam
    far_m: float = 25.0  # ... of the shallowest beam
    resolution_rad: float = math.radians(0.5)
    max_range_m: float = 80.0
    range_noise_std_m: float = 0.01

    def depressions_rad(self) -> np.ndarray:
        """Beam angles below horizontal, steepest (nearest) first."""
        steep, shallow = math.atan2(self.z_m, self.near_m), math.atan2(self.z_m, self.far_m)
        count = int((steep - shallow) / self.resolution_rad + 1e-9) + 1
        return steep - self.resolution_rad * np.arange(count)


VERTICAL_MOUNTS: dict[str, VerticalMount] = {
    "lidar_v_left": VerticalMount(x_m=1.5, y_m=0.5),
    "lidar_v_right": VerticalMount(x_m=1.5, y_m=-0.5),
}


class Hazard(NamedTuple):
    """A stretch of a profile that is not level ground, in vehicle-frame forward distance."""

    kind: HazardKind
    start_range_m: float
    end_range_m: float
    magnitude_m: float  # depth of a ditch or drop-off, height of a berm


def detect_hazards(profile: SurfaceProfile, step_m: float = 0.15) -> list[Hazard]:
    """Non-level stretches of a profile: runs of returns more than ``step_m`` below (ditch or,
    when the ground never comes back up within the profile, drop-off) or above (berm) the
    vehicle's ground plane.

    A hazard starts half a sample spacing past the last level return before it: a wall facing
    away from the sensor is in shadow, so its edge lies somewhere before the next beam's footprint.
    It ends at the first level return after it, which for a berm means after the shadow behind
    its crest (where its far side is hidden: a conservative end). The magnitude is the deepest
    or highest return seen, a lower bound when part of the hazard is hidden; for a drop-off, the
    median of its returns (its floor)."""
    ranges = np.asarray(profile.ranges_m, dtype=float)
    heights = np.asarray(profile.heights_m, dtype=float)
    level = np.where(heights < -step_m, -1, np.where(heights > step_m, 1, 0))
    hazards = []
    i = 0
    while i < len(level):
        if level[i] == 0:
            i += 1
            continue
        j = i
        while j + 1 < len(level) and level[j + 1] == level[i]:
            j += 1
        hazards.append(_describe_run(ranges, heights, level, i, j))
        i = j + 1
    return hazards


def _describe_run(ranges: np.ndarray, heights: np.ndarray, level: np.ndarray, i: int, j: int) -> Hazard:
    """The hazard made of returns i..j (all below, or all above, the level band)."""
    if i == 0:
        start = float(ranges[0])
    else:
        spacing = ranges[i - 1] - ranges[i - 2] if i >= 2 else 0.0
        start = float(min(ranges[i - 1] + spacing / 2, ranges[i]))
    # Runs are maximal, so whatever follows a low run is higher ground: the ground came back up.
    comes_back = j + 1 < len(level)
    end = float(ranges[j + 1]) if comes_back else float(ranges[j])
    run = heights[i : j + 1]
    if level[i] > 0:
        return Hazard(HazardKind.BERM, start, end, float(run.max()))
    if comes_back:
        return Hazard(HazardKind.DITCH, start, end, float(-run.min()))
    return Hazard(HazardKind.DROP_OFF, start, end, float(-np.median(run)))
