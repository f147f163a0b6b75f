"""A* on the lattice: 8-connected, every edge's fine cells free, the furthest reachable end."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from brain.planning.search import STEPS, Lattice, search


def open_field(rows: int = 60, cols: int = 150) -> np.ndarray:
    return np.ones((rows, cols), dtype=bool)


def run(free: np.ndarray, start: tuple[int, int], goal_col: int, stride: int, weight: float = 1.0):
    lattice = Lattice.build(free, stride, start)
    _rows, cols = lattice.node_centres()
    goal_distance = np.maximum(goal_col - cols, 0) * 0.2
    cost = np.ones(lattice.shape)
    return search(lattice, lattice.node_of(start), cols >= goal_col, goal_distance, cost, 0.2, weight)


def fine_cells_between(a: np.ndarray, b: np.ndarray) -> list[tuple[int, int]]:
    steps = int(max(abs(b - a)))
    return [tuple(a + (b - a) * t // steps) for t in range(steps + 1)]


@pytest.mark.parametrize("stride", [1, 2, 3])
def test_open_field_goes_straight(stride: int) -> None:
    result = run(open_field(), (30, 5), 140, stride)
    assert result.reached_goal
    assert result.cells[0].tolist() == [30, 5] and result.cells[-1, 1] >= 140
    assert np.all(result.cells[:, 0] == 30)


@pytest.mark.parametrize("stride", [1, 2])
def test_a_wall_is_passed_through_its_gap_on_free_cells_only(stride: int) -> None:
    free = open_field()
    free[:, 70:75] = False
    free[44:48, 70:75] = True  # a gap four cells wide
    result = run(free, (10, 5), 140, stride, weight=1.5)
    assert result.reached_goal
    cells = result.cells
    assert np.all(np.abs(np.diff(cells, axis=0)) <= stride)
    for a, b in itertools.pairwise(cells):
        assert all(free[cell] for cell in fine_cells_between(a, b))
    crossing = cells[(cells[:, 1] >= 70) & (cells[:, 1] < 75)]
    assert np.all((crossing[:, 0] >= 44) & (crossing[:, 0] < 48))


def test_no_way_through_ends_at_the_reachable_cell_nearest_the_goal() -> None:
    free = open_field()
    free[:, 90:92] = False
    result = run(free, (30, 5), 140, 2)
    assert not result.reached_goal
    assert 86 <= result.cells[-1, 1] < 90
    # The component check aimed straight for it instead of flooding all 30 x 45 reachable nodes.
    assert result.expansions < 30 * 45 / 2


def test_a_blocked_start_has_no_path() -> None:
    free = open_field()
    free[28:33, 3:8] = False
    result = run(free, (30, 5), 140, 2)
    assert len(result.cells) == 0 and not result.reached_goal


def test_lattice_edges_need_every_fine_cell_on_the_run() -> None:
    free = open_field(10, 10)
    free[4, 5] = False
    lattice = Lattice.build(free, 2, (4, 4))  # nodes at even rows and columns: (4, 4) is node (2, 2)
    node = lattice.node_of((4, 4))
    east = 1 << STEPS.index((0, 1))
    north = 1 << STEPS.index((1, 0))
    west = 1 << STEPS.index((0, -1))
    assert not lattice.edges[node] & east  # (4, 5) on the way to (4, 6) is blocked
    assert lattice.edges[node] & north and lattice.edges[node] & west
    assert not lattice.edges[node[0], node[1] + 1] & west  # and the same run from the other end
