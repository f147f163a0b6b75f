"""The simulated stereo camera pair and frame grabber of the ESVS.

On the vehicle, two FireWire cameras deliver frames into the ESVS computer's memory by DMA while
its processor does other work (RASCAL section III). Here a process renders the pair the rig sees
from the newest true pose, and writes it into the named shared-memory frame ring the ESVS reads,
stamped with the pose's measurement time (shared time) as its exposure time. It reads the
simulator's truth, so it is simulation code, like the lidars.

The ESVS's round announces each grab in the ring (its trigger), and the camera then renders one
frame per grab, started so that it is in the ring just before the grab: no frame is rendered
that the ESVS never looks at, and the one it takes is as fresh as the render time allows. With
no live trigger (no ESVS yet, or it stopped grabbing) the camera runs free at ``fps``.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from modules.esvs.frames import DEFAULT_SLOTS, RingWriter, Trigger
from modules.esvs.geometry import RASCAL_RIG
from modules.sim.camera import StereoRenderer
from modules.sim.scenario import DEFAULT_SCENARIO, load_scenario
from modules.sim.sensing import SensedTruth
from modules.sim.world import World
from protocol import channels
from protocol.messages import SimTruth
from rascal.runtime.config import setting
from rascal.runtime.module import Module, Runtime
from rascal.runtime.ports import Port

TRUTH_MAX_AGE_S = 0.5  # the simulator publishes at 100 Hz: older means it stopped
MAX_FPS = 60.0  # the Basler cameras' top rate
FAULT_SENSOR = "esvs"  # scenario fault schedules name the cameras by the system they feed
PHASE_S = 0.2  # how often the camera reads the trigger and, if its grid moved, retimes the exposures
PHASE_TOLERANCE_S = 0.002  # exposures this close to their ideal start are left where they are
STALE_TRIGGER_PERIODS = 3  # a trigger whose latest grab is older than this many of its periods is gone
MARGIN_S = 0.01  # a triggered frame is meant to be in the ring this long before its grab
RENDER_HISTORY = 32  # the slowest of this many recent frames sets how early a triggered frame starts
FIRST_RENDER_S = 0.05  # the render time assumed before the first frame


@dataclass(frozen=True)
class StereoCameraConfig:
    scenario: str = setting(str(DEFAULT_SCENARIO), "scenario file whose world the cameras see")
    fps: float = setting(15.0, "frame rate with no trigger (no ESVS grabbing); triggered: one frame per grab")
    ring_name: str = setting("rascal-stereo", "shared-memory frame ring the ESVS reads")
    ring_slots: int = setting(DEFAULT_SLOTS, "frames the ring holds (a reader may lag this many - 1)")
    seed_offset: int = setting(0, "combined with the scenario seed: change it for independent sensor noise")


class StereoCamera(Module):
    """Simulated stereo cameras: SIM_TRUTH in, rendered pairs into the shared-memory frame ring."""

    name = "stereo_camera"
    default_source_id = 19
    Config = StereoCameraConfig
    interface = (
        Port("in", "`SIM_TRUTH`", "SimTruth (the newest pose is used)", "the simulator's (100 Hz)", "0.5 s"),
        Port("in", "frame ring trigger", "the ESVS round's latest grab and period", "one per grab", "3 periods"),
        Port(
            "out",
            "frame ring `ring_name` (shared memory, `ring_slots` frames)",
            "656x490 grey pair, sequence, exposure time",
            "one per grab (10 Hz), or `fps` (15) untriggered",
        ),
        Port(
            "out",
            "`MODULE_STATUS`",
            "ModuleStatus (frames written, slowest recent frame, triggered or free-running, late frames, active fault)",
            "1 Hz",
        ),
    )

    def __init__(
        self,
        config: StereoCameraConfig,
        runtime: Runtime,
        world: World | None = None,
        seed: int = 0,
        monotonic_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        """``world`` (with its ``seed``) replaces the scenario file, and ``monotonic_ns`` the
        clock the ESVS's trigger is read with, for tests."""
        super().__init__(config, runtime)
        self.world = world
        self.seed = seed
        self.monotonic_ns = monotonic_ns
        self.writer: RingWriter | None = None
        self.sensed: SensedTruth[tuple[np.ndarray, np.ndarray]] | None = None  # from on_start
        self.written = 0
        self.frame_times_ns: deque[int] = deque(maxlen=RENDER_HISTORY)  # render and write, wall time
        self.trigger: Trigger | None = None  # the live trigger the exposures follow, None while running free
        self.start_ns = 0  # a start on the exposures' triggered grid (CLOCK_MONOTONIC)
        self.grab_ns = 0  # the grab the latest triggered frame was for
        self.late = 0  # triggered frames still being made at their grab

    def on_start(self) -> None:
        config = self.config
        if not 0 < config.fps <= MAX_FPS:
            raise ValueError(f"stereo_camera: fps must be in (0, {MAX_FPS}], not {config.fps}")
        if self.world is None:
            scenario = load_scenario(config.scenario)
            self.world, self.seed = scenario.world, scenario.seed
        cv2.setNumThreads(1)  # a simulated device: its cost is one core's work, not spread over all
        self.renderer = StereoRenderer(self.world, RASCAL_RIG)
        # Once, untimed, so that the noise bank and the caches are built before the first frame's
        # time sets how early triggered frames start.
        self.renderer.images((0.0, 0.0, 0.0), np.random.default_rng(0))
        self.writer = RingWriter(config.ring_name, RASCAL_RIG.height_px, RASCAL_RIG.width_px, config.ring_slots)
        truth = self.input(channels.SIM_TRUTH, TRUTH_MAX_AGE_S, SimTruth)
        self.sensed = SensedTruth(truth, self.world, FAULT_SENSOR)
        self.every(1.0 / config.fps, self.tick, priority=1)
        self.every(PHASE_S, self.phase, priority=2)

    def on_stop(self) -> None:
        if self.writer is not None:
            self.writer.close()

    def tick(self) -> None:
        """A frame, free-running or, triggered, for the next grab (counted late if not in time)."""
        trigger = self.trigger
        if trigger is not None:
            now_ns = self.monotonic_ns()
            self.grab_ns = trigger.grab_ns - (trigger.grab_ns - now_ns) // trigger.period_ns * trigger.period_ns
        self.expose()
        if trigger is not None and self.monotonic_ns() > self.grab_ns:
            self.late += 1

    def phase(self) -> None:
        """Put the exposures on the trigger's grid, each a frame's making ahead of its grab; back
        on the free-running grid when the trigger goes. Both grids keep time by themselves (the
        Runtime's and the ESVS's, on one monotonic clock), so this only checks them."""
        assert self.writer is not None
        now_ns = self.monotonic_ns()
        trigger = self.writer.trigger()
        if trigger is not None and now_ns - trigger.grab_ns > STALE_TRIGGER_PERIODS * trigger.period_ns:
            trigger = None
        if trigger is None:
            if self.trigger is not None:
                self.runtime.set_period("tick", 1.0 / self.config.fps)
            self.trigger = None
            return
        period_ns = trigger.period_ns
        lead_ns = max(self.frame_times_ns, default=int(FIRST_RENDER_S * 1e9)) + int(MARGIN_S * 1e9)
        start_ns = trigger.grab_ns - lead_ns  # one ideal start; the others are whole periods away
        if self.trigger is not None and self.trigger.period_ns == period_ns:
            off_ns = (start_ns - self.start_ns) % period_ns
            if min(off_ns, period_ns - off_ns) <= PHASE_TOLERANCE_S * 1e9:
                return
        # The first grab whose start is still ahead, and never one already given a frame.
        grab_ns = start_ns + lead_ns + -(-(now_ns - start_ns) // period_ns) * period_ns
        grab_ns = max(grab_ns, self.grab_ns + period_ns)
        self.runtime.set_period("tick", period_ns / 1e9, first_in_s=(grab_ns - lead_ns - now_ns) / 1e9)
        self.trigger, self.start_ns = trigger, grab_ns - lead_ns

    def expose(self) -> None:
        """One frame from the newest true pose, at most one per pose, as the faults allow (a stuck
        grabber hands out its last buffer again under a new time stamp: modules/sim/sensing.py)."""
        assert self.sensed is not None and self.writer is not None
        sensed = self.sensed.step(self.now_ns(), self.render)
        if sensed is not None:
            (left, right), t_meas_ns = sensed
            self.writer.write(left, right, t_meas_ns)
            self.written += 1

    def render(self, truth: SimTruth, t_meas_ns: int, noise_scale: float) -> tuple[np.ndarray, np.ndarray]:
        """The pair the cameras expose at the true pose, its noise seeded by the pose's time."""
        entropy = [self.seed % 2**64, self.config.seed_offset % 2**64, self.default_source_id, t_meas_ns % 2**64]
        rng = np.random.default_rng(np.random.SeedSequence(entropy))
        start = time.perf_counter_ns()
        pair = self.renderer.images((truth.east_m, truth.north_m, truth.yaw_rad), rng, noise_gain=noise_scale)
        self.frame_times_ns.append(time.perf_counter_ns() - start)
        return pair

    def status_detail(self) -> str:
        seq = self.writer.seq if self.writer is not None else 0
        slowest = max(self.frame_times_ns, default=0) / 1e6
        text = f"ring {self.config.ring_name!r} frames {self.written} (seq {seq}); render {slowest:.0f} ms"
        if self.trigger is not None:
            text += f"; triggered every {self.trigger.period_ns / 1e6:.0f} ms, {self.late} late"
        else:
            text += f"; free-running {self.config.fps:g} fps"
        fault = self.sensed.fault_names if self.sensed else ""
        return text + (f"; fault {fault}" if fault else "")
