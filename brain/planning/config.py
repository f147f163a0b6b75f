"""The planner's settings, with units in the names. The vehicle it plans for (footprint and
steering) is its ``vehicle`` section, the same VehicleGeometry the simulator and control hold
(brain/vehicle.py), set for all three by a deployment's ``[vehicle]`` table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from brain.planning.hybrid import HybridSettings
from brain.planning.pursuit import Bicycle
from brain.planning.swing import FrontSwing
from brain.vehicle import VehicleGeometry
from rascal.runtime.config import section, setting

SEARCH_METHODS = ("hybrid", "lattice")


@dataclass(frozen=True)
class PlannerConfig:
    """Everything the planner can be tuned by. Validated on construction: bad values raise ValueError."""

    vehicle: VehicleGeometry = section(VehicleGeometry, "the vehicle planned for: footprint and steering")
    # What the margins are for: the INS errs across the track, 3-8 cm RMS and up to 0.16 m, against
    # the exact corridor edge. Hazards are mapped in the INS's own frame, so against them only its
    # drift since they were seen counts: 2.5 cm RMS over 5 s, at most 0.13 m (measured in the wash
    # test); the map grows them by their sensors' noise besides.
    margin_m: float = setting(0.15, "extra clearance to lethal cells beyond the vehicle's half width")
    corridor_margin_m: float = setting(0.1, "extra clearance to the corridor edge beyond the vehicle's half width")
    horizon_m: float = setting(80.0, "length of the published path ahead of the vehicle")
    point_spacing_m: float = setting(1.0, "spacing of the published path points")
    check_spacing_m: float = setting(
        0.1, "spacing of the samples a path is checked at: half of it is given up to each side of a gap"
    )
    station_behind_m: float = setting(15.0, "how far behind the previous station the vehicle is searched for")
    station_ahead_m: float = setting(60.0, "how far ahead of the previous station the vehicle is searched for")
    max_path_deviation_m: float = setting(2.0, "re-plan when the vehicle is further than this from its path")
    centre_rounding_m: float = setting(
        16.0, "the centre line's RDDF corners are rounded over this much path (twice the course's 8 m turn window)"
    )
    # Candidates (RASCAL: new paths generated from the vehicle's velocity).
    offset_step_m: float = setting(0.5, "lateral spacing of candidate offsets")
    max_offsets: int = setting(41, "most candidate offsets; wide corridors get a coarser step")
    max_gap_offsets: int = setting(4, "extra offsets through the middle of the gaps where the path fails, widest first")
    transition_times_s: tuple[float, ...] = setting((1.2, 2.2, 3.5), "lateral transition lengths as seconds of travel")
    min_transition_m: float = setting(4.0, "shortest lateral transition")
    max_transition_m: float = setting(40.0, "longest lateral transition")
    hold_after_conflict_m: tuple[float, ...] = setting(
        (5.0, 15.0), "candidates return to the centre line this far past the conflict (or not within the horizon)"
    )
    lead_m: float = setting(3.0, "a late candidate completes its swerve this far before the conflict")
    allow_partial: bool = setting(
        True, "with no candidate clear all the way, drive on towards a stop short of the hazard if there is a way past"
    )
    min_partial_m: float = setting(
        10.0, "with no candidate clear for the whole horizon, one clear this far beyond the stopping distance will do"
    )
    far_partial_m: float = setting(
        30.0,
        "a partial candidate whose stop is this far beyond the stopping distance is driven even with no way past "
        "known yet: far hazards are mapped coarsely, and the map sharpens on the way",
    )
    cost_weight: float = setting(4.0, "score per metre of path per unit of footprint-mean cost")
    offset_weight: float = setting(0.05, "score per metre of path per metre of lateral offset")
    change_weight: float = setting(0.1, "score per metre of path per metre of departure from the current path")
    slope_weight: float = setting(2.0, "score per metre of path per squared lateral slope (gentle swerves)")
    time_weight: float = setting(
        10.0, "score per second it takes to drive a candidate under its speed caps (curvature, clearance, cost)"
    )
    # Fallback search: Hybrid A* over the vehicle's poses, or Kratos' A* over cells (footprint-summed
    # cost grid, 8-connected, binary heap) smoothed and pursued. The cost and heuristic settings serve both.
    search_method: str = setting(
        "hybrid", "'hybrid' (Hybrid A* over poses: drivable as found) or 'lattice' (cell A*, smoothed, pursued)"
    )
    search_stride: int = setting(
        3, "A* lattice step in grid cells (1 = every cell); a channel it misses gets finer ones, down to every cell"
    )
    search_cost_weight: float = setting(1.0, "A* step cost: length x (1 + weight x footprint-mean cost)")
    search_room_m: float = setting(
        2.0, "A* steps closer than this beyond the gate's clearance to a lethal cell cost more: room to turn"
    )
    search_room_weight: float = setting(2.0, "...up to this much more per metre at the clearance itself")
    search_unseen_cost: float = setting(
        1.0,
        "A* heuristic: the cost assumed for every cell to the goal, as if unseen (Kratos; fusion's cost at p = 0.5)",
    )
    search_heuristic_weight: float = setting(1.5, "A* heuristic inflation on top (>1 trades optimality for speed)")
    goal_margin_m: float = setting(2.0, "the search goal stays this far inside the grid window")
    hybrid_step_m: float = setting(1.0, "Hybrid A*: arc length of a motion primitive (longer than a bin's diagonal)")
    hybrid_cell_m: float = setting(0.5, "Hybrid A*: side of a closed-set bin")
    hybrid_heading_bins: int = setting(72, "Hybrid A*: closed-set heading bins (5 degrees); primitives turn whole bins")
    hybrid_steer_weight: float = setting(0.2, "Hybrid A*: extra cost per metre steered at full lock")
    hybrid_steer_change_weight: float = setting(0.5, "Hybrid A*: extra cost per full-lock swing of the steering")
    hybrid_heuristic_cell_m: float = setting(1.0, "Hybrid A*: cells of the coarse obstacle-aware cost-to-go")
    hybrid_analytic_every: int = setting(10, "Hybrid A*: a Dubins curve to the goal is tried every so many expansions")
    hybrid_max_expansions: int = setting(
        1500, "Hybrid A*: expansions before it settles for the node nearest the goal (~80 ms in pure Python)"
    )
    pursuit_lookahead_m: float = setting(
        2.0, "a searched path is published as the track pure pursuit this far ahead makes"
    )
    cost_cap: float = setting(10.0, "finite stand-in for lethal and very high costs in the footprint sums")
    # Speeds.
    slow_speed_mps: float = setting(
        1.0, "speed commanded when no candidate is left and no search gets through (RASCAL's 1 m/s)"
    )
    search_speed_mps: float = setting(
        2.5,
        "top speed on a searched path that gets through: its arcs are gate-checked and within the steering "
        "limit; the curvature, steering-rate and clearance caps still apply",
    )
    start_speed_mps: float = setting(1.0, "speed the profile may command at once from standstill")
    speed_lead_mps: float = setting(
        1.0, "on its path, a new profile starts from the last one's speed there, at most this above the vehicle's"
    )
    max_lateral_accel_mps2: float = setting(2.0, "lateral acceleration limit for curvature speeds")
    max_accel_mps2: float = setting(1.5, "longitudinal acceleration limit")
    max_decel_mps2: float = setting(2.0, "planned braking limit")
    curvature_window_m: float = setting(3.0, "path length curvature is averaged over")
    near_hazard_speed_mps: float = setting(3.0, "speed allowed at the minimum clearance to a hazard")
    hazard_speed_gain_mps_per_m: float = setting(6.0, "extra speed allowed per metre of further clearance")
    caution_probability: float = setting(
        0.6, "hazard probability from which a cell slows the vehicle nearby (unknown cells are 0.5: not caution)"
    )
    cost_speed_gain: float = setting(
        0.2, "speed divided by (1 + gain x footprint-mean cost); hazards nearby slow it by their clearance already"
    )
    # A kept path slowed for a hazard it passes close by is re-planned if a candidate is faster.
    faster_min_gain_mps: float = setting(1.0, "a kept path is re-examined where a hazard slows it by more than this")
    faster_lead_s: float = setting(1.0, "...and that slowdown is at least this many seconds of travel ahead")
    faster_min_saving_s: float = setting(
        0.3, "a candidate replaces the kept path if it drives the horizon this much sooner"
    )
    faster_retry_m: float = setting(
        3.0, "...and, with none found, is looked for again this much further on; so is a search that stops short"
    )

    def __post_init__(self) -> None:
        if self.search_method not in SEARCH_METHODS:
            raise ValueError(f"PlannerConfig.search_method: one of {SEARCH_METHODS}, got {self.search_method!r}")
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in ("search_method", "vehicle"):
                continue
            values = value if isinstance(value, tuple) else (value,)
            if not values or not all(isinstance(v, int | float) and math.isfinite(v) and v >= 0 for v in values):
                raise ValueError(f"PlannerConfig.{f.name}: must be finite and not negative, got {value!r}")
        positive = (
            "horizon_m",
            "point_spacing_m",
            "check_spacing_m",
            "offset_step_m",
            "min_transition_m",
            "max_accel_mps2",
            "max_decel_mps2",
            "max_lateral_accel_mps2",
            "curvature_window_m",
            "cost_cap",
            "pursuit_lookahead_m",
            "slow_speed_mps",
            "search_speed_mps",
            "search_room_m",
            "hybrid_step_m",
            "hybrid_cell_m",
            "hybrid_heuristic_cell_m",
        )
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"PlannerConfig.{name}: must be positive")
        if self.search_stride < 1 or self.max_offsets < 1:
            raise ValueError("PlannerConfig.search_stride and max_offsets: must be at least 1")
        if min(self.hybrid_heading_bins, self.hybrid_analytic_every, self.hybrid_max_expansions) < 1:
            raise ValueError("PlannerConfig.hybrid_heading_bins, analytic_every and max_expansions: must be at least 1")
        if self.hybrid_step_m <= self.hybrid_cell_m * math.sqrt(2.0):
            raise ValueError("PlannerConfig.hybrid_step_m: must exceed a bin's diagonal, so every step leaves its bin")
        if self.hybrid_step_m / self.turning_radius_m < math.tau / self.hybrid_heading_bins:
            raise ValueError("PlannerConfig.hybrid_step_m: a step must turn at least one heading bin at full lock")
        if self.search_heuristic_weight < 1.0:
            raise ValueError("PlannerConfig.search_heuristic_weight: must be at least 1")
        if self.max_transition_m < self.min_transition_m:
            raise ValueError("PlannerConfig.max_transition_m: must not be below min_transition_m")
        if self.check_spacing_m > self.point_spacing_m:
            raise ValueError("PlannerConfig.check_spacing_m: must not exceed point_spacing_m")
        if not 0.0 < self.caution_probability <= 1.0:
            raise ValueError("PlannerConfig.caution_probability: must be in (0, 1]")

    @property
    def half_width_m(self) -> float:
        return self.vehicle.half_width_m

    @property
    def clearance_m(self) -> float:
        """Least distance from the path (the vehicle's reference line) to a lethal cell centre."""
        return self.half_width_m + self.margin_m

    @property
    def corridor_clearance_m(self) -> float:
        """Least distance from the path to the corridor's edge."""
        return self.half_width_m + self.corridor_margin_m

    @property
    def front_swing(self) -> FrontSwing:
        """How far the vehicle's front corners reach beyond its track on a turn."""
        return FrontSwing(self.vehicle.front_m, self.vehicle.half_width_m)

    def map_reach_m(self, top_speed_mps: float) -> float:
        """How far from the corridor a map cell can still change a plan: within the gate's clearance
        and the search's room, where a caution cell still slows ``top_speed_mps``, or the search
        goal's margin from the window's edge."""
        slowing = max(0.0, top_speed_mps - self.near_hazard_speed_mps) / self.hazard_speed_gain_mps_per_m
        return max(self.clearance_m + max(slowing, self.search_room_m), self.goal_margin_m)

    @property
    def turning_radius_m(self) -> float:
        """The rear axle's tightest turn."""
        return self.vehicle.turning_radius_m

    @property
    def hybrid(self) -> HybridSettings:
        """The Hybrid A* fallback's settings, turning no tighter than the vehicle."""
        return HybridSettings(
            step_m=self.hybrid_step_m,
            cell_m=self.hybrid_cell_m,
            heading_bins=self.hybrid_heading_bins,
            min_radius_m=self.turning_radius_m,
            steer_weight=self.hybrid_steer_weight,
            steer_change_weight=self.hybrid_steer_change_weight,
            heuristic_weight=self.search_heuristic_weight,
            heuristic_cell_m=self.hybrid_heuristic_cell_m,
            analytic_every=self.hybrid_analytic_every,
            max_expansions=self.hybrid_max_expansions,
        )

    @property
    def bicycle(self) -> Bicycle:
        """The vehicle as a searched path's track is driven: at slow speed, by pure pursuit."""
        return Bicycle(
            wheelbase_m=self.vehicle.wheelbase_m,
            max_steering_rad=self.vehicle.max_steering_rad,
            max_steering_rate_radps=self.vehicle.max_steering_rate_radps,
            speed_mps=self.slow_speed_mps,
            lookahead_m=self.pursuit_lookahead_m,
        )
