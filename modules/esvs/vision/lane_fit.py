"""Lane borders from the bird's-eye heat map: RANSAC parabolas, then Kratos' greedy extension.

1. The hot cells between ``fit_x_min_m`` and ``fit_x_max_m`` are candidate points. RANSAC draws
   triples of them (vectorised: all hypotheses at once) and fits y = c0 + c1 x + c2 x^2 exactly
   through each; implausible parabolas (steeper than ``max_slope`` or tighter than
   ``max_curvature``) are dropped before scoring, which with a few lines among many noise cells
   leaves mostly triples from one line. The parabola whose inliers (within ``inlier_m``) carry the
   most heat wins; weighted least-squares refits on its inliers (re-selected after each) follow.
2. A parabola is not a road, so from its farthest and nearest inlier a greedy search follows the
   heat cell by cell beyond (into the whole heat map, which reaches past the fit range), each step
   taking the hottest cell within ``search_cells`` of where the trail's own direction points,
   stopping after ``max_gap_cells`` cold steps. The trail joins the inliers; a final refit gives
   the border and its x range.
3. The border's cells are removed and the search repeats, up to ``max_borders`` times. A border
   whose cell rows hold evidence in less than ``min_coverage`` of its span is dropped, and so is
   one that is not clearly hotter than the ground ``flank_m`` beside it (``stands_out``): on
   ground covered in bright speckle any parabola finds evidence in most rows.

``side`` is +1 for a border left of the vehicle (y > 0 at its near end), -1 for right.
``confidence`` is the share of the border's cell rows that hold evidence, times
1 - exp(-rows / ``confidence_rows``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from modules.esvs.vision.lane_heat import HeatMap
from protocol.messages import LaneBorder


@dataclass(frozen=True)
class FitParams:
    hot: float = 0.4  # a cell this hot is evidence
    fit_x_min_m: float = 11.6  # RANSAC range (VEHICLE x): RASCAL's 10-35 m ahead of the cameras
    fit_x_max_m: float = 36.6
    iterations: int = 200  # plausible hypotheses scored...
    draws_per_iteration: int = 10  # ...out of this many times as many random triples
    min_spread_m: float = 4.0  # a triple must span this much x to define a parabola
    inlier_m: float = 0.2
    refits: int = 2  # least-squares refits, each on the inliers of the last
    max_slope: float = 1.0  # |dy/dx| anywhere in the fit range
    max_curvature: float = 0.01  # |c2| (1/m): a 50 m radius
    min_rows: int = 8  # a border needs evidence in this many cell rows (4 m at 0.5 m cells)...
    min_coverage: float = 0.6  # ...and in this share of the rows it spans...
    min_contrast: float = 2.0  # ...and be this many times more often hot than the ground beside it
    flank_m: float = 0.8  # where "beside" is
    max_borders: int = 4
    extend: bool = True  # greedy extension beyond the RANSAC inliers
    search_cells: int = 2
    max_gap_cells: int = 3
    confidence_rows: float = 12.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.iterations < 1 or self.min_rows < 3 or self.max_borders < 0 or self.inlier_m <= 0:
            raise ValueError("need iterations >= 1, min_rows >= 3, max_borders >= 0 and inlier_m > 0")
        if self.search_cells < 0 or self.max_gap_cells < 0:
            raise ValueError("search_cells and max_gap_cells must not be negative")


def fit_borders(heat: HeatMap, params: FitParams | None = None) -> tuple[LaneBorder, ...]:
    """Every border found in ``heat``, left to right (by y at the near end)."""
    params = params or FitParams()
    rng = np.random.default_rng(params.seed)
    hot = heat.heat >= params.hot
    rows, columns = np.nonzero(hot)
    xs, ys = heat.x_of(rows), heat.y_of(columns)
    weights = heat.heat[rows, columns].astype(np.float64)
    in_fit = (xs >= params.fit_x_min_m) & (xs <= params.fit_x_max_m)
    free = np.ones(xs.size, dtype=bool)
    borders = []
    for _ in range(params.max_borders):
        candidates = np.flatnonzero(free & in_fit)
        candidate_x, candidate_y = xs[candidates], ys[candidates]
        coefficients = ransac(candidate_x, candidate_y, weights[candidates], params, rng)
        if coefficients is None:
            break
        inliers = candidates[_near(candidate_x, candidate_y, coefficients, params.inlier_m)]
        if _count_rows(rows[inliers]) < params.min_rows:
            break
        for _ in range(params.refits):
            coefficients = _weighted_fit(xs[inliers], ys[inliers], weights[inliers])
            refined = candidates[_near(candidate_x, candidate_y, coefficients, params.inlier_m)]
            if _count_rows(rows[refined]) < params.min_rows:
                break
            inliers = refined
        if params.extend:
            trail_x, trail_y, trail_w = extend(heat, hot, rows[inliers], columns[inliers], params)
        else:
            trail_x = trail_y = trail_w = np.zeros(0)
        all_x = np.concatenate([xs[inliers], trail_x])
        all_y = np.concatenate([ys[inliers], trail_y])
        all_w = np.concatenate([weights[inliers], trail_w])
        coefficients = _weighted_fit(all_x, all_y, all_w)
        x_min, x_max = float(all_x.min()), float(all_x.max())
        # Everything this border explains is used up, trail included.
        near = _near(xs, ys, coefficients, 2 * params.inlier_m)
        free &= ~(near & (xs >= x_min - heat.params.cell_x_m) & (xs <= x_max + heat.params.cell_x_m))
        border = _border(coefficients, x_min, x_max, all_x, heat, params)
        if border is not None and stands_out(heat, hot, coefficients, x_min, x_max, params):
            borders.append(border)
    return tuple(sorted(borders, key=lambda b: -(b.c0_m + b.c1 * b.x_min_m + b.c2_per_m * b.x_min_m**2)))


def _near(xs: np.ndarray, ys: np.ndarray, coefficients: np.ndarray, distance: float) -> np.ndarray:
    """Whether each point is within ``distance`` (in y) of the parabola (Horner, as np.polyval)."""
    c2, c1, c0 = coefficients
    return np.abs(ys - ((c2 * xs + c1) * xs + c0)) < distance


def _count_rows(rows: np.ndarray) -> int:
    """How many distinct cell rows (non-negative) there are."""
    return int(np.count_nonzero(np.bincount(rows)))


def ransac(
    xs: np.ndarray, ys: np.ndarray, weights: np.ndarray, params: FitParams, rng: np.random.Generator
) -> np.ndarray | None:
    """(c2, c1, c0) of the plausible parabola through triples of points with the most inlier
    weight, or None if no triple gives a plausible one."""
    if xs.size < 3:
        return None
    # Most random triples of a noisy map make wild parabolas; draw many, solve them all (cheap),
    # and score only the first ``iterations`` plausible ones (scoring is the costly part).
    triples = rng.integers(0, xs.size, size=(params.iterations * params.draws_per_iteration, 3)).T
    (xa, xb, xc), (ya, yb, yc) = xs[triples], ys[triples]  # one contiguous row per vertex: fast ufuncs
    spread = np.maximum(np.maximum(xa, xb), xc) - np.minimum(np.minimum(xa, xb), xc)
    keep = (xa != xb) & (xb != xc) & (xa != xc) & (spread >= params.min_spread_m)
    if not keep.any():
        return None
    # Exact parabola through the three points (divided differences), centred on x0.
    x0 = (params.fit_x_min_m + params.fit_x_max_m) / 2
    xa, xb, xc, ya, yb, yc = xa[keep] - x0, xb[keep] - x0, xc[keep] - x0, ya[keep], yb[keep], yc[keep]
    slope_ab, slope_ac = (yb - ya) / (xb - xa), (yc - ya) / (xc - xa)
    a = (slope_ac - slope_ab) / (xc - xb)
    curved = np.abs(a) <= params.max_curvature  # c2 is a: the cheap test first, on every triple
    a, xa, xb, ya = a[curved], xa[curved], xb[curved], ya[curved]
    b = slope_ab[curved] - a * (xa + xb)
    coefficients = _uncentre(np.column_stack([a, b, ya - a * xa * xa - b * xa]), x0)
    plausible = np.ones(len(coefficients), dtype=bool)
    for edge in (params.fit_x_min_m, params.fit_x_max_m):
        plausible &= np.abs(2 * coefficients[:, 0] * edge + coefficients[:, 1]) <= params.max_slope
    if not plausible.any():
        return None
    coefficients = coefficients[plausible][: params.iterations]
    # Scoring in float32 halves the memory traffic of the (hypotheses x points) arrays.
    c2, c1, c0 = coefficients.astype(np.float32).T[:, :, None]
    x32, y32 = xs.astype(np.float32), ys.astype(np.float32)
    inside = np.abs((c2 * x32 + c1) * x32 + c0 - y32) < np.float32(params.inlier_m)
    support = inside @ weights.astype(np.float32)
    return coefficients[int(np.argmax(support))]


def extend(
    heat: HeatMap, hot: np.ndarray, rows: np.ndarray, columns: np.ndarray, params: FitParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Greedy trails beyond the far and the near end of a border's cells: x, y, heat of the
    cells taken."""
    taken: list[tuple[int, int]] = []
    for step in (1, -1):
        end_row = rows.max() if step > 0 else rows.min()
        # The trail starts from the mean column at the end row and the direction of the last rows.
        last = np.abs(rows - end_row) <= 3
        start = float(columns[rows == end_row].mean())
        slope = _slope(rows[last], columns[last])
        taken += _follow(heat.heat, hot, int(end_row), start, slope, step, params)
    if not taken:
        empty = np.zeros(0)
        return empty, empty, empty
    trail_rows, trail_columns = np.array(taken).T
    return heat.x_of(trail_rows), heat.y_of(trail_columns), heat.heat[trail_rows, trail_columns].astype(np.float64)


def _follow(
    heat: np.ndarray, hot: np.ndarray, row: int, column: float, slope: float, step: int, params: FitParams
) -> list[tuple[int, int]]:
    """Cells taken walking rows ``step`` (+1 far, -1 near) from (``row``, ``column``), with
    ``slope`` columns per row."""
    taken = []
    last_row, last_column = row, column
    while 0 <= row + step < heat.shape[0] and abs(row + step - last_row) <= params.max_gap_cells + 1:
        row += step
        centre = round(last_column + slope * (row - last_row))
        low, high = max(centre - params.search_cells, 0), min(centre + params.search_cells + 1, heat.shape[1])
        if low >= high:
            break
        found = low + int(np.argmax(heat[row, low:high]))
        if hot[row, found]:
            # The direction blends towards the trail's own last step.
            slope = 0.5 * slope + 0.5 * (found - last_column) / (row - last_row)
            last_row, last_column = row, float(found)
            taken.append((row, found))
    return taken


def _slope(rows: np.ndarray, columns: np.ndarray) -> float:
    """Columns per row of the points (least squares), 0 if they share one row."""
    du = rows - rows.mean()
    spread = float(du @ du)
    return float(du @ (columns - columns.mean())) / spread if spread > 0 else 0.0


def _weighted_fit(xs: np.ndarray, ys: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(c2, c1, c0) minimising sum(weights * residual^2), from the 3x3 normal equations in x
    centred on the weighted mean (np.polyfit's general machinery costs 5x more here)."""
    x0 = float(weights @ xs / weights.sum())
    u = xs - x0
    powers = np.vstack([np.ones_like(u), u, u * u])  # rows u^0, u^1, u^2
    weighted = powers * weights
    normal = weighted @ powers.T
    rhs = weighted @ ys
    c, b, a = np.linalg.solve(normal, rhs)
    return np.array([a, b - 2 * a * x0, c - b * x0 + a * x0 * x0])  # _uncentre of one


def _uncentre(local: np.ndarray, x0: float) -> np.ndarray:
    """(a, b, c) of a (x - x0)^2 + b (x - x0) + c  ->  (c2, c1, c0) in x."""
    a, b, c = local[:, 0], local[:, 1], local[:, 2]
    return np.stack([a, b - 2 * a * x0, c - b * x0 + a * x0 * x0], axis=-1)


def stands_out(
    heat: HeatMap, hot: np.ndarray, coefficients: np.ndarray, x_min: float, x_max: float, params: FitParams
) -> bool:
    """Whether the parabola is hotter than the ground beside it: over its rows, the share with a
    hot cell on it must be ``min_contrast`` times the share with one ``flank_m`` to its left, or
    to its right, whichever side is colder (a neighbouring line on one side is fine; evidence all
    over, as on dense noise, is not)."""
    rows = np.arange(
        max(0, math.floor((x_min - heat.params.x_min_m) / heat.params.cell_x_m)),
        min(hot.shape[0], math.ceil((x_max - heat.params.x_min_m) / heat.params.cell_x_m) + 1),
    )
    centre = heat.column_of(np.polyval(coefficients, heat.x_of(rows)))
    flank = params.flank_m / heat.params.cell_y_m
    shares = []
    for offset in (0.0, -flank, flank):
        columns = np.rint(centre + offset).astype(np.int64)[:, None] + np.arange(-1, 2)
        inside = (columns >= 0) & (columns < hot.shape[1])
        lit = hot[rows[:, None], np.clip(columns, 0, hot.shape[1] - 1)] & inside
        shares.append(float(lit.any(axis=1).mean()) if rows.size else 0.0)
    return shares[0] >= params.min_contrast * min(shares[1], shares[2]) and shares[0] > 0


def _border(
    coefficients: np.ndarray, x_min: float, x_max: float, xs: np.ndarray, heat: HeatMap, params: FitParams
) -> LaneBorder | None:
    """The descriptor, or None when too few of the rows spanned hold evidence (scattered noise
    that happens to line up)."""
    c2, c1, c0 = (float(c) for c in coefficients)
    cell = heat.params.cell_x_m
    span_rows = round((x_max - x_min) / cell) + 1
    rows_with_evidence = np.unique(np.rint((xs - x_min) / cell)).size
    coverage = min(rows_with_evidence / span_rows, 1.0)
    if coverage < params.min_coverage:
        return None
    confidence = coverage * (1.0 - math.exp(-rows_with_evidence / params.confidence_rows))
    side = 1 if c0 + c1 * x_min + c2 * x_min * x_min > 0 else -1
    return LaneBorder(side, c0, c1, c2, x_min, x_max, confidence)
