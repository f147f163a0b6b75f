"""The simulated stereo camera pair and frame grabber of the ESVS.

On the vehicle, two FireWire cameras deliver frames into the ESVS computer's memory by DMA while
its processor does other work (RASCAL section III). Here a process renders, at the camera frame
rate, the pair the rig sees from the newest true pose, and writes it into the named
shared-memory frame ring the ESVS reads, stamped with the pose's measurement time (shared time)
as its exposure time. It reads the simulator's truth, so it is simulation code, like the lidars.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from modules.esvs.camera import StereoRenderer
from modules.esvs.frames import DEFAULT_SLOTS, RingWriter
from modules.esvs.geometry import RASCAL_RIG
from modules.sim.scenario import DEFAULT_SCENARIO, load_scenario
from modules.sim.world import FaultKind, World
from protocol import channels
from protocol.messages import SimTruth
from rascal.config import setting
from rascal.module import Module, Runtime
from rascal.rtdb import Validity

TRUTH_MAX_AGE_S = 0.5  # the simulator publishes at 100 Hz: older means it stopped
MAX_FPS = 60.0  # the Basler cameras' top rate
FAULT_SENSOR = "esvs"  # scenario fault schedules name the cameras by the system they feed


@dataclass(frozen=True)
class StereoCameraConfig:
    scenario: str = setting(str(DEFAULT_SCENARIO), "scenario file whose world the cameras see")
    fps: float = setting(15.0, "camera frame rate (the renderer manages >= 20 pairs/s)")
    ring_name: str = setting("rascal-stereo", "shared-memory frame ring the ESVS reads")
    ring_slots: int = setting(DEFAULT_SLOTS, "frames the ring holds (a reader may lag this many - 1)")
    seed_offset: int = setting(0, "combined with the scenario seed: change it for independent sensor noise")


class StereoCamera(Module):
    """Simulated stereo cameras: SIM_TRUTH in, rendered pairs into the shared-memory frame ring."""

    name = "stereo_camera"
    default_source_id = 19
    Config = StereoCameraConfig

    def __init__(self, config: StereoCameraConfig, runtime: Runtime, world: World | None = None, seed: int = 0) -> None:
        """``world`` (with its ``seed``) replaces the scenario file, for tests."""
        super().__init__(config, runtime)
        self.world = world
        self.seed = seed
        self.writer: RingWriter | None = None
        self.last_truth_ns: int | None = None
        self.last_pair: tuple[np.ndarray, np.ndarray] | None = None  # what a STUCK fault repeats
        self.written = 0
        self.render_s = 0.0
        self.fault = ""

    def on_start(self) -> None:
        config = self.config
        if not 0 < config.fps <= MAX_FPS:
            raise ValueError(f"stereo_camera: fps must be in (0, {MAX_FPS}], not {config.fps}")
        if self.world is None:
            scenario = load_scenario(config.scenario)
            self.world, self.seed = scenario.world, scenario.seed
        self.renderer = StereoRenderer(self.world, RASCAL_RIG)
        self.writer = RingWriter(config.ring_name, RASCAL_RIG.height_px, RASCAL_RIG.width_px, config.ring_slots)
        self.truth = self.input(channels.SIM_TRUTH, TRUTH_MAX_AGE_S, SimTruth)
        self.every(1.0 / config.fps, self.expose, priority=1)

    def on_stop(self) -> None:
        if self.writer is not None:
            self.writer.close()

    def expose(self) -> None:
        """One frame from the newest true pose, at most one per pose, as the faults allow."""
        reading = self.truth.read(self.now_ns())
        if reading.validity is not Validity.FRESH or reading.envelope is None:
            return
        truth: SimTruth = reading.value
        t_meas_ns = reading.envelope.t_meas_ns
        if t_meas_ns == self.last_truth_ns:
            return
        self.last_truth_ns = t_meas_ns
        assert self.world is not None and self.writer is not None
        faults = self.world.faults_for(FAULT_SENSOR, truth.scenario_time_s, truth.progress_m)
        kinds = {fault.kind for fault in faults}
        self.fault = ",".join(sorted(kind.value for kind in kinds))
        if FaultKind.SILENCE in kinds:
            return
        if FaultKind.STUCK in kinds:
            # A stuck grabber hands out its last buffer again under a new time stamp.
            if self.last_pair is not None:
                self.writer.write(*self.last_pair, t_meas_ns)
                self.written += 1
            return
        entropy = [self.seed % 2**64, self.config.seed_offset % 2**64, self.default_source_id, t_meas_ns % 2**64]
        rng = np.random.default_rng(np.random.SeedSequence(entropy))
        start = time.perf_counter()
        frame = self.renderer.render((truth.east_m, truth.north_m, truth.yaw_rad), rng)
        left, right = frame.left, frame.right
        extra = np.prod([fault.magnitude for fault in faults if fault.kind is FaultKind.NOISE])
        if extra > 1.0:
            # NOISE multiplies the sensor noise: add the difference on top of the rendered noise.
            std = self.renderer.config.noise_std_dn * float(np.sqrt(extra**2 - 1.0))
            left, right = (_noisy(image, std, rng) for image in (left, right))
        self.render_s = time.perf_counter() - start
        self.writer.write(left, right, t_meas_ns)
        self.last_pair = (left, right)
        self.written += 1

    def status_detail(self) -> str:
        seq = self.writer.seq if self.writer is not None else 0
        text = f"ring {self.config.ring_name!r} frames {self.written} (seq {seq}); render {self.render_s * 1e3:.0f} ms"
        return text + (f"; fault {self.fault}" if self.fault else "")


def _noisy(image: np.ndarray, std: float, rng: np.random.Generator) -> np.ndarray:
    noisy = image.astype(np.float32) + rng.normal(0.0, std, image.shape).astype(np.float32)
    return np.clip(noisy + 0.5, 0, 255).astype(np.uint8)
