"""Hybrid A* (Dolgov, Thrun, Montemerlo, Diebel 2008; Stanford's Junior): the planner's search
in the vehicle's own state space, so what it finds is a path the vehicle can drive.

Nodes are continuous rear-axle poses (east, north, heading); the closed set bins them by a
square of ``cell_m`` and a heading bin, and a bin's first expansion closes it. Headings are kept
exact on the bins: every primitive is a forward arc of ``step_m`` turning a whole number of
heading bins (``turns``), at most one turning radius tight, so the successors of a heading are
a table of displacements computed once per search (plain floats in the loop, heapq).

A primitive is published as chords of at most ``_CHORD_M`` between points on its arc, and the
search checks exactly what `PathGate` will check of them: samples along each chord at the gate's
spacing, each with the gate's lower bound on the distance to lethal cell centres (the best of
the four surrounding centres) at least its clearance plus half that spacing, and the same bound
on its depth inside the corridor; both grown by the front corners' swing
(`brain.planning.swing`) of the tightest primitive among the step and those in the nose's
length behind it. A sample whose cell's centre is clear by a cell's half diagonal more passes
without the bound's arithmetic, and a step from a cell clear by its length and the swing at
full lock more needs no check at all. So every path returned
passes the gate (but for the nose at a stop, which the planner trims for), and its turns are the
arcs' (no pursuit needed).

A step costs its length x its cells' weight (the planner's: footprint cost and the room term
that keeps to the middle of gaps), plus ``steer_weight`` per metre at full lock and
``steer_change_weight`` per full-lock swing between steps. The heuristic is the larger of the
straight distance to the goal and a Dijkstra cost-to-go over coarse cells of
``heuristic_cell_m``, each weighing the least of its free fine cells in the vehicle's component
(optimistic, and it sees walls, their gaps and the costly cells round them), times
``heuristic_weight``. Every ``analytic_every`` expansions a Dubins curve
from the node to a goal pose (the goal segment's centre and the point level with the node,
heading along the course) is tried and taken if clear.

The goal is the free cells within half a step of the goal segment; when a labelling shows none
reachable, the reachable cells nearest it (as `brain.planning.search` aims, but a step and a bin
deep, so a step cannot jump them), and a path there is marked not reached. The first successor
in the goal ends the search. After ``max_expansions`` it returns the path to the expanded node
with the least cost-to-go, marked not reached.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from brain.grid import GridWindow
from brain.planning.dubins import dubins_points
from brain.planning.swing import FrontSwing, curvature_at
from brain.pose import Pose

FloatArray = NDArray[np.float64]

_CHORD_M = 0.5  # published points along a primitive: the planner's track spacing
_STEERING_FRACTIONS = (0.2, 0.6, 1.0)  # turns per step as fractions of the tightest, each side
_EPSILON_M = 1e-6  # the gate recomputes samples from the published points: rounding
_CURVATURE_ROUNDING = 1.001  # the gate's curvature from the published chords, against the arc's
_MIDDLE_WEIGHT = 0.01  # a blocked search's target: nearest the goal, then nearest its middle


@dataclass(frozen=True)
class HybridSettings:
    """The search's own numbers; the planner's config holds them (``PlannerConfig.hybrid``)."""

    step_m: float  # arc length of a motion primitive
    cell_m: float  # closed-set bin side
    heading_bins: int
    min_radius_m: float  # the vehicle's tightest turn
    steer_weight: float
    steer_change_weight: float
    heuristic_weight: float
    heuristic_cell_m: float
    analytic_every: int
    max_expansions: int

    @property
    def heading_step_rad(self) -> float:
        return math.tau / self.heading_bins

    def turns(self) -> tuple[int, ...]:
        """Heading bins turned per step, right to left: arcs no tighter than the radius."""
        tightest = math.floor(self.step_m / self.min_radius_m / self.heading_step_rad)
        if tightest < 1:
            raise ValueError("a step must be able to turn at least one heading bin")
        left = sorted({max(1, round(f * tightest)) for f in _STEERING_FRACTIONS})
        return (*(-t for t in reversed(left)), 0, *left)


@dataclass(frozen=True)
class Terrain:
    """One cycle's grid as the search sees it."""

    window: GridWindow
    clearance_m: NDArray[np.float32]  # HazardField.clearance_m: exact, padded by one ring of cells
    corridor_depth_m: FloatArray  # LocalCorridor.depth: how far inside the corridor each centre is
    free: NDArray[np.bool_]  # cells a passing point may lie in: the cost-to-go's and reachability's
    weight: FloatArray  # each cell's step cost per metre, >= 1
    required_m: float  # the gate's clearance plus its half sample spacing
    corridor_required_m: float  # the gate's corridor clearance plus its half sample spacing
    spacing_m: float  # the gate's sample spacing
    swing: FrontSwing  # the gate's allowance for the front corners on a turn


@dataclass(frozen=True)
class HybridResult:
    """The path (N x 2 rear-axle points from the start, chords <= 0.5 m; empty when the start is
    not clear), whether it reached the goal, and the expansions it took."""

    points: FloatArray
    reached_goal: bool
    expansions: int


def _flat(values: FloatArray) -> memoryview:
    """A float array as a flat buffer of Python-indexable floats: no copy into 90,000 float
    objects, and indexing is as fast as a list's."""
    return np.ascontiguousarray(values, dtype=float).ravel().data


class _Grid:
    """The terrain as flat buffers for the loop; cell indices into the window padded by one ring."""

    def __init__(self, terrain: Terrain, reach_m: float, most_swing_m: float) -> None:
        w = terrain.window
        self.east0, self.north0, self.res = w.origin_east_m, w.origin_north_m, w.resolution_m
        self.inv_res = 1.0 / w.resolution_m
        self.rows, self.cols, self.stride = w.rows, w.cols, w.cols + 2
        self.spacing = terrain.spacing_m
        # Room beyond both requirements at each centre: the least of two 1-Lipschitz fields (the
        # clearance to hazards, the depth inside the corridor), so one bound serves both.
        hazard_room = terrain.clearance_m.astype(float) - (terrain.required_m + _EPSILON_M)
        corridor_room = np.pad(terrain.corridor_depth_m, 1, constant_values=-np.inf) - (
            terrain.corridor_required_m + _EPSILON_M
        )
        room = np.minimum(hazard_room, corridor_room)
        self.room = _flat(room)
        self.weight = _flat(np.pad(terrain.weight, 1, constant_values=1.0))
        self.sure = w.resolution_m * math.sqrt(2.0) / 2.0  # no point of a cell is further from its centre
        # Cells from which every sample within the reach of any point in them passes, whatever
        # the turn, so a step from there needs no checks: the room at its centre beats the
        # swing at full lock by the reach and three half diagonals (sample to its centre, the
        # two centres, this point to its centre).
        deep = room >= reach_m + 3.0 * self.sure + most_swing_m
        self.deep = deep.ravel().tobytes()

    def index(self, east: float, north: float) -> int:
        """Padded index of the cell holding the point, -1 outside the window."""
        u = (east - self.east0) * self.inv_res
        v = (north - self.north0) * self.inv_res
        if not (0.0 <= u < self.cols and 0.0 <= v < self.rows):
            return -1
        return (int(v) + 1) * self.stride + int(u) + 1

    def clear(self, east: float, north: float, swing: float = 0.0) -> bool:
        """Whether a gate sample here passes with the requirements grown by ``swing``."""
        i = self.index(east, north)
        if i < 0:
            return False
        room = self.room[i] - swing
        if room >= self.sure:
            return True
        return room > -self.sure and self.bound_clear(east, north, swing)

    def bound_clear(self, east: float, north: float, swing: float) -> bool:
        """`HazardField.clearance_bound` (and its like for the corridor's depth) against the
        requirements grown by ``swing``, as the gate computes it."""
        u = (east - self.east0) * self.inv_res + 0.5
        v = (north - self.north0) * self.inv_res + 0.5
        col, row = math.floor(u), math.floor(v)
        fu, fv = u - col, v - row
        i = row * self.stride + col
        m, s, res = self.room, self.stride, self.res
        return (
            m[i] - swing >= res * math.hypot(fu, fv)
            or m[i + 1] - swing >= res * math.hypot(1.0 - fu, fv)
            or m[i + s] - swing >= res * math.hypot(fu, 1.0 - fv)
            or m[i + s + 1] - swing >= res * math.hypot(1.0 - fu, 1.0 - fv)
        )

    def chord_clear(self, a: tuple[float, float], b: tuple[float, float], swing: float) -> bool:
        """The gate's samples of the chord a -> b after a (b included), computed as it does."""
        de, dn = b[0] - a[0], b[1] - a[1]
        pieces = max(1, math.ceil(math.hypot(de, dn) / self.spacing - 1e-9))
        inner = ((a[0] + i / pieces * de, a[1] + i / pieces * dn) for i in range(1, pieces))
        return all(self.clear(e, n, swing) for e, n in inner) and self.clear(*b, swing)


@dataclass(frozen=True)
class _Motion:
    """Per heading bin and turn: the arc's end, its published points and the gate's samples on
    them (offsets from the start of the arc), for a search whose headings start at ``yaw0``.
    Each turn's arc is laid out once and rotated to every heading."""

    end: list[list[tuple[float, float]]]
    points: list[list[list[tuple[float, float]]]]
    samples_east: list[list[list[float]]]
    samples_north: list[list[list[float]]]

    @classmethod
    def build(cls, settings: HybridSettings, turns: tuple[int, ...], yaw0: float, spacing_m: float) -> _Motion:
        chords = math.ceil(settings.step_m / _CHORD_M - 1e-9)
        yaw = yaw0 + np.arange(settings.heading_bins) * settings.heading_step_rad
        cos, sin = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        points, samples_east, samples_north = [], [], []
        for turn in turns:
            arc = _arc(turn * settings.heading_step_rad, settings.step_m, chords)
            east, north = _rotated(arc[1:], cos, sin)
            points.append([list(zip(e, n, strict=True)) for e, n in zip(east, north, strict=True)])
            east, north = _rotated(_chord_samples(arc, spacing_m), cos, sin)
            samples_east.append(east)
            samples_north.append(north)
        by_heading = range(settings.heading_bins)
        return cls(
            [[arcs[k][-1] for arcs in points] for k in by_heading],
            [[arcs[k] for arcs in points] for k in by_heading],
            [[arcs[k] for arcs in samples_east] for k in by_heading],
            [[arcs[k] for arcs in samples_north] for k in by_heading],
        )


def _rotated(offsets: FloatArray, cos: FloatArray, sin: FloatArray) -> tuple[list[list[float]], list[list[float]]]:
    """``offsets`` (N x 2, heading 0) turned to each heading: east and north lists per heading."""
    east = offsets[:, 0] * cos - offsets[:, 1] * sin
    north = offsets[:, 0] * sin + offsets[:, 1] * cos
    return east.tolist(), north.tolist()


def _arc(turn: float, length: float, chords: int) -> FloatArray:
    """Points from the origin, heading east, splitting an arc of ``length`` turning by ``turn``
    into equal chords."""
    s = length * np.arange(chords + 1) / chords
    if turn == 0.0:
        return np.column_stack([s, np.zeros_like(s)])
    radius = length / turn
    return np.column_stack([radius * np.sin(s / radius), radius * (1.0 - np.cos(s / radius))])


def _chord_samples(arc: FloatArray, spacing_m: float) -> FloatArray:
    """The gate's samples along the chords of ``arc`` after its start, each chord's end included."""
    out = []
    for a, b in itertools.pairwise(arc):
        pieces = max(1, math.ceil(math.hypot(*(b - a)) / spacing_m - 1e-9))
        out.append(a + np.arange(1, pieces + 1)[:, None] / pieces * (b - a))
    return np.vstack(out)


class _Target:
    """Where the search goes: the free cells of the vehicle's component within half a step of
    the goal segment, or when a labelling shows there are none, the component's cells nearest
    it (within a step and a bin of the nearest); with the coarse cost-to-go to them."""

    def __init__(
        self, terrain: Terrain, settings: HybridSettings, start: Pose, goal_a: FloatArray, goal_b: FloatArray
    ) -> None:
        w = terrain.window
        self.a = (float(goal_a[0]), float(goal_a[1]))
        self.b = (float(goal_b[0]), float(goal_b[1]))
        self.east0, self.north0, self.inv_res, self.stride = (
            w.origin_east_m,
            w.origin_north_m,
            1.0 / w.resolution_m,
            w.cols + 2,
        )
        east, north = w.cell_centres()
        distance = _segment_distance(east, north, np.asarray(goal_a, float), np.asarray(goal_b, float))
        component = _component(terrain.free, w, start)
        goal = component & (distance <= settings.step_m / 2.0)
        self.blocked = not goal.any()
        if self.blocked:
            middle = (np.asarray(goal_a, float) + np.asarray(goal_b, float)) / 2.0
            shortfall = np.where(
                component, distance + _MIDDLE_WEIGHT * np.hypot(east - middle[0], north - middle[1]), np.inf
            )
            # As deep as a step and a bin, so a step towards it cannot jump it: the nose, which a
            # stop must leave clear, reaches further than that beyond the rear axle anyway.
            goal = shortfall <= shortfall.min() + settings.step_m + settings.cell_m
        self.goal = np.pad(goal, 1, constant_values=False).ravel().tobytes()
        self.coarse = _CostToGo(w, np.where(component, terrain.weight, np.inf), goal, settings.heuristic_cell_m)

    def reached(self, east: float, north: float) -> bool:
        """Whether the point (inside the window) lies in a goal cell."""
        col = int((east - self.east0) * self.inv_res)
        row = int((north - self.north0) * self.inv_res)
        return bool(self.goal[(row + 1) * self.stride + col + 1])

    def distance(self, east: float, north: float) -> float:
        """Straight distance to the goal segment (0 for a blocked search: its goal is cells)."""
        if self.blocked:
            return 0.0
        (ae, an), (be, bn) = self.a, self.b
        de, dn = be - ae, bn - an
        t = max(0.0, min(1.0, ((east - ae) * de + (north - an) * dn) / max(de * de + dn * dn, 1e-12)))
        return math.hypot(east - ae - t * de, north - an - t * dn)

    def cost_to_go(self, east: float, north: float) -> float:
        """The least cost still to come, about: the straight distance (every step weighs at least
        1) or the coarse cells' way round."""
        return max(self.distance(east, north), self.coarse.at(east, north))

    def poses(self, east: float, north: float, heading: float) -> list[Pose]:
        """Goal poses for an analytic expansion from (east, north): on the goal segment level
        with the node, and its middle; heading along the course. None for a blocked search."""
        if self.blocked:
            return []
        (ae, an), (be, bn) = self.a, self.b
        de, dn = be - ae, bn - an
        t = max(0.0, min(1.0, ((east - ae) * de + (north - an) * dn) / max(de * de + dn * dn, 1e-12)))
        return [Pose(ae + t * de, an + t * dn, heading), Pose((ae + be) / 2.0, (an + bn) / 2.0, heading)]


def _segment_distance(east: FloatArray, north: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    direction = b - a
    length2 = max(float(direction @ direction), 1e-12)
    t = np.clip(((east - a[0]) * direction[0] + (north - a[1]) * direction[1]) / length2, 0.0, 1.0)
    return np.hypot(east - a[0] - t * direction[0], north - a[1] - t * direction[1])


def _component(free: NDArray[np.bool_], window: GridWindow, start: Pose) -> NDArray[np.bool_]:
    """The free cells 8-connected to the start's cell (all free cells if that one is not free:
    the start may pass the exact test where the cell's centre-based margin does not)."""
    row, col = (int(v) for v in window.cell_of(start[0], start[1]))
    _, labels = cv2.connectedComponents(free.astype(np.uint8), connectivity=8)
    label = labels[row, col] if window.inside(row, col) else 0
    return labels == label if label else free.copy()


class _CostToGo:
    """Dijkstra from the target over coarse cells (8-connected), each weighted by the least step
    weight of its free cells (so it never overestimates), bilinear between their centres."""

    def __init__(self, window: GridWindow, weight: FloatArray, goal: NDArray[np.bool_], cell_m: float) -> None:
        factor = max(1, round(cell_m / window.resolution_m))
        self.east0, self.north0 = window.origin_east_m, window.origin_north_m
        self.size = factor * window.resolution_m
        coarse_weight, coarse_goal = _coarse_min(weight, factor), _coarse_min(np.where(goal, 0.0, np.inf), factor) == 0
        self.rows, self.cols = coarse_weight.shape
        self.values = _flat(_fill(_dijkstra(coarse_weight, coarse_goal, self.size), self.size))

    def at(self, east: float, north: float) -> float:
        u = (east - self.east0) / self.size - 0.5
        v = (north - self.north0) / self.size - 0.5
        col, row = math.floor(u), math.floor(v)
        fu, fv = u - col, v - row
        if 0 <= col < self.cols - 1 and 0 <= row < self.rows - 1:
            i, values = row * self.cols + col, self.values
            corners = (values[i], values[i + 1], values[i + self.cols], values[i + self.cols + 1])
            if math.isfinite(max(corners)):
                return (corners[0] * (1 - fu) + corners[1] * fu) * (1 - fv) + (
                    corners[2] * (1 - fu) + corners[3] * fu
                ) * fv
        own_col = min(max(round(u), 0), self.cols - 1)
        own_row = min(max(round(v), 0), self.rows - 1)
        return self.values[own_row * self.cols + own_col]


def _coarse_min(values: FloatArray, factor: int) -> FloatArray:
    """The least value in each block of ``factor`` x ``factor`` cells (inf pads the edges)."""
    rows, cols = -(-values.shape[0] // factor), -(-values.shape[1] // factor)
    padded = np.full((rows * factor, cols * factor), np.inf)
    padded[: values.shape[0], : values.shape[1]] = values
    return padded.reshape(rows, factor, cols, factor).min(axis=(1, 3))


def _dijkstra(weight: FloatArray, goal: NDArray[np.bool_], step_m: float) -> FloatArray:
    """Least cost from every cell to a goal cell, a step costing its length x the mean of its
    two cells' weights (inf weight: blocked; inf cost: unreachable)."""
    rows, cols = weight.shape
    stride = cols + 2
    weights = np.pad(weight, 1, constant_values=np.inf).ravel().tolist()
    cost = [math.inf] * len(weights)
    moves = [
        (dr * stride + dc, step_m * math.hypot(dr, dc) / 2.0) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc
    ]
    heap = [(0.0, int(i)) for i in np.flatnonzero(np.pad(goal & np.isfinite(weight), 1).ravel())]
    for _, i in heap:
        cost[i] = 0.0
    pop, push = heapq.heappop, heapq.heappush
    while heap:
        c, i = pop(heap)
        if c > cost[i]:
            continue
        here = weights[i]
        for offset, half_length in moves:
            j = i + offset
            step = c + half_length * (here + weights[j])
            if step < cost[j]:
                cost[j] = step
                push(heap, (step, j))
    return np.asarray(cost).reshape(rows + 2, cols + 2)[1:-1, 1:-1]


def _fill(values: FloatArray, step_m: float) -> FloatArray:
    """Unreached cells beside reached ones get the best neighbour plus a diagonal step, so
    interpolating next to a wall stays finite."""
    padded = np.pad(values, 1, constant_values=np.inf)
    rows, cols = values.shape
    near = np.min(
        [padded[1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols] for dr in (-1, 0, 1) for dc in (-1, 0, 1)], axis=0
    )
    return np.where(np.isfinite(values), values, near + step_m * math.sqrt(2.0))


class _Search:
    """One search's state: the nodes (parallel lists), the open heap and the closed bins."""

    def __init__(
        self, terrain: Terrain, settings: HybridSettings, start: Pose, target: _Target, goal_heading: float
    ) -> None:
        self.goal_heading = goal_heading
        self.settings = settings
        self.target = target
        self.turns = settings.turns()
        # Each primitive's front swing (indexed like turns), and how many primitives back the
        # nose reaches: a step's samples take the largest swing among it and those.
        self.swing_of = [
            terrain.swing.of(abs(turn) * settings.heading_step_rad / settings.step_m * _CURVATURE_ROUNDING) + _EPSILON_M
            for turn in self.turns
        ]
        self.swing = terrain.swing
        self.behind = math.ceil(terrain.swing.front_m / settings.step_m - 1e-9)
        self.grid = _Grid(terrain, settings.step_m, max(self.swing_of))
        self.motion = _Motion.build(settings, self.turns, start[2], terrain.spacing_m)
        self.start = start
        tightest = max(self.turns)
        self.radius = settings.step_m / (tightest * settings.heading_step_rad)
        # penalty[last][next]: steering held and steering swung, per step.
        self.penalty = [
            [
                settings.step_m * settings.steer_weight * abs(turn) / tightest
                + settings.steer_change_weight * abs(turn - last) / tightest
                for turn in self.turns
            ]
            for last in self.turns
        ]
        self.next_heading = [
            [(k + turn) % settings.heading_bins for turn in self.turns] for k in range(settings.heading_bins)
        ]
        w = terrain.window
        self.bin_cols = math.ceil(w.cols * w.resolution_m / settings.cell_m)
        bin_rows = math.ceil(w.rows * w.resolution_m / settings.cell_m)
        self.closed = bytearray(self.bin_cols * bin_rows * settings.heading_bins)
        self.best_g: dict[int, float] = {}
        self.east, self.north, self.cost, self.left = [start[0]], [start[1]], [0.0], [target.cost_to_go(*start[:2])]
        self.heading, self.turn, self.parent = [0], [self.turns.index(0)], [-1]
        self.key = [self.bin_of(start[0], start[1], 0)]

    def bin_of(self, east: float, north: float, heading: int) -> int:
        """The closed-set bin of a pose (inside the window)."""
        grid, s = self.grid, self.settings
        col = int((east - grid.east0) / s.cell_m)
        row = int((north - grid.north0) / s.cell_m)
        return (row * self.bin_cols + col) * s.heading_bins + heading

    def run(self) -> HybridResult:
        s, target = self.settings, self.target
        if not self.grid.clear(*self.start[:2]) or not math.isfinite(self.left[0]):
            return HybridResult(np.empty((0, 2)), False, 0)
        if target.reached(*self.start[:2]):
            return self.result(0, [], False, 0)
        heap = [(s.heuristic_weight * self.left[0], 0)]
        best, expansions = 0, 0
        while heap and expansions < s.max_expansions:
            _, node = heapq.heappop(heap)
            if self.closed[self.key[node]]:
                continue
            self.closed[self.key[node]] = 1
            expansions += 1
            if self.left[node] < self.left[best]:
                best = node
            if (expansions - 1) % s.analytic_every == 0:
                tail = self.analytic(node)
                if tail is not None:
                    return self.result(node, tail, True, expansions)
            arrived = self.expand(node, heap)
            if arrived >= 0:
                return self.result(arrived, [], not target.blocked, expansions)
        return self.result(best, [], False, expansions)

    def expand(self, node: int, heap: list[tuple[float, int]]) -> int:
        """Push every clear successor that is the cheapest yet to its bin; the first one in the
        goal ends the search at once (its index; else -1): in front of the goal the heuristic,
        blind to steering and optimistic about weights, leaves a wide band of nodes with
        about the goal's estimate to expand first. The loop's hot spot: locals, and the window
        test and bin inlined."""
        s, grid, motion = self.settings, self.grid, self.motion
        east, north, k, g = self.east[node], self.north[node], self.heading[node], self.cost[node]
        ends, mids, headings = motion.end[k], motion.points[k], self.next_heading[k]
        samples_east, samples_north = motion.samples_east[k], motion.samples_north[k]
        penalties = self.penalty[self.turn[node]]
        swing_of, recent = self.swing_of, self.recent_swing(node)
        e0, n0, inv, cols, rows, stride = grid.east0, grid.north0, grid.inv_res, grid.cols, grid.rows, grid.stride
        deep = grid.deep[(int((north - n0) * inv) + 1) * stride + int((east - e0) * inv) + 1]
        cell_m, bin_cols, bins, step_m, closed, best_g = (
            s.cell_m,
            self.bin_cols,
            s.heading_bins,
            s.step_m,
            self.closed,
            self.best_g,
        )
        for index, (de, dn) in enumerate(ends):
            e, n = east + de, north + dn
            u, v = (e - e0) * inv, (n - n0) * inv
            if not (0.0 <= u < cols and 0.0 <= v < rows):
                continue
            key = (int((n - n0) / cell_m) * bin_cols + int((e - e0) / cell_m)) * bins + headings[index]
            if closed[key]:
                continue
            known = best_g.get(key, math.inf)
            penalty = penalties[index]
            if g + step_m + penalty >= known or not (
                deep
                or self._samples_clear(
                    east, north, samples_east[index], samples_north[index], max(recent, swing_of[index])
                )
            ):
                continue
            me, mn = mids[index][0]
            middle = grid.weight[grid.index(east + me, north + mn)]
            cost = g + 0.5 * step_m * (middle + grid.weight[(int(v) + 1) * stride + int(u) + 1]) + penalty
            if cost >= known:
                continue
            left = self.target.cost_to_go(e, n)
            if not math.isfinite(left):
                continue
            best_g[key] = cost
            self.east.append(e)
            self.north.append(n)
            self.cost.append(cost)
            self.left.append(left)
            self.heading.append(headings[index])
            self.turn.append(index)
            self.parent.append(node)
            self.key.append(key)
            if self.target.reached(e, n):
                return len(self.key) - 1
            heapq.heappush(heap, (cost + s.heuristic_weight * left, len(self.key) - 1))
        return -1

    def recent_swing(self, node: int) -> float:
        """The largest swing among the primitives that end at ``node``, as far back as the nose."""
        swing = 0.0
        for _ in range(self.behind):
            if node <= 0:
                break
            swing = max(swing, self.swing_of[self.turn[node]])
            node = self.parent[node]
        return swing

    def _samples_clear(
        self, east: float, north: float, offsets_east: list[float], offsets_north: list[float], swing: float
    ) -> bool:
        """`_Grid.clear` for a primitive's samples, inlined."""
        grid = self.grid
        room, sure = grid.room, grid.sure
        e0, n0, inv, cols, rows, stride = grid.east0, grid.north0, grid.inv_res, grid.cols, grid.rows, grid.stride
        for de, dn in zip(offsets_east, offsets_north, strict=True):
            e, n = east + de, north + dn
            u, v = (e - e0) * inv, (n - n0) * inv
            if not (0.0 <= u < cols and 0.0 <= v < rows):
                return False
            r = room[(int(v) + 1) * stride + int(u) + 1] - swing
            if r >= sure:
                continue
            if r <= -sure or not grid.bound_clear(e, n, swing):
                return False
        return True

    def analytic(self, node: int) -> list[tuple[float, float]] | None:
        """Chord points of a clear Dubins curve from the node to a goal pose, or None."""
        heading = self.start.yaw_rad + self.heading[node] * self.settings.heading_step_rad
        pose = Pose(self.east[node], self.north[node], heading)
        for goal in self.target.poses(pose.east_m, pose.north_m, self.goal_heading):
            if self.grid.clear(goal.east_m, goal.north_m):
                tail = self._clear_curve(node, dubins_points(pose, goal, self.radius, _CHORD_M))
                if tail:
                    return tail
        return None

    def _clear_curve(self, node: int, points: Iterator[tuple[float, float]]) -> list[tuple[float, float]] | None:
        """The points after the first (the node's), if every chord between them is clear. Each
        chord's samples take the largest swing of the vertices within the nose behind its start,
        curvatures computed from the points as the gate will (`brain.planning.swing`), and of
        the node's own primitives while those are within the nose."""
        previous = next(points, None)
        if previous is None:
            return None
        before = self.point_before(node)
        history, front = self.recent_swing(node), self.swing.front_m
        vertices: deque[tuple[float, float]] = deque()  # (along the tail, swing) within the nose
        along, out = 0.0, []
        for point in points:
            if before is not None:
                vertices.append((along, self.vertex_swing(before, previous, point)))
            while vertices and vertices[0][0] < along - front:
                vertices.popleft()
            swing = max((swing for _along, swing in vertices), default=0.0)
            if along < front:
                swing = max(swing, history)
            if not self.grid.chord_clear(previous, point, swing):
                return None
            out.append(point)
            along += math.hypot(point[0] - previous[0], point[1] - previous[1])
            before, previous = previous, point
        return out

    def point_before(self, node: int) -> tuple[float, float] | None:
        """The published point before ``node``'s (None for the start: the gate sees no vertex there)."""
        if node <= 0:
            return None
        parent = self.parent[node]
        arc = self.motion.points[self.heading[parent]][self.turn[node]]
        de, dn = arc[-2] if len(arc) >= 2 else (0.0, 0.0)
        return self.east[parent] + de, self.north[parent] + dn

    def vertex_swing(self, a: tuple[float, float], b: tuple[float, float], c: tuple[float, float]) -> float:
        """The swing at vertex ``b`` of the polyline a-b-c, its curvature as the gate computes it."""
        return self.swing.of(curvature_at(a, b, c) * _CURVATURE_ROUNDING) + _EPSILON_M

    def result(self, node: int, tail: list[tuple[float, float]], reached: bool, expansions: int) -> HybridResult:
        """The published points from the start through ``node`` (and an analytic tail)."""
        chain = []
        while node > 0:
            chain.append(node)
            node = self.parent[node]
        points = [self.start[:2]]
        for child in reversed(chain):
            parent = self.parent[child]
            east, north = self.east[parent], self.north[parent]
            arc = self.motion.points[self.heading[parent]][self.turn[child]]
            points.extend((east + de, north + dn) for de, dn in arc[:-1])
            points.append((self.east[child], self.north[child]))
        points.extend(tail)
        return HybridResult(np.asarray(points, dtype=float).reshape(-1, 2), reached, expansions)


def hybrid_search(
    terrain: Terrain,
    settings: HybridSettings,
    start: Pose,
    goal_a: FloatArray,
    goal_b: FloatArray,
    goal_heading: float,
) -> HybridResult:
    """Hybrid A* from the rear-axle pose ``start`` to the goal segment ``goal_a``-``goal_b``,
    arriving along ``goal_heading`` (module docstring)."""
    target = _Target(terrain, settings, start, goal_a, goal_b)
    return _Search(terrain, settings, start, target, goal_heading).run()
