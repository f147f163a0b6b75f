"""The ESVS configuration: what a deployment file or ``--set`` gives at start, and which settings
a ConfigUpdate may change while it runs (``LIVE_KEYS``), with one validation for both."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

from modules.esvs import scheduling
from modules.esvs.vision.pipeline import VisionParams
from rascal.runtime.config import ConfigError, parse_assignments, setting

MODES = ("monolithic", "cambada")
MIN_ROUND_S, MAX_ROUND_S = 0.033, 1.0
LIVE_KEYS = frozenset({"round_period_s", "hang_rounds", "hang_min_s", "max_range_m", "min_obstacle_points", "lane_hot"})
INJECT_KEY = "inject_fault"  # not a setting: a one-shot fault for the watchdog's tests
_VISION = VisionParams()


@dataclass(frozen=True)
class EsvsConfig:
    mode: str = setting("monolithic", "monolithic: one worker, whole pipeline; cambada: obstacle and lane workers")
    ring_name: str = setting("rascal-stereo", "shared-memory frame ring the camera (stereo_camera) writes")
    round_period_s: float = setting(0.1, "the round: timer, grab, receive, send, process (RASCAL: 100 ms); 0.033-1")
    hang_rounds: float = setting(2.0, "a worker without a result this many rounds after it was due is hung...")
    hang_min_s: float = setting(0.2, "...but never sooner than this: a short round must not kill a slow frame")
    startup_timeout_s: float = setting(10.0, "a worker that has not said hello this long after its start is hung")
    vehicle_state_max_age_s: float = setting(0.5, "VEHICLE_STATE older than this is reported stale")
    sched: str = setting("fifo", "priorities: fifo (SCHED_FIFO, falling back to nice if refused), nice, none")
    round_priority: int = setting(50, "SCHED_FIFO priority of the round (above every worker, as RASCAL's)")
    vision_priority: int = setting(20, "monolithic worker priority (RASCAL: vision runs lowest)")
    obstacle_priority: int = setting(45, "cambada: obstacle worker priority (the highest: CAMBADA's Avoid)")
    obstacle_every_rounds: int = setting(1, "cambada: obstacle worker period, in rounds (every frame)")
    obstacle_offset_s: float = setting(0.0, "cambada: obstacle worker activation offset")
    lane_priority: int = setting(25, "cambada: lane worker priority")
    lane_every_rounds: int = setting(2, "cambada: lane worker period, in rounds (every second frame)")
    lane_offset_s: float = setting(0.05, "cambada: lane worker activation offset (de-phased from obstacles)")
    # The vision package's own defaults, so that they are stated once.
    max_range_m: float = setting(_VISION.max_range_m, "obstacle points are sought up to this far ahead of the cameras")
    min_obstacle_points: int = setting(_VISION.clusters.min_points, "stereo points an obstacle needs")
    lane_hot: float = setting(_VISION.fit.hot, "heat-map cells this hot are lane evidence (0-1)")
    allow_fault_injection: bool = setting(False, "accept ConfigUpdate inject_fault=hang|crash (watchdog tests)")

    def __post_init__(self) -> None:
        check_config(self)  # at load time, so that the launcher reports a bad setting by name

    def hang_timeout_s(self) -> float:
        return max(self.hang_rounds * self.round_period_s, self.hang_min_s)

    def worker_timing(self) -> dict[str, tuple[int, float, int]]:
        """CAMBADA mode: role -> (period in rounds, offset in seconds, priority)."""
        return {
            "obstacles": (self.obstacle_every_rounds, self.obstacle_offset_s, self.obstacle_priority),
            "lanes": (self.lane_every_rounds, self.lane_offset_s, self.lane_priority),
        }


def check_config(config: EsvsConfig) -> None:
    """Raise ConfigError (a ValueError) naming every setting that cannot be used."""
    problems = []
    if config.mode not in MODES:
        problems.append(f"mode must be one of {MODES}, not {config.mode!r}")
    if not MIN_ROUND_S <= config.round_period_s <= MAX_ROUND_S:
        problems.append(f"round_period_s must be in {MIN_ROUND_S}..{MAX_ROUND_S} s, not {config.round_period_s}")
    if not (math.isfinite(config.hang_rounds) and config.hang_rounds >= 1.0):
        problems.append(f"hang_rounds must be >= 1, not {config.hang_rounds}")
    for name in ("hang_min_s", "startup_timeout_s", "vehicle_state_max_age_s"):
        value = getattr(config, name)
        if not (math.isfinite(value) and value > 0):
            problems.append(f"{name} must be positive, not {value}")
    for name in ("round_priority", "vision_priority", "obstacle_priority", "lane_priority"):
        try:
            scheduling.check(config.sched, getattr(config, name))
        except ValueError as exc:
            problems.append(f"{name}: {exc}")
    for role, (rounds, offset, _priority) in config.worker_timing().items():
        if rounds < 1:
            problems.append(f"{role} period must be >= 1 round, not {rounds}")
        elif not 0 <= offset < rounds * config.round_period_s:
            problems.append(f"{role} offset must be in [0, its period of {rounds} round(s)), not {offset}")
    if not (math.isfinite(config.max_range_m) and 12.0 <= config.max_range_m <= 100.0):
        problems.append(f"max_range_m must be in 12..100 m, not {config.max_range_m}")
    if not 1 <= config.min_obstacle_points <= 100_000:
        problems.append(f"min_obstacle_points must be in 1..100000, not {config.min_obstacle_points}")
    if not (math.isfinite(config.lane_hot) and 0.0 < config.lane_hot < 1.0):
        problems.append(f"lane_hot must be in (0, 1), not {config.lane_hot}")
    if problems:
        raise ConfigError("; ".join(problems))


def vision_params(config: EsvsConfig) -> VisionParams:
    """The vision package's defaults with the ESVS's settings in place."""
    return replace(
        _VISION,
        max_range_m=config.max_range_m,
        clusters=replace(_VISION.clusters, min_points=config.min_obstacle_points),
        fit=replace(_VISION.fit, hot=config.lane_hot),
    )


def updated(config: EsvsConfig, key: str, text: str) -> EsvsConfig:
    """``config`` with ``key`` set from ``text`` while running; ConfigError or ValueError says why not."""
    known = {f.name for f in fields(EsvsConfig)}
    if key in known and key not in LIVE_KEYS:
        raise ConfigError(f"{key} cannot change while the ESVS runs (restart it); live: {sorted(LIVE_KEYS)}")
    values = parse_assignments(EsvsConfig, [f"{key}={text}"], where="CONFIG")
    return replace(config, **values)  # checked whole by __post_init__
