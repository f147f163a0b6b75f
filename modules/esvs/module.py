"""The ESVS process: RASCAL's time-triggered round around a supervised vision worker.

Every ``round_period_s`` the round runs, in RASCAL's order (section III):

1. **timer**: the Runtime activates the round on its grid (period, jitter and overruns go into
   ModuleStatus);
2. **grab**: note the newest frame in the camera's shared-memory ring; never wait for one;
3. **receive**: read the newest VEHICLE_STATE (recorded and reported by age only);
4. **send**: publish the last completed report, once: OBSTACLES_ESVS and LANE_BORDERS stamped
   with the frame's exposure time;
5. **process**: hand the new frame to the vision worker (monolithic), which copies it from the
   ring and works while the round sleeps. In CAMBADA mode the obstacle and lane workers run on
   their own timers instead.

The watchdog runs at the start of each round and at each further quarter round: a worker that
crashed or hung is killed and replaced by its hot spare while the round and the heartbeat go on.
Those quarter-round activations also send a report that has come in, rather than hold it for the
next round's send step: obstacle-to-actuator latency is the ESVS's first consumer.
"""

from __future__ import annotations

import statistics
import time
from collections import deque
from multiprocessing.context import BaseContext
from typing import NamedTuple

from modules.esvs import scheduling
from modules.esvs.frames import FrameInfo, RingReader
from modules.esvs.geometry import RASCAL_RIG
from modules.esvs.settings import INJECT_KEY, EsvsConfig, check_config, updated, vision_params
from modules.esvs.watchdog import Supervised, Watchdog, worker_context
from modules.esvs.worker import FAULTS, Inject, Process, Report, Retime, SetParams, WorkerSpec
from protocol import channels
from protocol.codec import Envelope
from protocol.messages import ConfigUpdate, LaneBorders, ModuleState, ObstacleList, Severity, VehicleState
from rascal.runtime.config import ConfigError
from rascal.runtime.module import Module, Runtime
from rascal.runtime.ports import Port
from rascal.runtime.rtdb import Validity

ACTIVATION_HISTORY = 4096  # per worker, for inter-activation statistics
CAMERA_SILENT_S = 1.0  # no new frame for this long: the module reports itself DEGRADED
# The watchdog looks at the workers at the round's start and this many - 1 times between rounds
# (tasks of the round's period at staggered offsets, so ModuleStatus still reports the round).
WATCHES_PER_ROUND = 4
RIG_SHAPE = (RASCAL_RIG.height_px, RASCAL_RIG.width_px)  # frames of another size are not processed


def _newer(exposed_ns: int, pending: Pending | None, sent_ns: int) -> bool:
    """Whether a report of the frame exposed at ``exposed_ns`` replaces what waits to be sent."""
    return exposed_ns != sent_ns and (pending is None or exposed_ns > pending.t_exposure_ns)


class Pending(NamedTuple):
    """A completed report waiting for the round's send step."""

    message: ObstacleList | LaneBorders
    t_exposure_ns: int  # shared time: it orders frames across camera restarts too


class Esvs(Module):
    """Embedded stereo vision system: camera frames in, OBSTACLES_ESVS and LANE_BORDERS out."""

    name = "esvs"
    default_source_id = 20
    Config = EsvsConfig
    interface = (
        Port(
            "in",
            "frame ring `ring_name` (shared memory)",
            "stereo pair 656x490 grey, sequence, exposure time",
            "one per round (the camera is triggered by the grabs)",
            "newest frame only; silent 1 s: DEGRADED",
        ),
        Port("out", "frame ring trigger", "this grab's time and the round period, for the camera", "one per round"),
        Port(
            "in",
            "`VEHICLE_STATE`",
            "VehicleState (recorded; its age is reported in status)",
            "the INS's",
            "`vehicle_state_max_age_s` (0.5 s)",
        ),
        Port("in", "`CONFIG`", "ConfigUpdate for `esvs` (live keys below)", "on demand"),
        Port(
            "out",
            "`OBSTACLES_ESVS`",
            "ObstacleList (`ESVS`, VEHICLE frame), `t_meas_ns` = exposure time",
            "one per round with a new result",
        ),
        Port(
            "out",
            "`LANE_BORDERS`",
            "LaneBorders (`ESVS`, VEHICLE frame), `t_meas_ns` = exposure time",
            "one per round with a new result",
        ),
        Port(
            "out",
            "`HEALTH`",
            "`worker_started`, `worker_restart`, `config`, `config_rejected`, `fault_injected`",
            "on event",
        ),
        Port(
            "out",
            "`MODULE_STATUS`",
            "ModuleStatus: round period, jitter, overruns, worker restarts; detail below",
            "1 Hz",
        ),
    )

    def __init__(self, config: EsvsConfig, runtime: Runtime, context: BaseContext | None = None) -> None:
        """``context`` (a multiprocessing context) replaces the fork server, for tests."""
        super().__init__(config, runtime)
        self.context = context
        self.base_restarts = runtime.restarts
        self.reader: RingReader | None = None
        self.watchdog: Watchdog | None = None
        self.grabbed: FrameInfo | None = None
        self.handed = True  # the grabbed frame went to the worker (or there is none)
        self.pending_obstacles: Pending | None = None  # the last completed reports, not yet sent
        self.pending_lanes: Pending | None = None
        # Exposure of the last report sent on each channel: a frame reported twice (its worker
        # died as the report came in, and the replacement got the frame too) is sent once. Only
        # equal, not older: a time master restarted on another clock may step shared time back.
        self.sent_obstacles_ns = -1
        self.sent_lanes_ns = -1
        self.frames_grabbed = 0
        self.frames_unseen = 0  # written by the camera between two grabs
        self.frames_processed = 0
        self.reports_sent = 0
        self.vehicle_state: VehicleState | None = None
        self.scheduling = ""
        self.activations: dict[str, deque[Report]] = {}
        self.wrong_ring = 0  # generation of a ring whose frames do not fit the rig (reported once)

    # -- lifecycle ------------------------------------------------------------------------------

    def on_start(self) -> None:
        config = self.config
        check_config(config)
        self.reader = RingReader(config.ring_name)
        self.vehicle = self.bus.latest(channels.VEHICLE_STATE, int(config.vehicle_state_max_age_s * 1e9), VehicleState)
        self.bus.subscribe(channels.CONFIG, self.on_config)
        self.epoch_ns = time.monotonic_ns()
        specs = self._specs()
        self.activations = {spec.role: deque(maxlen=ACTIVATION_HISTORY) for spec in specs}
        self.watchdog = Watchdog(
            self.context or worker_context(),
            specs,
            config.hang_timeout_s(),
            config.startup_timeout_s,
            self.report,
        )
        self.watchdog.start()
        # After the fork server exists, and reset on fork: no worker inherits the round's class.
        self.scheduling = scheduling.apply(config.sched, config.round_priority, 0, reset_on_fork=True)
        self.every(config.round_period_s, self.round, priority=5)
        for k in range(1, WATCHES_PER_ROUND):
            self.every(
                config.round_period_s, self.watch, offset_s=config.round_period_s * k / WATCHES_PER_ROUND, priority=6
            )

    def on_stop(self) -> None:
        if self.watchdog is not None:
            self.watchdog.stop()
        if self.reader is not None:
            self.reader.close()

    def _specs(self) -> list[WorkerSpec]:
        config = self.config
        params = vision_params(config)
        if config.mode == "monolithic":
            return [
                WorkerSpec(
                    "vision",
                    config.ring_name,
                    params,
                    policy=config.sched,
                    priority=config.vision_priority,
                    nice=scheduling.fallback_nice(config.vision_priority, config.round_priority),
                )
            ]
        timing = config.worker_timing()
        top = max(priority for _rounds, _offset, priority in timing.values())
        return [
            WorkerSpec(
                role,
                config.ring_name,
                params,
                policy=config.sched,
                priority=priority,
                nice=scheduling.fallback_nice(priority, top),
                period_ns=int(rounds * config.round_period_s * 1e9),
                offset_ns=int(offset * 1e9),
                epoch_ns=self.epoch_ns,
            )
            for role, (rounds, offset, priority) in timing.items()
        ]

    # -- the round ------------------------------------------------------------------------------

    def round(self) -> None:
        self._supervise()
        self._grab()
        self._receive()
        self._send()
        self._process()

    def watch(self) -> None:
        """The watchdog's own activations between rounds: a dead worker is replaced within a
        quarter round, a report that came in goes out now, and a worker that became free gets
        the grabbed frame now rather than a round later."""
        self._supervise()
        self._send()
        self._process()

    def _supervise(self) -> None:
        assert self.watchdog is not None
        restarts = self.watchdog.restarts
        for report in self.watchdog.check():
            self._collect(report)
        if self.watchdog.restarts != restarts:
            self.handed = False  # the frame the dead worker had goes to its replacement
        self.runtime.restarts = self.base_restarts + self.watchdog.restarts

    def _collect(self, report: Report) -> None:
        self.activations[report.role].append(report)
        if report.seq == 0:
            return
        if report.role in ("vision", "obstacles"):
            self.frames_processed += 1
        exposed = report.t_exposure_ns
        if report.obstacles is not None and _newer(exposed, self.pending_obstacles, self.sent_obstacles_ns):
            self.pending_obstacles = Pending(report.obstacles, exposed)
        if report.lanes is not None and _newer(exposed, self.pending_lanes, self.sent_lanes_ns):
            self.pending_lanes = Pending(report.lanes, exposed)

    def _grab(self) -> None:
        assert self.reader is not None
        info = self.reader.newest()
        # The camera renders one frame per grab, finished just before it: tell it our grid.
        self.reader.trigger(int(self.config.round_period_s * 1e9))
        if info is None or (self.grabbed is not None and info[:2] == self.grabbed[:2]):
            return
        if self.reader.shape != RIG_SHAPE:
            if self.reader.generation != self.wrong_ring:
                self.wrong_ring = self.reader.generation
                self.report(
                    Severity.ERROR,
                    "frame_size",
                    f"frame ring {self.config.ring_name!r} holds {self.reader.shape[1]}x{self.reader.shape[0]} "
                    f"frames; the rig is {RIG_SHAPE[1]}x{RIG_SHAPE[0]}",
                )
            return
        if self.grabbed is not None and info.generation == self.grabbed.generation:
            self.frames_unseen += max(0, info.seq - self.grabbed.seq - 1)
        self.grabbed = info
        self.handed = False
        self.frames_grabbed += 1

    def _receive(self) -> None:
        # The algorithms do not use the vehicle state yet; the round keeps the newest valid one.
        self.vehicle_state = self.vehicle.fresh(self.now_ns())

    def _send(self) -> None:
        obstacles, lanes = self.pending_obstacles, self.pending_lanes
        if obstacles is not None:
            self.bus.publish(channels.OBSTACLES_ESVS, obstacles.message, t_meas_ns=obstacles.t_exposure_ns)
            self.pending_obstacles, self.sent_obstacles_ns = None, obstacles.t_exposure_ns
            self.reports_sent += 1
        if lanes is not None:
            self.bus.publish(channels.LANE_BORDERS, lanes.message, t_meas_ns=lanes.t_exposure_ns)
            self.pending_lanes, self.sent_lanes_ns = None, lanes.t_exposure_ns
        self.runtime.state = self._state()

    def _process(self) -> None:
        if self.config.mode != "monolithic" or self.handed or self.grabbed is None:
            return
        assert self.watchdog is not None
        worker = self.watchdog.workers["vision"]
        if worker.idle and worker.send(Process(self.grabbed.generation, self.grabbed.seq)):
            self.handed = True

    def _state(self) -> ModuleState:
        assert self.watchdog is not None
        camera_silent = self.grabbed is None or time.monotonic_ns() - self.grabbed.written_ns > CAMERA_SILENT_S * 1e9
        workers_ready = all(worker.ready for worker in self.watchdog.workers.values())
        return ModuleState.OK if workers_ready and not camera_silent else ModuleState.DEGRADED

    # -- configuration --------------------------------------------------------------------------

    def on_config(self, message: ConfigUpdate, _envelope: Envelope) -> None:
        if message.module not in (self.name, f"{self.name}/{self.instance()}"):
            return
        if message.key == INJECT_KEY:
            self._inject(message.value)
            return
        try:
            config = updated(self.config, message.key, message.value)
        except (ConfigError, ValueError) as exc:
            self.report(Severity.WARNING, "config_rejected", f"{message.key}={message.value!r} rejected: {exc}")
            return
        before = getattr(self.config, message.key)
        self.config = config
        self._apply(message.key)
        self.report(Severity.INFO, "config", f"{message.key} changed from {before} to {getattr(config, message.key)}")

    def _apply(self, key: str) -> None:
        assert self.watchdog is not None
        config = self.config
        if key in ("round_period_s", "hang_rounds", "hang_min_s"):
            self.watchdog.set_hang_timeout(config.hang_timeout_s())
        if key == "round_period_s":
            self._retime(config.round_period_s)
            for spec in self._specs():
                if spec.periodic:
                    retime = Retime(spec.period_ns, spec.offset_ns, spec.epoch_ns)
                    self.watchdog.broadcast(retime, roles=(spec.role,))
        if key in ("max_range_m", "min_obstacle_points", "lane_hot"):
            self.watchdog.broadcast(SetParams(vision_params(config)))

    def _retime(self, period_s: float) -> None:
        """Move the round and the watchdog's checks to a new period, staggered as at the start."""
        self.runtime.set_period("round", period_s)
        quarter = period_s / WATCHES_PER_ROUND
        self.runtime.set_period("watch", period_s, first_in_s=period_s + quarter, stagger_s=quarter)

    def _inject(self, value: str) -> None:
        """``hang`` or ``crash``, optionally ``:role``: the next activation of that worker hangs
        (sleeps a minute) or exits. Refused unless allow_fault_injection is set."""
        assert self.watchdog is not None
        fault, _, role = value.partition(":")
        role = role or ("vision" if self.config.mode == "monolithic" else "obstacles")
        if not self.config.allow_fault_injection:
            self.report(Severity.WARNING, "config_rejected", f"{INJECT_KEY}: fault injection is disabled")
        elif fault not in FAULTS or role not in self.watchdog.workers:
            self.report(
                Severity.WARNING,
                "config_rejected",
                f"{INJECT_KEY}={value!r}: expected one of {FAULTS}, optionally :{'|'.join(self.watchdog.workers)}",
            )
        else:
            self.watchdog.broadcast(Inject(fault), roles=(role,))
            self.report(Severity.WARNING, "fault_injected", f"{role} worker: {fault} on its next activation")

    # -- status ---------------------------------------------------------------------------------

    def status_detail(self) -> str:
        if self.watchdog is None:
            return "starting"
        config = self.config
        dropped = max(0, self.frames_grabbed - self.frames_processed)
        parts = [
            f"{config.mode} round {config.round_period_s * 1e3:.0f} ms ({self.scheduling})",
            f"frames grabbed {self.frames_grabbed} processed {self.frames_processed} dropped {dropped} "
            f"unseen {self.frames_unseen}",
            f"reports sent {self.reports_sent}; worker restarts {self.watchdog.restarts}",
        ]
        parts += [self._worker_status(worker) for worker in self.watchdog.workers.values()]
        parts.append(self._vehicle_status())
        if self.reader is not None and not self.reader.attached and self.runtime.state is not ModuleState.STOPPING:
            parts.append(f"no frame ring {config.ring_name!r}")
        return "; ".join(parts)

    def _worker_status(self, worker: Supervised) -> str:
        recent = [r.compute_s for r in list(self.activations[worker.role])[-50:] if r.seq]
        compute = f" exec {statistics.fmean(recent) * 1e3:.0f} ms" if recent else ""
        state = "ready" if worker.ready else "starting"
        spare = "spare ready" if worker.spare is not None and worker.spare.ready else "no spare yet"
        if worker.backoff > 1:
            spare += f"; hang timeout {worker.timeout_ns / 1e6:.0f} ms after back-off"
        return (
            f"{worker.role} pid {worker.pid} {state} {worker.scheduling or '?'}{compute} "
            f"(crashes {worker.crashes}, hangs {worker.hangs}; {spare})"
        )

    def _vehicle_status(self) -> str:
        reading = self.vehicle.read(self.now_ns())
        if reading.validity is Validity.NEVER or reading.age_ns is None:
            return "no vehicle state"
        word = "age" if reading.validity is Validity.FRESH else "stale, age"
        return f"vehicle state {word} {reading.age_ns / 1e9:.2f} s"
