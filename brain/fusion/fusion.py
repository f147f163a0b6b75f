"""Sensor fusion into the rolling bird's-eye hazard map (sans-IO: messages and times in, arrays out).

RASCAL plotted every sensor's compact descriptors into one central bird's-eye map and categorised
them stochastically into hazards and environment. Here each message is placed with the vehicle
pose at its own ``t_meas_ns`` (PoseHistory), then:

- an ObstacleList adds its class's hit log-odds over every footprint (grown by the sensor's
  position noise at that range), after subtracting its miss log-odds over the part of the
  sensor's view it saw clear: the view sector cut short before every reported object, whose
  shadow stays unknown;
- a SurfaceProfile adds hits over its hazardous stretches and misses over its level ones, in a
  strip along its line;
- a GroundSweep does the same for its stretches across the road, each a box: the level ones as
  deep as the ground the line moves over between sweeps, the low and high ones grown by the
  sensor's noise; it is remembered for minutes, so it counts less while the heading's claimed
  uncertainty moves its line more than ``sweep_heading_tolerance_m`` to one side;
- LaneBorders mark a band outside each border as outside the lane and a band inside it as inside.

Evidence fades with a half-life, applied in steps as time advances. ``cost_map()`` fuses the
classes and builds the planner's layers; ``snapshot()`` is the MapSnapshot for the bus.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from brain.fusion.cost import CostConfig, CostMap, build_cost_map, hazard_probability
from brain.fusion.evidence import EvidenceLayers, Layer
from brain.fusion.poses import PoseHistory, heading_std_rad
from brain.fusion.profile import classify_profile
from brain.fusion.raster import (
    Stamp,
    boxes,
    rectangles,
    sensor_frame,
    slanted_boxes,
    strips,
    vehicle_frame,
    view_polygon,
)
from brain.fusion.sensors import DEFAULT_SENSOR_MODELS, SensorClass, SensorModel
from brain.fusion.snapshot import encode_snapshot
from brain.fusion.window import WindowPlacement
from brain.grid import GridWindow
from brain.pose import Pose
from protocol.messages import Frame, GroundSweep, LaneBorders, MapSnapshot, ObstacleList, SurfaceProfile, VehicleState
from rascal.runtime.config import setting

NS_PER_S = 1_000_000_000
MAX_EXTENT_M = 50.0  # a descriptor claiming a larger object is clipped to this
MAX_BORDER_M = 200.0  # lane borders are drawn at most this far from where they start
MAX_SWEEP_GAP_M = 2.0  # a ground sweep's hazards reach back at most this far towards the last one's line


@dataclass(frozen=True)
class FusionConfig:
    resolution_m: float = setting(0.2, "cell size")
    window_east_m: float = setting(96.0, "window extent along east, or along the heading's axis if turning")
    window_north_m: float = setting(96.0, "window extent along north, or across it (120 x 30 m: the planner's)")
    lead_m: float = setting(40.0, "the window is centred this far ahead of the vehicle")
    recentre_m: float = setting(3.0, "the window moves once its ideal centre is this far from the current one")
    margin_m: float = setting(5.0, "... but keeps the vehicle at least this far inside every edge")
    turn_with_heading: bool = setting(True, "a rectangular window lays its long side along the heading's nearer axis")
    half_life_s: float = setting(5.0, "evidence not renewed halves in this time (fades toward unknown)")
    lane_half_life_s: float = setting(3.0, "the same for lane beliefs")
    sweep_half_life_s: float = setting(
        300.0, "the same for the sweeping lidar's ground: terrain does not move, and its line is 37 m ahead"
    )
    sweep_half_distance_m: float = setting(
        200.0, "... and it also halves every this many metres driven: remembered ground moves with the pose's drift"
    )
    sweep_heading_tolerance_m: float = setting(
        0.25,
        "the sweep's ground counts in full while the heading's uncertainty moves it at most this far "
        "across at its range, and less in proportion beyond: it is remembered for minutes",
    )
    decay_step_s: float = setting(0.1, "evidence fades in steps this far apart (exact over each step)")
    evidence_min: float = setting(-2.0, "lowest log-odds one sensor class can hold in a cell (seen clear)")
    evidence_max: float = setting(4.0, "highest log-odds one sensor class can hold in a cell")
    agreement_min: float = setting(0.25, "a class whose log-odds exceed this supports a hazard in the cell")
    agreement_log_odds: float = setting(1.0, "added for each supporting class beyond the first")
    support_log_odds: float = setting(
        1.0, "a class's detection this strong no longer loses log-odds to other classes' clear views"
    )
    margin_cap_log_odds: float = setting(
        1.0,
        "the ring a detection's range noise adds round it raises a cell's log-odds to at most this "
        "(below the hazard threshold): far detections mark where a hazard may be, near ones where it is",
    )
    view_bin_deg: float = setting(1.0, "bearing bins of a clear view: a reported object shadows whole bins")
    clear_margin_m: float = setting(0.3, "a clear view stops this much (plus the sensor's noise) short of objects")
    pose_span_s: float = setting(3.0, "navigation states kept for placing late descriptors")
    max_extrapolation_s: float = setting(0.1, "farthest a pose is extrapolated past the states kept")
    profile_step_m: float = setting(0.15, "ground this far above or below the vehicle's ground plane is a hazard")
    profile_max_slope: float = setting(0.5, "rise over run between neighbouring returns that is a hazard")
    profile_min_rise_m: float = setting(
        0.05, "...if the rise is at least this: the nearest returns are 6 cm apart, and 1 cm of noise makes slopes"
    )
    profile_max_gap_m: float = setting(3.0, "level returns farther apart leave the ground between them unknown")
    profile_lost_m: float = setting(1.0, "a profile ending this far short of the sensor's range has lost the ground")
    lane_band_m: float = setting(3.0, "width of the band marked on each side of a lane border")

    def __post_init__(self) -> None:
        positive = (
            "half_life_s",
            "lane_half_life_s",
            "sweep_half_life_s",
            "sweep_half_distance_m",
            "sweep_heading_tolerance_m",
            "decay_step_s",
            "view_bin_deg",
            "pose_span_s",
            "lane_band_m",
            "support_log_odds",
        )
        bad = [name for name in positive if not getattr(self, name) > 0]
        if bad:
            raise ValueError(f"fusion settings must be positive: {bad}")
        if not self.evidence_min < 0 < self.evidence_max:
            raise ValueError("evidence_min must be negative and evidence_max positive")
        non_negative = ("clear_margin_m", "max_extrapolation_s", "agreement_log_odds", "profile_min_rise_m")
        if any(getattr(self, name) < 0 for name in non_negative):
            raise ValueError(f"fusion settings must be >= 0: {', '.join(non_negative)}")

    def placement(self) -> WindowPlacement:
        return WindowPlacement(
            self.window_east_m,
            self.window_north_m,
            self.resolution_m,
            self.lead_m,
            self.recentre_m,
            self.margin_m,
            self.turn_with_heading,
        )


@dataclass
class FusionStats:
    """Counters for a heartbeat: what was fused and what was refused, by reason."""

    messages: int = 0
    descriptors: int = 0
    no_pose: int = 0  # message time outside the pose history (see PoseHistory.stats for which side)
    unknown_sensor: int = 0  # no model for the message's sensor
    bad_frame: int = 0
    bad_descriptor: int = 0  # non-finite values, lane borders with a side other than +-1, mismatched profiles
    out_of_range: int = 0  # obstacles beyond the sensor's detection range
    moves: int = 0
    decays: int = 0


class HazardFusion:
    """The bird's-eye hazard map: feed it poses and descriptors, ask it for the cost map."""

    def __init__(
        self,
        config: FusionConfig | None = None,
        sensors: Mapping[int, SensorModel] | None = None,
        cost: CostConfig | None = None,
    ) -> None:
        self.config = config or FusionConfig()
        self.cost_config = cost or CostConfig()
        self.sensors = dict(DEFAULT_SENSOR_MODELS if sensors is None else sensors)
        self.placement = self.config.placement()
        self.poses = PoseHistory(
            round(self.config.pose_span_s * NS_PER_S), round(self.config.max_extrapolation_s * NS_PER_S)
        )
        self.stats = FusionStats()
        self.layers: EvidenceLayers | None = None
        self.stamp: Stamp | None = None
        self.t_ns: int | None = None  # map time: the newest time fused
        self.last_fused_ns: dict[int, int] = {}  # per Sensor: the newest t_meas_ns fused from it
        self._sweep_poses: dict[int, Pose] = {}  # per sweeping lidar: the pose of its last sweep
        self._yaw_std_rad = 0.0  # the newest navigation state's heading uncertainty
        self._t_decayed_ns: int | None = None  # the time the layers' evidence refers to
        self._decayed_at: Pose | None = None  # where the vehicle was then
        self._half_lives_s = np.full(len(SensorClass), self.config.half_life_s, np.float32)
        self._half_lives_s[SensorClass.LIDAR_SWEEP] = self.config.sweep_half_life_s
        self._half_distances_m = np.full(len(SensorClass), np.inf, np.float32)
        self._half_distances_m[SensorClass.LIDAR_SWEEP] = self.config.sweep_half_distance_m

    @property
    def window(self) -> GridWindow | None:
        return self.layers.window if self.layers else None

    # -- inputs -----------------------------------------------------------------------------

    def add_pose(self, t_meas_ns: int, state: VehicleState) -> bool:
        """A navigation state; the newest one also moves the window when the vehicle has gone far
        enough. False when the state is unusable (invalid quality or non-finite)."""
        if not self.poses.add(t_meas_ns, state):
            return False
        if t_meas_ns == self.poses.newest_ns:
            pose = self.poses.newest()
            assert pose is not None
            self._yaw_std_rad = heading_std_rad(state)
            self._follow(pose)
            self._advance(t_meas_ns)
        return True

    def add_obstacles(self, t_meas_ns: int, message: ObstacleList) -> bool:
        """Fuse one ObstacleList; False (counted) when it cannot be placed."""
        placed = self._prepare(t_meas_ns, message.sensor)
        if placed is None:
            return False
        model, pose, weight = placed
        if message.frame not in (Frame.VEHICLE, Frame.ENU):
            self.stats.bad_frame += 1
            return False
        obstacles = np.array(message.obstacles, dtype=float).reshape(-1, 8)
        xy, yaw = obstacles[:, 0:2], obstacles[:, 5]
        if message.frame == Frame.ENU:
            xy = vehicle_frame(pose).from_enu(xy)
            yaw = yaw - pose.yaw_rad
        # Where each obstacle lies as the sensor sees it: range and bearing from its mount.
        c, s = math.cos(model.yaw_rad), math.sin(model.yaw_rad)
        dx, dy = xy[:, 0] - model.x_m, xy[:, 1] - model.y_m
        in_sensor = np.column_stack((c * dx + s * dy, -s * dx + c * dy))
        distance = np.hypot(in_sensor[:, 0], in_sensor[:, 1])
        finite = np.isfinite(obstacles).all(axis=1) & np.isfinite(yaw) & np.isfinite(distance)
        self.stats.bad_descriptor += int(np.count_nonzero(~finite))
        keep = finite & (distance <= model.detect_range_m)
        self.stats.out_of_range += int(np.count_nonzero(finite & ~keep))
        # The footprint grown by the noise every range has is the hazard; the ring the noise of
        # its range adds only says where it may be (capped below the threshold), so a rock seen
        # 30 m off by stereo does not close a passage beside it before nearer views place it.
        core = np.clip(obstacles[keep, 2:4], 0.0, MAX_EXTENT_M) / 2 + model.noise_m
        ring = core + (model.noise_per_m2 * distance[keep] ** 2)[:, None]
        assert self.layers is not None and self.stamp is not None
        # The clear view first, the detections over it: a message never clears its own footprints.
        seen = view_polygon(
            model,
            in_sensor[keep],
            np.hypot(core[:, 0], core[:, 1]),
            math.radians(self.config.view_bin_deg),
            self.config.clear_margin_m + self.config.resolution_m,
        )
        if len(core):
            confidence = np.clip(obstacles[keep, 6], 0.0, 1.0)
            range_factor = np.minimum(1.0, model.max_range_m / np.maximum(distance[keep], 1e-9))
            hits = model.hit_log_odds * weight * confidence * range_factor
            to_enu = vehicle_frame(pose).to_enu
            cores = to_enu(rectangles(xy[keep], core, yaw[keep]))
            self.stamp.fill_each(to_enu(rectangles(xy[keep], ring, yaw[keep])), hits)
            self.stamp.fill_each(cores, np.zeros_like(hits))  # the rings alone
            self.layers.add_capped(model.sensor_class, self.stamp, self.config.margin_cap_log_odds)
        self.stamp.fill(sensor_frame(pose, model).to_enu(seen)[None], model.miss_log_odds * weight)
        if len(core):
            self.stamp.fill_each(cores, hits)
        self.layers.add(model.sensor_class, self.stamp)
        self._fused(message.sensor, t_meas_ns, int(np.count_nonzero(keep)))
        return True

    def add_profile(self, t_meas_ns: int, message: SurfaceProfile) -> bool:
        """Fuse one vertical-lidar ground profile; False (counted) when it cannot be placed."""
        placed = self._prepare(t_meas_ns, message.sensor)
        if placed is None:
            return False
        model, pose, weight = placed
        config = self.config
        try:
            stretches = classify_profile(
                message.ranges_m,
                message.heights_m,
                config.profile_step_m,
                config.profile_max_slope,
                config.profile_max_gap_m,
                expected_end_m=model.max_range_m,
                lost_m=config.profile_lost_m,
                point_half_m=config.resolution_m,
                max_range_m=model.detect_range_m,
                min_rise_m=config.profile_min_rise_m,
            )
        except ValueError:
            self.stats.bad_descriptor += 1
            return False
        assert self.layers is not None and self.stamp is not None
        frame = vehicle_frame(pose)
        y, width = message.lateral_m, model.line_half_width_m
        # Positions along the line are uncertain by the sensor's noise: hazards grow, level ground
        # shrinks; hazards are drawn last, over any level ground they overlap.
        start, end = stretches.level.T
        start, end = start + model.noise_at(start), end - model.noise_at(end)
        level = end > start
        self.stamp.fill(frame.to_enu(strips(start[level], end[level], y, width)), model.miss_log_odds * weight)
        start, end = stretches.hazard.T
        start, end = start - model.noise_at(start), end + model.noise_at(end)
        self.stamp.fill(frame.to_enu(strips(start, end, y, width)), model.hit_log_odds * weight)
        self.layers.add(model.sensor_class, self.stamp)
        self._fused(message.sensor, t_meas_ns, 1)
        return True

    def add_ground_sweep(self, t_meas_ns: int, message: GroundSweep) -> bool:
        """Fuse one sweeping-lidar ground line; False (counted) when it cannot be placed."""
        placed = self._prepare(t_meas_ns, message.sensor)
        if placed is None:
            return False
        model, pose, weight = placed
        rows = np.array(message.stretches, dtype=float).reshape(-1, 5)  # GroundStretch fields
        finite = np.all(np.isfinite(rows), axis=1) & (rows[:, 0] <= rows[:, 1]) & (rows[:, 2] <= rows[:, 3])
        self.stats.bad_descriptor += int(np.count_nonzero(~finite))
        near = _nearest_m(rows, model.x_m, model.y_m)
        keep = finite & (near <= model.detect_range_m)
        self.stats.out_of_range += int(np.count_nonzero(finite & ~keep))
        rows, near = rows[keep], near[keep]
        # A heading 0.5 deg off puts the line 0.3 m to one side at 37 m, and the sweep's ground is
        # kept for minutes: while the heading is that uncertain (standing at the start, on the
        # compass alone) it counts for less, so a few later sweeps outweigh it.
        if len(near):
            across_m = self._yaw_std_rad * float(near.max())
            weight *= min(1.0, self.config.sweep_heading_tolerance_m / max(across_m, 1e-9))
        assert self.layers is not None and self.stamp is not None
        frame = vehicle_frame(pose)
        level = rows[:, 4] == 0.0
        # Each sweep speaks for the ground as deep as the line moves between sweeps: level ground
        # half that either side. Hazards reach back to the last sweep's line (a ditch's near wall
        # may lie anywhere after it; a busy machine sweeps less often), are grown by the noise, and
        # are drawn last, over any level ground they overlap.
        half = model.line_half_width_m
        last = self._sweep_poses.get(message.sensor)
        moved_m = _distance_m(last, pose) if last else 0.0
        self._sweep_poses[message.sensor] = pose
        back_m = min(max(half, moved_m), MAX_SWEEP_GAP_M)
        self.stamp.fill(
            frame.to_enu(boxes(*(rows[level, :4] + (-half, half, 0.0, 0.0)).T)), model.miss_log_odds * weight
        )
        noise = model.noise_at(near[~level])
        grown = rows[~level, :4] + np.outer(noise, (-1.0, 1.0, -1.0, 1.0))
        # The reach back and ahead follows the beams (a box seen off to the side is a slab of a
        # slanting run: modules/lidar/sweep.py), not the vehicle's x axis.
        centre_x, centre_y = (grown[:, 0] + grown[:, 1]) / 2 - model.x_m, (grown[:, 2] + grown[:, 3]) / 2 - model.y_m
        slope = centre_y / np.maximum(centre_x, 1.0)
        x_from, x_to, y_from, y_to = grown.T
        outlines = slanted_boxes(x_from, x_to, y_from, y_to, back_m, half, slope)
        self.stamp.fill(frame.to_enu(outlines), model.hit_log_odds * weight)
        self.layers.add(model.sensor_class, self.stamp)
        self._fused(message.sensor, t_meas_ns, len(rows))
        return True

    def add_lane_borders(self, t_meas_ns: int, message: LaneBorders) -> bool:
        """Fuse lane borders (y = c0 + c1 x + c2 x^2 in the vehicle frame); False when unplaceable."""
        placed = self._prepare(t_meas_ns, message.sensor)
        if placed is None:
            return False
        _model, pose, weight = placed
        assert self.layers is not None and self.stamp is not None
        frame = vehicle_frame(pose)
        band = self.config.lane_band_m
        lanes = 0
        for border in message.borders:
            if border.side not in (1, -1) or not all(map(math.isfinite, border)) or border.x_min_m >= border.x_max_m:
                self.stats.bad_descriptor += 1
                continue
            x_to = min(border.x_max_m, border.x_min_m + MAX_BORDER_M)
            x = np.linspace(border.x_min_m, x_to, max(2, math.ceil(x_to - border.x_min_m) + 1))
            with np.errstate(over="ignore", invalid="ignore"):
                y = border.c0_m + border.c1 * x + border.c2_per_m * x * x
            if not np.all(np.isfinite(y)):  # finite but absurd coefficients
                self.stats.bad_descriptor += 1
                continue
            line = np.column_stack((x, y))
            belief = float(np.clip(border.confidence, 0.0, 1.0)) * weight
            for shift, outside in ((border.side * band, True), (-border.side * band, False)):
                polygon = np.concatenate((line, np.column_stack((x, y + shift))[::-1]))
                self.stamp.fill(frame.to_enu(polygon)[None], 1.0)
                self.layers.mark_lane(self.stamp, belief, outside)
            lanes += 1
        self._fused(message.sensor, t_meas_ns, lanes)
        return True

    # -- outputs ----------------------------------------------------------------------------

    def hazard_log_odds(self) -> Layer:
        """Fused hazard log-odds per cell of the current window."""
        if self.layers is None:
            raise RuntimeError("the map has no window before the first pose")
        config = self.config
        return self.layers.fused_log_odds(config.agreement_min, config.agreement_log_odds, config.support_log_odds)

    def cost_map(self) -> CostMap:
        """Hazard probability, cost and lethal cells for the planner, at the current map time."""
        if self.layers is None or self.t_ns is None:
            raise RuntimeError("the map has no window before the first pose")
        return build_cost_map(self.layers.window, self.hazard_log_odds(), self.layers.lane, self.cost_config, self.t_ns)

    def snapshot(self, downsample: int = 1) -> MapSnapshot:
        """The hazard probability as a MapSnapshot."""
        if self.layers is None:
            raise RuntimeError("the map has no window before the first pose")
        return encode_snapshot(self.layers.window, hazard_probability(self.hazard_log_odds()), downsample)

    # -- internals --------------------------------------------------------------------------

    def _prepare(self, t_meas_ns: int, sensor: int) -> tuple[SensorModel, Pose, float] | None:
        """The sensor's model, the pose at the message's time and the weight of its evidence
        (its age in half-lives since the layers' time), or None with the reason counted."""
        model = self.sensors.get(sensor)
        if model is None:
            self.stats.unknown_sensor += 1
            return None
        pose = self.poses.at(t_meas_ns)
        if pose is None or self.layers is None:
            self.stats.no_pose += 1
            return None
        self._advance(t_meas_ns)
        assert self._t_decayed_ns is not None
        age_s = max(0, self._t_decayed_ns - t_meas_ns) / NS_PER_S
        return model, pose, 0.5 ** (age_s / self.config.half_life_s)

    def _fused(self, sensor: int, t_meas_ns: int, descriptors: int) -> None:
        self.stats.messages += 1
        self.stats.descriptors += descriptors
        self.last_fused_ns[sensor] = max(t_meas_ns, self.last_fused_ns.get(sensor, t_meas_ns))

    def _follow(self, pose: Pose) -> None:
        if self.layers is None:
            window = self.placement.place(pose)
            self.layers = EvidenceLayers(window, len(SensorClass), self.config.evidence_min, self.config.evidence_max)
            self.stamp = Stamp(window)
        elif self.placement.needs_move(self.layers.window, pose):
            window = self.placement.place(pose, self.layers.window)
            self.layers.roll(window)
            self.stamp = Stamp(window)
            self.stats.moves += 1

    def _advance(self, t_ns: int) -> None:
        """Move map time forward to ``t_ns`` and let the evidence fade for every whole step: by
        the time elapsed, and the sweep's ground also by the distance driven."""
        if self.t_ns is None or t_ns > self.t_ns:
            self.t_ns = t_ns
        if self._t_decayed_ns is None or self._decayed_at is None:
            self._t_decayed_ns, self._decayed_at = self.t_ns, self.poses.newest()
            return
        elapsed_s = (self.t_ns - self._t_decayed_ns) / NS_PER_S
        if elapsed_s >= self.config.decay_step_s and self.layers is not None:
            here = self.poses.newest()
            assert here is not None  # the layers exist from the first pose on
            driven_m = _distance_m(self._decayed_at, here)
            factors = 0.5 ** (elapsed_s / self._half_lives_s + driven_m / self._half_distances_m)
            self.layers.decay(factors, 0.5 ** (elapsed_s / self.config.lane_half_life_s))
            self._t_decayed_ns, self._decayed_at = self.t_ns, here
            self.stats.decays += 1


def _distance_m(a: Pose, b: Pose) -> float:
    return math.hypot(b.east_m - a.east_m, b.north_m - a.north_m)


def _nearest_m(boxes: np.ndarray, x_m: float, y_m: float) -> np.ndarray:
    """Distance from (x_m, y_m) to the nearest point of each box (rows x_near, x_far, y_right, y_left, ...)."""
    dx = np.maximum(np.maximum(boxes[:, 0] - x_m, x_m - boxes[:, 1]), 0.0)
    dy = np.maximum(np.maximum(boxes[:, 2] - y_m, y_m - boxes[:, 3]), 0.0)
    return np.hypot(dx, dy)
