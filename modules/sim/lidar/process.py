"""One simulated lidar per process: it reads the simulator's true pose, looks at the scenario's
world from its mount, and publishes what that lidar would: obstacle descriptors (horizontal
lidars), a ground profile (vertical lidars) or the ground line across the road (the sweeping
lidar), with the scenario's sensor faults applied.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from brain.pose import Pose
from modules.lidar.cluster import describe_scan
from modules.lidar.profile import VERTICAL_MOUNTS, Hazard, detect_hazards
from modules.lidar.scan import HORIZONTAL_MOUNTS, ScanSpec
from modules.lidar.sweep import SWEEP_MOUNT, describe_sweep
from modules.sim.lidar.profile import profile_scan
from modules.sim.lidar.raycast import Scene, add_noise, cast
from modules.sim.lidar.sweep import sweep_scan
from modules.sim.scenario import DEFAULT_SCENARIO, load_scenario
from modules.sim.sensing import SensedTruth
from modules.sim.world import World
from protocol import channels
from protocol.messages import Frame, GroundSweep, ObstacleList, Sensor, SimTruth, SurfaceProfile
from rascal.runtime.config import setting
from rascal.runtime.module import Module, Runtime
from rascal.runtime.ports import Port

# Source ids the runner gives each lidar process (``--source-id``), and what each one is.
SOURCE_IDS: dict[str, int] = {
    "lidar_h_left": 21,
    "lidar_h_right": 22,
    "lidar_v_left": 23,
    "lidar_v_right": 24,
    "lidar_sweep": 25,
}
SENSORS: dict[str, Sensor] = {
    "lidar_h_left": Sensor.LIDAR_H_LEFT,
    "lidar_h_right": Sensor.LIDAR_H_RIGHT,
    "lidar_v_left": Sensor.LIDAR_V_LEFT,
    "lidar_v_right": Sensor.LIDAR_V_RIGHT,
    "lidar_sweep": Sensor.LIDAR_SWEEP,
}
CHANNELS: dict[str, str] = {
    "lidar_h_left": channels.OBSTACLES_LIDAR,
    "lidar_h_right": channels.OBSTACLES_LIDAR,
    "lidar_v_left": channels.SURFACE_PROFILE,
    "lidar_v_right": channels.SURFACE_PROFILE,
    "lidar_sweep": channels.GROUND_SWEEP,
}
Output = ObstacleList | SurfaceProfile | GroundSweep
# The simulator publishes truth far faster than this; a pose older than this means it stopped,
# and a lidar without a pose has nothing to scan from.
TRUTH_MAX_AGE_S = 0.5


@dataclass(frozen=True)
class LidarConfig:
    sensor: str = setting(
        "lidar_h_left", "which lidar: lidar_h_left, lidar_h_right, lidar_v_left, lidar_v_right, lidar_sweep"
    )
    scenario: str = setting(str(DEFAULT_SCENARIO), "scenario file whose world the lidar sees")
    rate_hz: float = setting(25.0, "publication rate (a horizontal scanner sweeps at 75 Hz; the newest sweep is sent)")
    noise_std_m: float = setting(0.01, "range noise, one sigma, before any NOISE fault")
    seed_offset: int = setting(0, "combined with the scenario seed: change it for independent noise")


class Lidar(Module):
    """Simulated lidar: horizontal ones publish ObstacleList, vertical ones SurfaceProfile, the
    sweeping one GroundSweep."""

    name = "lidar"
    default_source_id = SOURCE_IDS["lidar_h_left"]
    Config = LidarConfig
    interface = (
        Port("in", "`SIM_TRUTH`", "SimTruth (the newest pose is used)", "the simulator's", "0.5 s"),
        Port(
            "out",
            "`OBSTACLES_LIDAR` (horizontal lidars)",
            "ObstacleList (`LIDAR_H_LEFT`/`_RIGHT`, VEHICLE frame)",
            "`rate_hz` (25)",
        ),
        Port(
            "out",
            "`SURFACE_PROFILE` (vertical lidars)",
            "SurfaceProfile (`LIDAR_V_LEFT`/`_RIGHT`, `lateral_m` +-0.5)",
            "`rate_hz` (25)",
        ),
        Port(
            "out",
            "`GROUND_SWEEP` (sweeping lidar)",
            "GroundSweep (`LIDAR_SWEEP`, VEHICLE frame)",
            "`rate_hz` (the deployments: 37.5, a SICK's rate at 0.5 deg)",
        ),
        Port("out", "`MODULE_STATUS`", "ModuleStatus", "1 Hz"),
    )

    def __init__(self, config: LidarConfig, runtime: Runtime, world: World | None = None, seed: int = 0) -> None:
        """``world`` (with its ``seed``) replaces the scenario file: tests and an in-process
        simulator hand it over; otherwise on_start loads ``config.scenario``."""
        super().__init__(config, runtime)
        self.world = world
        self.seed = seed
        self.published = 0
        self.sensed: SensedTruth[Output] | None = None  # from on_start

    def on_start(self) -> None:
        config = self.config
        if config.sensor not in SENSORS:
            raise ValueError(f"lidar: sensor must be one of {sorted(SENSORS)}, not {config.sensor!r}")
        if not 0 < config.rate_hz <= ScanSpec.scan_rate_hz:
            raise ValueError(f"lidar: rate_hz must be in (0, {ScanSpec.scan_rate_hz}], the scanner's sweep rate")
        if self.world is None:
            scenario = load_scenario(config.scenario)
            self.world, self.seed = scenario.world, scenario.seed
        self.scene = Scene.from_obstacles(self.world.obstacles)
        self.spec = ScanSpec(range_noise_std_m=config.noise_std_m)
        self.sweep_mount = replace(SWEEP_MOUNT, range_noise_std_m=config.noise_std_m)
        vertical = VERTICAL_MOUNTS.get(config.sensor)
        self.vertical_mount = replace(vertical, range_noise_std_m=config.noise_std_m) if vertical else None
        self.entropy = [*_words(self.seed % 2**64), *_words(config.seed_offset % 2**64), SOURCE_IDS[config.sensor]]
        truth = self.input(channels.SIM_TRUTH, TRUTH_MAX_AGE_S)
        self.sensed = SensedTruth(truth, self.world, config.sensor)
        self.every(1.0 / config.rate_hz, self.sweep, priority=1)

    def sweep(self) -> None:
        """Scan from the newest true pose and publish, as the active faults allow
        (modules/sim/sensing.py: one output per new pose at most; a stuck scanner repeats its
        last, so only the content gives it away)."""
        assert self.sensed is not None
        sensed = self.sensed.step(self.now_ns(), self.measure)
        if sensed is not None:
            output, t_meas_ns = sensed
            self.bus.publish(CHANNELS[self.config.sensor], output, t_meas_ns=t_meas_ns)
            self.published += 1

    def measure(self, truth: SimTruth, t_meas_ns: int, noise_scale: float = 1.0) -> Output:
        """What this lidar sees from the vehicle pose in ``truth``. The noise is drawn from a
        generator seeded by (seed, seed_offset, sensor, t_meas_ns): the same truth stream gives
        the same output however the process happens to be scheduled."""
        assert self.world is not None
        sensor = self.config.sensor
        pose = Pose(truth.east_m, truth.north_m, truth.yaw_rad)
        if sensor in HORIZONTAL_MOUNTS:
            scan = cast(self.scene, pose, HORIZONTAL_MOUNTS[sensor], self.spec)
            if scan.returns.size:  # nothing in view, nothing to draw: no generator either
                add_noise(scan, self._rng(t_meas_ns), noise_scale)
            return ObstacleList(int(SENSORS[sensor]), int(Frame.VEHICLE), describe_scan(scan))
        rng = self._rng(t_meas_ns)
        if sensor == "lidar_sweep":
            returns = sweep_scan(self.world.hazards, self.scene, pose, self.sweep_mount, rng, noise_scale)
            return describe_sweep(returns, self.sweep_mount, int(SENSORS[sensor]))
        assert self.vertical_mount is not None
        return profile_scan(self.world.hazards, pose, self.vertical_mount, int(SENSORS[sensor]), rng, noise_scale)

    def _rng(self, t_meas_ns: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence(self._entropy(t_meas_ns)))

    def _entropy(self, t_meas_ns: int) -> np.ndarray:
        """(seed, seed_offset, source id, t_meas_ns) as the 32-bit words SeedSequence makes of
        that list itself: the same generator, without its slow conversion of Python ints."""
        return np.array([*self.entropy, *_words(t_meas_ns % 2**64)], dtype=np.uint32)

    def instance(self) -> str:
        return self.config.sensor

    def status_detail(self) -> str:
        faults = self.sensed.fault_names if self.sensed else ""
        last = self.sensed.gate.last if self.sensed else None
        summary = _summary(last) if last is not None else ""
        return f"{self.config.sensor}: sent {self.published}; {summary}" + (f"; fault {faults}" if faults else "")


def _words(value: int) -> list[int]:
    """A non-negative int as SeedSequence splits it: 32-bit words, least significant first."""
    words = [value & 0xFFFFFFFF]
    value >>= 32
    while value:
        words.append(value & 0xFFFFFFFF)
        value >>= 32
    return words


def _summary(output: Output) -> str:
    """The heartbeat's account of a measurement (worked out once a second, not every scan)."""
    if isinstance(output, ObstacleList):
        return f"{len(output.obstacles)} obstacles"
    if isinstance(output, GroundSweep):
        return _sweep_summary(output)
    return _hazard_summary(detect_hazards(output))


def _hazard_summary(hazards: list[Hazard]) -> str:
    if not hazards:
        return "level ground"
    return ", ".join(f"{h.kind.value} {h.start_range_m:.1f}-{h.end_range_m:.1f} m" for h in hazards)


def _sweep_summary(sweep: GroundSweep) -> str:
    low = sum(1 for stretch in sweep.stretches if stretch.height_m < 0)
    high = sum(1 for stretch in sweep.stretches if stretch.height_m > 0)
    return f"{len(sweep.stretches)} stretches ({low} low, {high} high)"
