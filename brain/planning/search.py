"""Kratos' fallback search: A* over a footprint-cost grid, 8-connected, with a binary heap.

The graph is a lattice of every ``stride``-th cell of the grid window, aligned so the vehicle's
cell is a node. An edge joins 8-neighbouring nodes when every fine cell on the straight run
between them is free (clear of lethal cells by the clearance plus slack, and inside the corridor
mask), so a lattice path is a fine-grid path and needs no re-check. A stride of k searches
1/k^2 of the nodes and still finds every free channel about k cells wide; the planner searches
finer lattices, down to every cell, when a labelling shows a channel the coarse one missed.
Edge validity, node weights and the heuristic are numpy arrays computed before the loop; the
loop itself is plain Python over flat lists, which is what heapq is fast with.

A step costs its length times (1 + weight x footprint-mean cost) at the node it enters, the path
length plus the summed footprint costs as in Kratos. The heuristic is the straight distance to
the goal set times ``heuristic_weight``: the planner makes that the cost per metre of unseen
cells (Kratos' choice) times an inflation, which overestimates on cells seen clear and so is
not admissible, trading a slightly longer path (smoothed afterwards) for far fewer expansions.

A connected-component labelling of the free nodes (cv2, in C) answers first whether any goal
node is reachable at all; if none is, the goal becomes the reachable node nearest the goal set,
so the search does not flood the whole window to find out.
"""

from __future__ import annotations

import functools
import heapq
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

# (d_row, d_col) of the 8 neighbours; bit i of a node's edge mask allows step i.
STEPS = ((0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1), (-1, 0), (-1, 1))


@dataclass(frozen=True)
class SearchResult:
    """Fine-grid (row, col) cells from the start to the end of the path; empty when the start
    is blocked. ``reached_goal`` is False when the path ends at the reachable node nearest the goal."""

    cells: NDArray[np.intp]  # (N, 2)
    reached_goal: bool
    expansions: int


@dataclass(frozen=True)
class Lattice:
    """Every ``stride``-th cell from ``offset``: the search graph over one cycle's free mask."""

    stride: int
    offset: tuple[int, int]
    shape: tuple[int, int]
    free: NDArray[np.bool_]  # lattice-shaped
    edges: NDArray[np.uint8]  # lattice-shaped bit masks over STEPS

    @classmethod
    def build(cls, free_cells: NDArray[np.bool_], stride: int, anchor: tuple[int, int]) -> Lattice:
        """The lattice through ``anchor`` (a fine cell) over the fine free mask."""
        if stride < 1:
            raise ValueError("the lattice stride must be at least 1")
        offset = (anchor[0] % stride, anchor[1] % stride)
        free = free_cells[offset[0] :: stride, offset[1] :: stride]
        shape = free.shape
        edges = np.zeros(shape, dtype=np.uint8)
        for bit, (dr, dc) in enumerate(STEPS[:4]):
            # run[r, c]: every fine cell from (r, c) to (r + stride*dr, c + stride*dc) is free.
            run = _runs_free(free_cells, dr, dc, stride)
            forward = run[offset[0] :: stride, offset[1] :: stride][: shape[0], : shape[1]]
            edges |= forward.astype(np.uint8) << bit
            # The reverse step from the far node uses the same run.
            reverse = np.zeros(shape, dtype=bool)
            src_r = slice(max(0, -dr), shape[0] - max(0, dr))
            src_c = slice(max(0, -dc), shape[1] - max(0, dc))
            dst_r = slice(max(0, dr), shape[0] - max(0, -dr))
            dst_c = slice(max(0, dc), shape[1] - max(0, -dc))
            reverse[dst_r, dst_c] = forward[src_r, src_c]
            edges |= reverse.astype(np.uint8) << (bit + 4)
        return cls(stride, offset, shape, free, edges)

    def node_of(self, cell: tuple[int, int]) -> tuple[int, int]:
        return (cell[0] - self.offset[0]) // self.stride, (cell[1] - self.offset[1]) // self.stride

    def cells_of(self, nodes: NDArray[np.intp]) -> NDArray[np.intp]:
        """Fine (row, col) of lattice (i, j) nodes, N x 2."""
        return nodes * self.stride + np.asarray(self.offset)

    def node_centres(self) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """Fine rows and columns of every node, lattice-shaped."""
        i, j = np.mgrid[0 : self.shape[0], 0 : self.shape[1]]
        return i * self.stride + self.offset[0], j * self.stride + self.offset[1]


def search(
    lattice: Lattice,
    start: tuple[int, int],
    goal: NDArray[np.bool_],
    goal_distance_m: NDArray[np.float64],
    step_weight: NDArray[np.float64],
    resolution_m: float,
    heuristic_weight: float = 1.0,
    shortfall_m: NDArray[np.float64] | None = None,
) -> SearchResult:
    """A* on ``lattice`` from the node ``start`` (i, j) to any node in ``goal``.

    ``goal_distance_m`` is each node's straight distance to the goal set, ``step_weight`` each
    node's cost multiplier (>= 1), both lattice-shaped. When no goal node is reachable, the path
    ends at the reachable node with the least ``shortfall_m`` (default: the goal distance).
    """
    rows, cols = lattice.shape
    if not (0 <= start[0] < rows and 0 <= start[1] < cols) or not lattice.free[start]:
        return SearchResult(np.empty((0, 2), dtype=np.intp), False, 0)
    reach_goal = goal & lattice.free
    labels = _components(lattice.free)
    mine = labels == labels[start]
    if reach_goal[mine].any():
        target = reach_goal
        distance = goal_distance_m
    else:
        # No goal node connects to the start: aim for the reachable node nearest the goal instead.
        rank = goal_distance_m if shortfall_m is None else shortfall_m
        flat = np.where(mine, rank, np.inf).ravel()
        nearest = int(np.argmin(flat))
        target = np.zeros(lattice.shape, dtype=bool)
        target.flat[nearest] = True
        i, j = np.mgrid[0:rows, 0:cols]
        distance = np.hypot(i - nearest // cols, j - nearest % cols) * (lattice.stride * resolution_m)
    nodes, reached, expansions = _astar(
        lattice, start, target, distance * heuristic_weight, step_weight, resolution_m * lattice.stride
    )
    reached_goal = reached and bool(reach_goal.flat[nodes[-1]])
    pairs = np.column_stack([np.asarray(nodes) // cols, np.asarray(nodes) % cols])
    return SearchResult(lattice.cells_of(pairs), reached_goal, expansions)


def _astar(
    lattice: Lattice,
    start: tuple[int, int],
    target: NDArray[np.bool_],
    heuristic_m: NDArray[np.float64],
    step_weight: NDArray[np.float64],
    step_m: float,
) -> tuple[list[int], bool, int]:
    """Flat-index A*; returns the node path, whether a target was reached, and the expansions.
    Without reaching one, the path leads to the expanded node with the smallest heuristic."""
    cols = lattice.shape[1]
    edges = lattice.edges.ravel().tolist()
    heuristic = heuristic_m.ravel().tolist()
    weight = step_weight.ravel().tolist()
    is_target = target.ravel().tolist()
    moves_by_mask = _moves(cols, step_m)
    size = len(edges)
    best_g = [math.inf] * size
    parent = [-1] * size
    closed = bytearray(size)
    origin = start[0] * cols + start[1]
    best_g[origin] = 0.0
    heap = [(heuristic[origin], 0.0, origin)]
    nearest, nearest_h = origin, heuristic[origin]
    expansions = 0
    found = -1
    pop, push = heapq.heappop, heapq.heappush
    while heap:
        _, g, node = pop(heap)
        if closed[node]:
            continue
        closed[node] = 1
        expansions += 1
        if is_target[node]:
            found = node
            break
        if heuristic[node] < nearest_h:
            nearest, nearest_h = node, heuristic[node]
        for offset, length in moves_by_mask[edges[node]]:
            nxt = node + offset
            if closed[nxt]:
                continue
            cost = g + length * weight[nxt]
            if cost < best_g[nxt]:
                best_g[nxt] = cost
                parent[nxt] = node
                push(heap, (cost + heuristic[nxt], cost, nxt))
    end = found if found >= 0 else nearest
    path = [end]
    while parent[path[-1]] >= 0:
        path.append(parent[path[-1]])
    path.reverse()
    return path, found >= 0, expansions


@functools.lru_cache(maxsize=8)
def _moves(cols: int, step_m: float) -> list[list[tuple[int, float]]]:
    """For each of the 256 edge masks, the (flat offset, length) of the steps it allows."""
    steps = [(dr * cols + dc, step_m * math.hypot(dr, dc)) for dr, dc in STEPS]
    return [[steps[bit] for bit in range(8) if mask >> bit & 1] for mask in range(256)]


def _runs_free(free: NDArray[np.bool_], dr: int, dc: int, stride: int) -> NDArray[np.bool_]:
    """run[r, c]: cells (r + t*dr, c + t*dc) are free for t = 0..stride (False past the edge)."""
    rows, cols = free.shape
    run = free.copy()
    for t in range(1, stride + 1):
        shifted = np.zeros_like(free)
        r_dst = slice(max(0, -t * dr), rows - max(0, t * dr))
        c_dst = slice(max(0, -t * dc), cols - max(0, t * dc))
        r_src = slice(max(0, t * dr), rows - max(0, -t * dr))
        c_src = slice(max(0, t * dc), cols - max(0, -t * dc))
        shifted[r_dst, c_dst] = free[r_src, c_src]
        run &= shifted
    return run


def _components(free: NDArray[np.bool_]) -> NDArray[np.int32]:
    """8-connected labels of the free nodes (0 for blocked ones)."""
    _, labels = cv2.connectedComponents(free.astype(np.uint8), connectivity=8)
    return np.asarray(labels, dtype=np.int32)
