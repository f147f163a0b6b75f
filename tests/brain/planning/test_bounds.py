"""The corridor as a hard boundary: local sub-corridors and the raster mask agree with Corridor."""

from __future__ import annotations

import numpy as np

from brain.grid import GridWindow
from brain.planning.bounds import LocalCorridor
from tests.brain.planning.scenes import course_through

ZIGZAG = course_through([(0.0, 0.0), (40.0, 10.0), (60.0, -5.0), (90.0, 0.0), (300.0, 80.0)], half_width_m=5.0)


def test_raster_mask_matches_the_corridor_at_cell_centres() -> None:
    corridor = ZIGZAG.corridor
    window = GridWindow(-10.0, -20.0, 0.2, rows=200, cols=600)
    east, north = window.cell_centres()
    truth = corridor.distance_to_edge(east, north)
    for clearance in (0.0, 0.6, 1.3):
        mask = LocalCorridor(corridor).mask(window, clearance)
        # float32 inside the mask: only cells within a millimetre of the threshold may differ.
        differ = mask != (truth >= clearance)
        assert np.all(np.abs(truth[differ] - clearance) < 1e-3)
        assert mask.sum() > 1000


def test_local_distances_equal_the_whole_corridor() -> None:
    corridor = ZIGZAG.corridor
    local = LocalCorridor(corridor)
    rng = np.random.default_rng(3)
    east, north = rng.uniform(20.0, 80.0, 500), rng.uniform(-12.0, 15.0, 500)
    np.testing.assert_allclose(local.distance_to_edge(east, north), corridor.distance_to_edge(east, north))
    near = local.near((20.0, -12.0, 80.0, 15.0))
    assert near is not None and len(near.half_width_m) < len(corridor.half_width_m)


def test_points_no_band_can_reach_are_outside() -> None:
    local = LocalCorridor(ZIGZAG.corridor)
    assert local.near((1000.0, 1000.0, 1001.0, 1001.0)) is None
    assert np.all(local.distance_to_edge(np.array([1000.0]), np.array([1000.0])) == -np.inf)
