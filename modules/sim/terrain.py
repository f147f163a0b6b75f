"""The terrain model: flat ground (height 0) except for the scenario's hazards.

Each hazard is a strip: ``u`` runs along its ``yaw_rad`` (the direction a vehicle crosses it) over
``length_m``, ``v`` across it over ``width_m``. Inside the strip:

- a ditch goes down by ``magnitude_m`` over 45 deg walls and comes back up;
- a berm goes up by ``magnitude_m`` over 45 deg walls and comes back down;
- a drop-off falls by ``magnitude_m`` at its near edge (u = -length/2) over a steep face
  (5:1) and stays down to the strip's far end. A drop-off is meant to be longer than the
  sensors reach; crossed the other way it is a step up.

Overlapping hazards add. The vehicle is assumed level on the plane z = 0 (SimTruth has no
attitude), so heights are relative to the ground under the vehicle. The simulated lidars, the
camera renderer and the referee all read the ground from here.
"""

from __future__ import annotations

import math

import numpy as np

from modules.sim.world import HazardKind, TerrainHazard

WALL_SLOPE = 1.0  # rise over run of ditch and berm walls (45 deg)

CLIFF_SLOPE = 5.0  # rise over run of a drop-off's face


def ground_height(
    hazards: tuple[TerrainHazard, ...] | list[TerrainHazard], east: np.ndarray, north: np.ndarray
) -> np.ndarray:
    """Terrain height at ENU points (arrays of one shape), by the hazard model above."""
    height = np.zeros(np.shape(east))
    for hazard in hazards:
        dx, dy = east - hazard.east_m, north - hazard.north_m
        c, s = math.cos(hazard.yaw_rad), math.sin(hazard.yaw_rad)
        u, v = dx * c + dy * s, -dx * s + dy * c
        half = hazard.length_m / 2
        inside = (np.abs(u) <= half) & (np.abs(v) <= hazard.width_m / 2)
        if hazard.kind is HazardKind.DROP_OFF:
            run = min(hazard.magnitude_m / CLIFF_SLOPE, half / 2)
            shape = -np.clip((u + half) / run, 0.0, 1.0)
        else:
            run = min(hazard.magnitude_m / WALL_SLOPE, half / 2)
            sign = 1.0 if hazard.kind is HazardKind.BERM else -1.0
            shape = sign * np.clip((half - np.abs(u)) / run, 0.0, 1.0)
        height += np.where(inside, hazard.magnitude_m * shape, 0.0)
    return height
