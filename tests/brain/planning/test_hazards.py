"""One cycle's view of the fused map: clearance bounds, footprint costs, input checks."""

from __future__ import annotations

import numpy as np
import pytest

from brain.grid import GridWindow, Sides
from brain.planning.hazards import HazardField
from tests.brain.planning.scenes import Map


def field_of(grid: Map, footprint_m: float = 1.0, caution: float = 0.5) -> HazardField:
    return HazardField(grid.window, grid.hazard, grid.cost, footprint_m, cost_cap=10.0, caution_probability=caution)


def scattered(seed: int) -> Map:
    rng = np.random.default_rng(seed)
    grid = Map(GridWindow(-3.0, 2.0, 0.2, rows=60, cols=80))
    lethal = rng.random(grid.window.shape) < 0.01
    lethal[:, 0] |= rng.random(grid.window.shape[0]) < 0.3  # hazards on the window's edge too
    grid.cost[lethal] = np.inf
    return grid


def exact_distance(points: np.ndarray, centres: np.ndarray) -> np.ndarray:
    return np.min(np.hypot(points[:, None, 0] - centres[None, :, 0], points[:, None, 1] - centres[None, :, 1]), axis=1)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_clearance_bound_never_overstates_and_is_exact_at_cell_centres(seed: int) -> None:
    grid = scattered(seed)
    hazards = field_of(grid)
    rng = np.random.default_rng(seed + 100)
    # Inside, on the edges and well outside the window (it spans east -3..13, north 2..14).
    points = np.column_stack([rng.uniform(-8.0, 18.0, 3000), rng.uniform(-3.0, 19.0, 3000)])
    truth = exact_distance(points, grid.lethal_centres())
    bound = hazards.clearance_bound(points[:, 0], points[:, 1])
    assert np.all(bound <= truth + 1e-5)
    # Within the window it loses at most a cell diagonal (half of it each side of a centre).
    inside = (points[:, 0] > -3.0) & (points[:, 0] < 13.0) & (points[:, 1] > 2.0) & (points[:, 1] < 14.0)
    assert np.all(bound[inside] >= truth[inside] - 0.2 * np.sqrt(2) - 1e-5)
    centres = np.column_stack([grid.east.ravel()[::37], grid.north.ravel()[::37]])
    np.testing.assert_allclose(
        hazards.clearance_bound(centres[:, 0], centres[:, 1]), exact_distance(centres, grid.lethal_centres()), atol=1e-4
    )


def test_no_lethal_cells_means_unbounded_clearance() -> None:
    grid = Map(GridWindow(0.0, 0.0, 0.5, rows=10, cols=10))
    hazards = field_of(grid)
    assert np.all(np.isinf(hazards.clearance_bound([1.0, 50.0], [1.0, -3.0])))
    assert np.all(np.isinf(hazards.caution_clearance([1.0], [1.0])))


def test_caution_clearance_is_a_lower_bound_to_uncertain_and_lethal_cells() -> None:
    grid = scattered(7)
    grid.hazard[30, 40] = 0.6  # not lethal, but a caution cell
    grid.hazard[10, 10] = 0.4  # below the caution probability
    hazards = field_of(grid, caution=0.5)
    caution = np.vstack([grid.lethal_centres(), [[grid.east[30, 40], grid.north[30, 40]]]])
    rng = np.random.default_rng(8)
    points = np.column_stack([rng.uniform(-6.0, 16.0, 2000), rng.uniform(-1.0, 17.0, 2000)])
    bound = hazards.caution_clearance(points[:, 0], points[:, 1])
    truth = exact_distance(points, caution)
    assert np.all(bound <= truth + 1e-5)
    # As exact as the lethal clearance: inside the window it loses at most a cell diagonal.
    inside = (points[:, 0] > -3.0) & (points[:, 0] < 13.0) & (points[:, 1] > 2.0) & (points[:, 1] < 14.0)
    assert np.all(bound[inside] >= truth[inside] - 0.2 * np.sqrt(2) - 1e-5)


def test_footprint_cost_is_the_mean_over_the_footprint_square() -> None:
    grid = Map(GridWindow(0.0, 0.0, 0.5, rows=20, cols=20))
    grid.cost[10, 10] = 9.0
    grid.cost[2, 2] = np.inf  # lethal counts as the cap
    hazards = field_of(grid, footprint_m=1.0)  # 2 * round(1.0 / 0.5) + 1 = 5 cells a side
    assert hazards.footprint_cost[10, 10] == pytest.approx(9.0 / 25)
    assert hazards.footprint_cost[12, 8] == pytest.approx(9.0 / 25)
    assert hazards.footprint_cost[13, 10] == 0.0
    assert hazards.footprint_cost[2, 2] == pytest.approx(10.0 / 25)
    assert hazards.cost_at(5.25, 5.25) == pytest.approx(9.0 / 25)
    assert hazards.cost_at(-1.0, 5.0) == 0.0  # outside the window nothing is known


@pytest.mark.parametrize(
    ("hazard", "cost", "message"),
    [
        (np.zeros((3, 3), np.float32), np.zeros((4, 4), np.float32), "shape"),
        (np.zeros((4, 4), np.float32), np.full((4, 4), np.nan, np.float32), "cost"),
        (np.zeros((4, 4), np.float32), np.full((4, 4), -1.0, np.float32), "cost"),
        (np.full((4, 4), 1.5, np.float32), np.zeros((4, 4), np.float32), "hazard_probability"),
        (np.zeros((4, 4), np.int32), np.zeros((4, 4), np.float32), "float"),
    ],
)
def test_bad_layers_are_refused_by_name(hazard: np.ndarray, cost: np.ndarray, message: str) -> None:
    window = GridWindow(0.0, 0.0, 1.0, rows=4, cols=4)
    with pytest.raises(ValueError, match=message):
        HazardField(window, hazard, cost, 1.0, 10.0, 0.5)


@pytest.mark.parametrize("seed", [4, 5])
def test_walls_count_as_lethal_cells_just_outside_their_edges(seed: int) -> None:
    """A cropped window's cut edges: a ring of lethal cells half a cell outside them, nothing
    beyond them passes, and the bound still never overstates (open edges stay open)."""
    grid = scattered(seed)
    window, res = grid.window, grid.window.resolution_m
    walls = Sides(south=True, north=False, west=False, east=True)
    hazards = HazardField(window, grid.hazard, grid.cost, 1.0, 10.0, 0.5, walls=walls)
    ring_east = window.origin_east_m + (np.arange(-1, window.cols + 1) + 0.5) * res
    ring_north = window.origin_north_m + (np.arange(-1, window.rows + 1) + 0.5) * res
    south = np.column_stack([ring_east, np.full_like(ring_east, window.origin_north_m - res / 2)])
    east_edge = window.origin_east_m + window.cols * res + res / 2
    east = np.column_stack([np.full_like(ring_north, east_edge), ring_north])
    marked = np.vstack([grid.lethal_centres(), south, east])
    rng = np.random.default_rng(seed + 100)
    points = np.column_stack([rng.uniform(-8.0, 18.0, 3000), rng.uniform(-3.0, 19.0, 3000)])
    bound = hazards.clearance_bound(points[:, 0], points[:, 1])
    assert np.all(bound <= exact_distance(points, marked) + 1e-5)
    # Past a wall's ring (and along it): the strips below the south ring and right of the east one.
    along_e = (points[:, 0] >= ring_east[0]) & (points[:, 0] <= ring_east[-1])
    along_n = (points[:, 1] >= ring_north[0]) & (points[:, 1] <= ring_north[-1])
    past = (along_e & (points[:, 1] <= south[0, 1])) | (along_n & (points[:, 0] >= east_edge))
    assert past.sum() > 500
    assert np.all(bound[past] == 0.0)
    assert np.all(hazards.caution_clearance(points[past, 0], points[past, 1]) == 0.0)
    # Beyond the open north edge, away from the walls and lethal cells, it is as open as ever.
    assert hazards.clearance_bound([-2.0], [40.0])[0] > 20.0
    unwalled = field_of(grid).clearance_bound(points[:, 0], points[:, 1])
    assert np.all(bound <= unwalled + 1e-5)


def test_a_window_without_lethal_cells_has_only_its_walls() -> None:
    grid = Map(GridWindow(0.0, 0.0, 0.5, rows=10, cols=10))
    hazards = HazardField(grid.window, grid.hazard, grid.cost, 1.0, 10.0, 0.5, walls=Sides(west=True))
    np.testing.assert_allclose(
        hazards.clearance_bound([0.25, 2.25, 4.75], [2.25, 2.25, 2.25]), [0.5, 2.5, 5.0], atol=1e-6
    )
    assert hazards.clearance_bound([-1.0], [2.0])[0] == 0.0
    assert np.isinf(field_of(grid).clearance_bound([-1.0], [2.0])[0])
