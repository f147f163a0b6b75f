"""The brain's sensor health: which inputs are alive, the driving mode that follows, its speed cap.

RASCAL's race ended because its planner did not notice that the lidars had gone silent. Here
every input has a max age, measured from its ``t_meas_ns``, and the brain drives in the mode its
live inputs allow:

======================  ===========================================  =============================
mode                    when                                         speed cap
======================  ===========================================  =============================
NORMAL                  navigation and every obstacle sensor live    the course's
LIDAR_DEGRADED          some lidars silent, one horizontal one live  the course's (reported); with
                                                                     the sweeping lidar silent, stop
                                                                     within the vertical ones' 24 m
STEREO_ONLY             both horizontal lidars silent, stereo live   stop within stereo's 35 m
LIDAR_ONLY              stereo silent, a horizontal lidar live       stop within the lidars' 40 m
BLIND                   no obstacle sensor live                      0: stop
NAV_LOST                vehicle state stale, or its quality INVALID  0: stop
======================  ===========================================  =============================

Dead reckoning (GPS lost) caps the speed too, lower as the position uncertainty grows, since
the corridor and the map are only as good as the position. Sans-IO: times come in as arguments.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from protocol.messages import NavQuality, VehicleState

LIDARS = ("lidar_h_left", "lidar_h_right", "lidar_v_left", "lidar_v_right", "lidar_sweep")
HORIZONTAL_LIDARS = ("lidar_h_left", "lidar_h_right")
SWEEP_LIDAR = "lidar_sweep"  # sees ditches across the road 37 m ahead; without it only the vertical lidars
STEREO = "esvs"
NAVIGATION = "navigation"


class DriveMode(enum.Enum):
    NORMAL = "normal"
    LIDAR_DEGRADED = "lidar_degraded"
    STEREO_ONLY = "stereo_only"
    LIDAR_ONLY = "lidar_only"
    BLIND = "blind"
    NAV_LOST = "nav_lost"


@dataclass(frozen=True)
class HealthParams:
    lidar_max_age_s: float = 0.2  # lidars publish at 25 Hz: five missed scans
    stereo_max_age_s: float = 0.5  # the ESVS round is 0.1 s: a worker restart fits, a dead ESVS does not
    navigation_max_age_s: float = 0.2  # 100 Hz solutions
    stereo_range_m: float = 35.0
    lidar_range_m: float = 40.0
    ground_range_m: float = 24.0  # the vertical lidars' reach: where a ditch is seen without the sweep
    braking_mps2: float = 2.0  # the planner's comfortable deceleration, also used for stopping
    reaction_s: float = 0.5  # detection, planning and actuation latency before braking starts
    margin_m: float = 5.0  # stop this much short of the sensor's range
    dead_reckoning_cap_mps: float = 8.0
    dead_reckoning_sigma_for_crawl_m: float = 2.0  # at this horizontal 1-sigma, crawl
    crawl_mps: float = 1.0


@dataclass(frozen=True)
class Assessment:
    mode: DriveMode
    speed_cap_mps: float
    silent: tuple[str, ...]  # inputs past their max age (or never heard)
    reason: str


def stopping_speed_mps(range_m: float, params: HealthParams) -> float:
    """The highest speed from which the vehicle stops within ``range_m`` minus the margin:
    v * reaction + v^2 / (2 a) = d, solved for v."""
    distance = max(0.0, range_m - params.margin_m)
    a, t = params.braking_mps2, params.reaction_s
    return -a * t + math.sqrt((a * t) ** 2 + 2.0 * a * distance)


class SensorHealth:
    """Remembers when each input was last measured and judges the drive mode from it."""

    def __init__(self, params: HealthParams | None = None, expected: tuple[str, ...] = (*LIDARS, STEREO)) -> None:
        self.params = params or HealthParams()
        self.expected = expected
        self.last_ns: dict[str, int] = {}
        self.navigation: VehicleState | None = None

    def heard(self, source: str, t_meas_ns: int) -> None:
        if t_meas_ns > self.last_ns.get(source, -1):
            self.last_ns[source] = t_meas_ns

    def heard_navigation(self, state: VehicleState, t_meas_ns: int) -> None:
        self.heard(NAVIGATION, t_meas_ns)
        self.navigation = state

    def oldest_live_ns(self, sources: tuple[str, ...], now_ns: int) -> int | None:
        """The oldest of the newest measurement times of those ``sources`` that are alive: how
        stale the freshest picture they give together is."""
        times = [self.last_ns[source] for source in sources if self.alive(source, now_ns)]
        return min(times) if times else None

    def alive(self, source: str, now_ns: int) -> bool:
        last = self.last_ns.get(source)
        if last is None:
            return False
        return now_ns - last <= self._max_age_s(source) * 1e9

    def assess(self, now_ns: int, course_speed_mps: float = math.inf) -> Assessment:
        p = self.params
        silent = tuple(source for source in (*self.expected, NAVIGATION) if not self.alive(source, now_ns))
        nav = self.navigation
        if NAVIGATION in silent or nav is None or nav.quality == NavQuality.INVALID:
            return Assessment(DriveMode.NAV_LOST, 0.0, silent, "no valid vehicle state")
        horizontal = [name for name in HORIZONTAL_LIDARS if name in self.expected and name not in silent]
        stereo = STEREO in self.expected and STEREO not in silent
        lidars_silent = [name for name in LIDARS if name in self.expected and name in silent]
        if not horizontal and not stereo:
            mode, cap, reason = DriveMode.BLIND, 0.0, "no obstacle sensor is live"
        elif not horizontal:
            mode, cap = DriveMode.STEREO_ONLY, stopping_speed_mps(p.stereo_range_m, p)
            reason = f"horizontal lidars silent: stereo alone, stopping within {p.stereo_range_m:.0f} m"
        elif not stereo and STEREO in self.expected:
            mode, cap = DriveMode.LIDAR_ONLY, stopping_speed_mps(p.lidar_range_m, p)
            reason = f"stereo silent: lidars alone, stopping within {p.lidar_range_m:.0f} m"
        elif lidars_silent:
            mode, cap, reason = DriveMode.LIDAR_DEGRADED, math.inf, f"silent: {', '.join(lidars_silent)}"
            if SWEEP_LIDAR in lidars_silent:
                cap = stopping_speed_mps(p.ground_range_m, p)
                reason += f"; ditches seen only {p.ground_range_m:.0f} m ahead, stopping within that"
        else:
            mode, cap, reason = DriveMode.NORMAL, math.inf, "all inputs live"
        if nav.quality == NavQuality.DEAD_RECKONING:
            cap = min(cap, self._dead_reckoning_cap(nav))
            reason += f"; dead reckoning, capped at {cap:.1f} m/s"
        return Assessment(mode, min(cap, course_speed_mps), silent, reason)

    def _dead_reckoning_cap(self, nav: VehicleState) -> float:
        """From the dead-reckoning cap down to a crawl as the position 1-sigma grows."""
        p = self.params
        sigma = math.sqrt(max(0.0, nav.covariance[0] + nav.covariance[6]))
        share = min(1.0, sigma / p.dead_reckoning_sigma_for_crawl_m)
        return p.dead_reckoning_cap_mps + share * (p.crawl_mps - p.dead_reckoning_cap_mps)

    def _max_age_s(self, source: str) -> float:
        if source == NAVIGATION:
            return self.params.navigation_max_age_s
        if source == STEREO:
            return self.params.stereo_max_age_s
        return self.params.lidar_max_age_s
