"""RASCAL's re-plan: swerve candidates generated from the vehicle's speed, scored, gated.

When the current path meets a hazard, candidates leave it as lateral offsets in the corridor
frame: a quintic blend to an offset, a level stretch past the conflict, and a blend of the same
length back to the centre line. Blend lengths are seconds of travel at the current speed, so a
fast vehicle swerves gently and a slow one sharply (and also at the course's speed there, so a
vehicle slowed below it has swerves gentle enough to speed up through). A late variant keeps the current path until
just before the conflict. Everything is evaluated at once as (candidates x stations) arrays at
the published point spacing, against a raster of the hazard clearance across the corridor at
each station: candidates through a lethal cell there are dropped, and so are swerves sharper
than the vehicle turns (it would overshoot them towards the corridor's edge); the rest are scored
(footprint cost integral + offset + change from the current path + squared slope + the time
to drive it under the speed caps it will get: a sharp swerve, or one that shaves an obstacle,
is slow), and the
cheapest go through the full `PathGate` in order until one passes; those with room to spare
first, then tight ones, each within a budget of checks. Failing all, the candidate clear
furthest may be cut short of its hazard (a partial path, which the planner ends in a stop).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from brain.planning.checks import PathGate
from brain.planning.config import PlannerConfig
from brain.planning.frame import CorridorFrame
from brain.planning.profile import LateralProfile, blend_value, swerve
from brain.planning.speed import clearance_cap, reachable, travel_time_s

FloatArray = NDArray[np.float64]

# Full checks per cycle at most (the scored order makes the first few the likely winners): of
# candidates with room to spare, of tight ones (near misses, mostly), of ones clear part of the way.
_MAX_GATED = 16
_MAX_TIGHT = 6
_MAX_PARTIAL = 6
_RASTER_STEP_M = 0.1  # lateral spacing of the cross-section raster
_RASTER_MAX_COLUMNS = 240  # wider corridors get a coarser raster
_GAP_DEPTH_M = 4.0  # gaps are looked for from the conflict to a vehicle length and this much beyond


@dataclass(frozen=True)
class Choice:
    """The chosen candidate (None when none passed) and how many there were at each stage.

    ``partial`` marks a candidate clear only for part of the horizon: its points stop short of
    the first hazard (the path then ends in a stop), a way to keep moving towards a hazard far
    ahead that no single swerve passes, and to try again as it comes closer.
    """

    profile: LateralProfile | None
    points: FloatArray | None  # the published polyline (N x 2) of the chosen profile
    stations_m: FloatArray | None
    generated: int
    clear: int
    gated: int
    partial: bool = False


def stations(start_m: float, end_m: float, spacing_m: float) -> FloatArray:
    """The vehicle's station, every multiple of the spacing after it, and the end (the lattice of
    multiples keeps a kept path's points where they were)."""
    inner = np.arange(math.floor(start_m / spacing_m) + 1, math.ceil(end_m / spacing_m)) * spacing_m
    inner = inner[(inner > start_m + 1e-6) & (inner < end_m - 1e-6)]
    return np.concatenate([[start_m], inner, [end_m]]) if end_m > start_m else np.array([start_m])


def choose(
    frame: CorridorFrame,
    gate: PathGate,
    config: PlannerConfig,
    base: LateralProfile,
    s_start_m: float,
    s_end_m: float,
    conflict_m: float,
    speed_mps: float,
    late_start: bool,
    min_length_m: float,
) -> Choice:
    """The cheapest candidate that passes the gate, from ``base`` at ``s_start_m`` to ``s_end_m``;
    failing that, the one clear furthest (at least ``min_length_m``), cut short of its hazard.

    ``conflict_m`` is the station where the current path first fails; ``late_start`` allows
    candidates that follow ``base`` until just before it. A path through to ``s_end_m`` only
    stops there (and needs its nose clear beyond) when that is the end of the course.
    """
    stops_at_end = s_end_m >= frame.length_m - 1e-6
    s = stations(s_start_m, s_end_m, config.point_spacing_m)
    params = _parameters(frame, gate, config, base, s, conflict_m, speed_mps, late_start)
    begin, offset, length, back = (params[:, i : i + 1] for i in range(4))
    d = _evaluate(base, s, begin, offset, length, back)
    raster = _CrossSections(frame, gate, s, float(d.min()), float(d.max()))
    # The published points are samples of the full check too, so this only drops near-sure failures.
    clearance = raster.clearance(d)
    ok = clearance >= gate.clearance_m
    clear_upto = np.where(ok.all(axis=1), len(s), np.argmin(ok, axis=1))  # leading clear stations
    generated = len(params)
    need = int(np.searchsorted(s - s[0], min_length_m)) + 1  # stations a partial path must keep
    index = np.flatnonzero(clear_upto >= min(need, len(s)))
    if len(index) == 0:
        return Choice(None, None, None, generated, 0, 0)
    weight = _trapezoid_weights(s)
    base_d = base.at(s)[0]
    # A swerve sharper than the vehicle can turn is not a path it can follow: it would cut or
    # overshoot it (a 4 m offset over a 4 m blend asks for a 0.7 m radius; the vehicle turns 2.3 m).
    kappa = _curvature(frame, config, s, d[index])
    drivable = kappa.max(axis=1, initial=0.0) <= 1.0 / config.turning_radius_m
    index, kappa = index[drivable], kappa[drivable]
    if len(index) == 0:
        return Choice(None, None, None, generated, 0, 0)
    cost = raster.cost(d[index])
    caps = _speed_caps(frame, config, s, kappa, clearance[index], cost)
    along = s - s[0]
    start = max(speed_mps, config.start_speed_mps)
    speeds = reachable(along, caps, start, np.inf, config.max_accel_mps2, config.max_decel_mps2)
    score = (
        config.cost_weight * (cost @ weight)
        + config.offset_weight * (np.abs(d[index]) @ weight)
        + config.change_weight * (np.abs(d[index] - base_d) @ weight)
        + config.slope_weight * ((np.diff(d[index], axis=1) ** 2 / np.diff(s)).sum(axis=1) if len(s) > 1 else 0.0)
        + config.time_weight * travel_time_s(along, speeds)
    )
    # Candidates the frame cannot vouch for are tried last, not dropped: the corridor is a union
    # of capsules, wider than the frame's band at the outside of corners.
    room = frame.sure_half_width_at(s) - gate.corridor_clearance_m - config.check_spacing_m / 2
    unsure = np.any(np.abs(d[index]) > room, axis=1)
    # So are those that pass hazards within half a point spacing at a point: between two points
    # the full check may find them closer.
    tight = np.min(clearance[index], axis=1) < gate.clearance_m + config.point_spacing_m / 2
    full = clear_upto[index] == len(s)
    order = np.lexsort((score, tight, unsure))
    roomy = order[full[order] & ~tight[order]][:_MAX_GATED]
    cramped = order[full[order] & tight[order]][:_MAX_TIGHT]
    gated = 0
    for i in index[np.concatenate([roomy, cramped])]:
        gated += 1
        begin_m, offset_m, transition_m, return_m = params[i].tolist()
        profile = swerve(base, begin_m, offset_m, transition_m, return_m)
        points = np.column_stack(frame.to_enu(s, profile.at(s)[0]))
        if gate.check(points, nose=stops_at_end).ok:
            return Choice(profile, points, s, generated, int(full.sum()), gated)
    # Longest clear stretch first, then as above.
    for i in index[np.lexsort((score, unsure, -clear_upto[index]))][:_MAX_PARTIAL]:
        gated += 1
        begin_m, offset_m, transition_m, return_m = params[i].tolist()
        profile = swerve(base, begin_m, offset_m, transition_m, return_m)
        # Stop a turning radius and a nose short of the conflict: room to turn away towards the
        # way past it, which a vehicle that cannot reverse needs once it stands there.
        keep = int(clear_upto[i])
        if keep < len(s):
            keep = int(np.searchsorted(s, s[keep] - gate.nose_m - config.turning_radius_m, side="right"))
        points = np.column_stack(frame.to_enu(s[:keep], profile.at(s[:keep])[0]))
        cut = _clear_prefix(gate, points, min_length_m)
        if cut is not None:
            return Choice(profile, points[:cut], s[:cut], generated, int(full.sum()), gated, partial=True)
    return Choice(None, None, None, generated, int(full.sum()), gated)


def _curvature(frame: CorridorFrame, config: PlannerConfig, s: FloatArray, d: FloatArray) -> FloatArray:
    """Each candidate's curvature magnitude at each station (candidates x stations), estimated in
    the frame: that of the centre line plus that of the offset, averaged over the curvature window
    as the published path's is. Zero with fewer than three stations."""
    if len(s) < 3:
        return np.zeros(d.shape)
    bend = np.gradient(np.unwrap(frame.heading_at(s)), s)
    kappa = np.abs(bend + np.gradient(np.gradient(d, s, axis=1), s, axis=1))
    width = max(1, round(config.curvature_window_m / config.point_spacing_m)) | 1
    return cv2.blur(kappa.astype(np.float32), (width, 1), borderType=cv2.BORDER_REPLICATE).astype(float)


def _speed_caps(
    frame: CorridorFrame,
    config: PlannerConfig,
    s: FloatArray,
    kappa: FloatArray,
    clearance: FloatArray,
    cost: FloatArray,
) -> FloatArray:
    """The speed caps the planner will put on each candidate (candidates x stations): the
    course's speed slowed by the footprint cost, the lateral acceleration in the curvature
    ``kappa`` (`_curvature`), and the clearance to hazards."""
    course = frame.speed_at(s) / (1.0 + config.cost_speed_gain * cost)
    with np.errstate(divide="ignore"):
        turn = np.sqrt(config.max_lateral_accel_mps2 / kappa)
    near = clearance_cap(
        clearance, config.clearance_m, config.near_hazard_speed_mps, config.hazard_speed_gain_mps_per_m
    )
    return np.minimum.reduce([course, turn, near])


def _clear_prefix(gate: PathGate, points: FloatArray, min_length_m: float) -> int | None:
    """How many leading points pass the gate (stopping at the last, nose included), if they
    reach ``min_length_m``; a failure is cut off with a nose length to spare, twice at most."""
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(points, axis=0).T))])
    count = len(points)
    for _ in range(3):
        if count < 2 or along[count - 1] < min_length_m:
            return None
        verdict = gate.check(points[:count])
        if verdict.ok:
            return count
        count = int(np.searchsorted(along, verdict.first_failure_m - gate.nose_m, side="left"))
    return None


class _CrossSections:
    """Hazard clearance and footprint cost sampled across the corridor at each station.

    Candidates differ only in their offsets at the same stations, so one raster of cross-sections
    replaces a map lookup per candidate point. Offsets in between take the better of the two
    raster neighbours' clearance minus the lateral gap (the distance is 1-Lipschitz and the frame
    maps a lateral step of x to a point x away), a lower bound that loses at most half a raster step.
    """

    def __init__(self, frame: CorridorFrame, gate: PathGate, s: FloatArray, low_m: float, high_m: float) -> None:
        span = max(high_m - low_m, 0.0)
        self.step = max(_RASTER_STEP_M, span / _RASTER_MAX_COLUMNS)
        self.low = low_m
        self.count = max(2, math.ceil(span / self.step - 1e-9) + 1)
        lateral = low_m + self.step * np.arange(self.count)
        east, north = frame.cross_sections(s, lateral)
        self._clearance = gate.hazards.clearance_bound(east, north)
        self._cost = gate.hazards.cost_at(east, north)
        self._rows = np.arange(len(s))

    def clearance(self, d: FloatArray) -> FloatArray:
        """Lower bounds on the clearance at offsets ``d`` (candidates x stations)."""
        u = (d - self.low) / self.step
        left = np.clip(np.floor(u).astype(np.intp), 0, self.count - 2)
        from_left = self._clearance[self._rows, left] - np.abs(u - left) * self.step
        from_right = self._clearance[self._rows, left + 1] - np.abs(u - left - 1) * self.step
        return np.maximum(from_left, from_right)

    def cost(self, d: FloatArray) -> FloatArray:
        """Footprint-mean cost at the raster offset nearest ``d``."""
        nearest = np.clip(np.rint((d - self.low) / self.step).astype(np.intp), 0, self.count - 1)
        return self._cost[self._rows, nearest]


def _gap_offsets(frame: CorridorFrame, gate: PathGate, config: PlannerConfig, conflict_m: float) -> FloatArray:
    """Offsets through the middle of each gap across the corridor where the current path fails.

    A hazard that leaves a gap barely wider than the vehicle's clearance (a wash across the road
    with a strip at each side) is passed only by an offset close to the gap's middle, which the
    regular offset step may straddle. Across the stretch from the conflict to a vehicle length and
    a few metres on, each offset's margin is the least of its clearance to lethal cells and to the
    corridor's edge beyond what the gate asks; every run of offsets with a positive margin gives
    the offset of its best margin."""
    s = np.arange(conflict_m, conflict_m + config.vehicle.length_m + _GAP_DEPTH_M, config.check_spacing_m)
    s = s[s <= frame.length_m]
    if len(s) == 0 or config.max_gap_offsets == 0:
        return np.zeros(0)
    slack = config.check_spacing_m / 2.0
    reach = float(np.min(frame.sure_half_width_at(s))) - gate.corridor_clearance_m - slack
    if reach <= 0.0:
        return np.zeros(0)
    lateral = np.arange(-reach, reach + _RASTER_STEP_M / 2, _RASTER_STEP_M)
    east, north = frame.cross_sections(s, lateral)
    margin = np.minimum(
        gate.hazards.clearance_bound(east, north).min(axis=0) - gate.clearance_m - slack, reach - np.abs(lateral)
    )
    open_ = margin > 0.0
    edges = np.flatnonzero(np.diff(np.concatenate([[0], open_.astype(np.int8), [0]])))
    best = [start + int(np.argmax(margin[start:end])) for start, end in zip(edges[::2], edges[1::2], strict=True)]
    best.sort(key=lambda i: -margin[i])
    return lateral[best[: config.max_gap_offsets]]


def _parameters(
    frame: CorridorFrame,
    gate: PathGate,
    config: PlannerConfig,
    base: LateralProfile,
    s: FloatArray,
    conflict_m: float,
    speed_mps: float,
    late_start: bool,
) -> FloatArray:
    """Rows of (begin station, offset, transition length, return station)."""
    # The gate wants half a check spacing more than the clearance at its samples.
    room = float(np.max(frame.half_width_at(s))) - config.corridor_clearance_m - config.check_spacing_m / 2
    reach = max(room, 0.0)
    step = max(config.offset_step_m, 2.0 * reach / max(config.max_offsets - 1, 1))
    count = math.floor(reach / step + 1e-9)
    offsets = np.union1d(step * np.arange(-count, count + 1), _gap_offsets(frame, gate, config, conflict_m))
    # Seconds of travel at the current speed, and at the course's speed here: a vehicle slowed
    # below it also gets swerves gentle enough to speed up through.
    course_mps = max(float(frame.speed_at(s[0])), speed_mps)
    times = np.asarray(config.transition_times_s)
    lengths = np.unique(
        np.clip(
            np.concatenate([times * speed_mps, times * course_mps]), config.min_transition_m, config.max_transition_m
        )
    )
    start = float(s[0])
    # (begin, length, return) of each swerve shape; every shape goes to every offset
    shapes: list[tuple[float, float, float]] = []
    for length in lengths:
        begins = [start]
        late = conflict_m - config.lead_m - length
        if late_start and late > start + config.point_spacing_m:
            begins.append(late)
        for begin in begins:
            returns = {max(conflict_m + hold, begin + length) for hold in config.hold_after_conflict_m}
            returns.add(max(float(s[-1]), begin + length))  # no return within the horizon
            shapes.extend((begin, length, back) for back in sorted(returns))
    shape = np.repeat(np.asarray(shapes, dtype=float), len(offsets), axis=0)
    return np.column_stack([shape[:, 0], np.tile(offsets, len(shapes)), shape[:, 1], shape[:, 2]])


def _evaluate(
    base: LateralProfile,
    s: FloatArray,
    begin: FloatArray,
    offset: FloatArray,
    length: FloatArray,
    back: FloatArray,
) -> FloatArray:
    """d(s) of every candidate (rows) at every station (columns), as `swerve` builds them."""
    base_d = base.at(s)[0]
    start_d, start_slope = base.at(begin)
    x_in = s - begin
    x_out = s - back
    d_in = blend_value(x_in, length, start_d, start_slope, offset)
    d_out = blend_value(x_out, length, offset, 0.0, 0.0)
    before = x_in < 0.0
    rising = x_in < length
    level = x_out < 0.0
    return np.select([before, rising, level], [np.broadcast_to(base_d, d_in.shape), d_in, offset], d_out)


def _trapezoid_weights(s: FloatArray) -> FloatArray:
    """Integration weights of samples at stations ``s`` (trapezoid rule)."""
    if len(s) < 2:
        return np.ones(len(s))
    gap = np.diff(s)
    return np.concatenate([[gap[0] / 2], (gap[:-1] + gap[1:]) / 2, [gap[-1] / 2]])
