"""ESVS real-time framework: inter-activation jitter of the vision processes, monolithic against
CAMBADA's modular split (CAMBADA Tables 1 and 3), under background CPU load; and how long the
watchdog takes from a killed vision worker to the next report of a new frame.

A camera process writes pre-rendered stereo pairs of the default scenario into the shared-memory
ring at the round rate; two busy-loop processes load the CPU for the whole run (stopped after);
the ESVS runs in this process on a private loopback bus. Each configuration runs for ``--duration``:

* monolithic, default scheduling: one worker runs the whole pipeline when the round hands it a
  frame (CAMBADA's original architecture: a frame is taken only after the previous is done);
* monolithic, SCHED_FIFO: the same with the round above the worker (RASCAL's priorities);
* CAMBADA, default scheduling / SCHED_FIFO: obstacle worker every round (priority 45), lane
  worker every second round (priority 25, offset half a round), each on its own timer.

Per process: period, activations (after the first second), mean / min / max / standard deviation
of the intervals between them, execution time, and watchdog restarts (a worker starved past its
hang timeout is killed and replaced). SCHED_FIFO rows fall back to nice values where the OS
refuses (the sched column says which).
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import random
import signal
import statistics
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from multiprocessing.synchronize import Event

import numpy as np
from rich.console import Console

from benchmarks.report import Table, machine_line, print_table
from modules.esvs import scheduling
from modules.esvs.frames import RingWriter
from modules.esvs.geometry import RASCAL_RIG
from modules.esvs.module import Esvs
from modules.esvs.settings import EsvsConfig
from modules.sim.camera import render_pair
from modules.sim.scenario import load_scenario
from protocol.auth import Keyring
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from rascal.runtime.module import Runtime

FRAMES = 6
KILLS = 3
KILLER_PERIOD_S = 0.005  # how finely the kills are placed
CAMERA_PRIORITY = 60  # above the round (50) and every worker
CAMERA_RATE = 1.5  # camera frames per round: every round finds a new frame
SETTLE_NS = 1_000_000_000  # statistics leave out the first second (start-up)
INTERVAL_COLUMNS = ["architecture", "process", "period", "sched", "n", "mean", "min", "max", "std"]


@dataclass(frozen=True)
class Setup:
    label: str
    mode: str
    sched: str


SETUPS = [
    Setup("monolithic", "monolithic", "none"),
    Setup("monolithic", "monolithic", "fifo"),
    Setup("CAMBADA", "cambada", "none"),
    Setup("CAMBADA", "cambada", "fifo"),
]


class TimedEsvs(Esvs):
    """The ESVS with its round activations and published reports recorded."""

    def on_start(self) -> None:
        self.round_ns: list[int] = []
        self.sent: list[tuple[int, int]] = []  # (CLOCK_MONOTONIC when sent, exposure time)
        super().on_start()

    def round(self) -> None:
        self.round_ns.append(time.monotonic_ns())
        super().round()

    def _send(self) -> None:  # at the round and at each quarter-round watch
        pending = self.pending_obstacles
        super()._send()
        if pending is not None:
            self.sent.append((time.monotonic_ns(), pending.t_exposure_ns))


def render_frames(count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Pairs from the first metres of the default scenario's route, a metre apart."""
    scenario = load_scenario()
    east, north, yaw = scenario.start_pose()
    rng = np.random.default_rng(2005)
    return [
        (frame.left, frame.right)
        for frame in (
            render_pair(scenario.world, (east + k * math.cos(yaw), north + k * math.sin(yaw), yaw), RASCAL_RIG, rng)
            for k in range(count)
        )
    ]


def camera(ring_name: str, frames: list[tuple[np.ndarray, np.ndarray]], fps: float, stop: Event) -> None:
    """The frame grabber: the pairs in turn, at ``fps``, stamped with wall-clock exposure time.
    It stands for hardware (cameras and DMA), so it runs above everything else where allowed:
    the load must not reach the measurements through missing frames."""
    scheduling.apply("fifo", CAMERA_PRIORITY, 0)
    writer = RingWriter(ring_name, RASCAL_RIG.height_px, RASCAL_RIG.width_px)
    try:
        period, due, k = 1.0 / fps, time.monotonic(), 0
        while not stop.is_set():
            left, right = frames[k % len(frames)]
            writer.write(left, right, time.time_ns())
            k += 1
            due += period
            stop.wait(max(0.0, due - time.monotonic()))
    finally:
        writer.close()


def busy(stop: Event, end_s: float) -> None:
    """Background load: spin until told to stop (or the deadline, whichever is first)."""
    while time.monotonic() < end_s and not stop.is_set():
        pass


def run_esvs(config: EsvsConfig, duration_s: float, kills: int = 0) -> TimedEsvs:
    """The ESVS in this process for ``duration_s``; ``kills`` SIGKILLs of its vision worker,
    spread over the run's second half."""
    # A private loopback multicast bus, not mem://: that one never blocks in poll, so the
    # Runtime would spin, and a spinning real-time round gets throttled by the kernel.
    url = f"udpm://239.255.{random.randint(0, 255)}.{random.randint(1, 254)}:{random.randrange(20000, 60000, 16)}?ttl=0"
    runtime = Runtime(Bus.open(url, source_id=20, clock=MasterClock(), keyring=Keyring.generate()), MasterClock())
    esvs = TimedEsvs(config, runtime)
    if kills:
        start: list[float] = []
        # Spread over the second half, each at a different phase of the round (seeded).
        phases = np.random.default_rng(kills).uniform(0.0, config.round_period_s, kills)
        times = [duration_s * (0.4 + 0.5 * k / kills) + phases[k] for k in range(kills)]
        esvs.kills_ns: list[int] = []  # type: ignore[misc]

        def killer() -> None:
            start[:] = start or [time.monotonic()]
            if times and time.monotonic() - start[0] >= times[0]:
                times.pop(0)
                assert esvs.watchdog is not None
                esvs.kills_ns.append(time.monotonic_ns())  # type: ignore[attr-defined]
                os.kill(esvs.watchdog.workers["vision"].pid, signal.SIGKILL)

        runtime.add_task("killer", killer, KILLER_PERIOD_S)
    try:
        runtime.run(esvs, duration_s)
    finally:
        # The round may have made this process real-time; the next setup starts from scratch.
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    return esvs


def interval_row(
    label: str, process: str, period_ms: float, sched: str, times_ns: list[int], exec_s: list[float], restarts: str
) -> list[str]:
    """One table row: the intervals between consecutive activations, and execution times."""
    intervals = np.diff(np.asarray(times_ns, dtype=np.int64)) / 1e6
    head = [label, process, f"{period_ms:.0f}", sched, str(len(times_ns))]
    if intervals.size < 2:
        return [*head, *["-"] * 6, restarts]
    execution = [f"{statistics.fmean(exec_s) * 1e3:.1f}", f"{max(exec_s) * 1e3:.1f}"] if exec_s else ["-", "-"]
    spread = [f"{value:.1f}" for value in (intervals.mean(), intervals.min(), intervals.max(), intervals.std())]
    return [*head, *spread, *execution, restarts]


def measure(setup: Setup, ring_name: str, args: argparse.Namespace) -> list[list[str]]:
    config = EsvsConfig(mode=setup.mode, sched=setup.sched, ring_name=ring_name, round_period_s=args.round_period)
    esvs = run_esvs(config, args.duration)
    assert esvs.watchdog is not None
    period_ms = args.round_period * 1e3
    settled_ns = esvs.round_ns[0] + SETTLE_NS
    rounds = [t for t in esvs.round_ns if t >= settled_ns]
    rows = [interval_row(setup.label, "round", period_ms, esvs.scheduling, rounds, [], "-")]
    periods = {"vision": 1, **{role: rounds for role, (rounds, _o, _p) in config.worker_timing().items()}}
    for role, reports in esvs.activations.items():
        worker = esvs.watchdog.workers[role]
        settle = [r for r in reports if r.activated_ns >= settled_ns]
        rows.append(
            interval_row(
                setup.label,
                role,
                periods[role] * period_ms,
                worker.scheduling.split(" (")[0],
                [r.activated_ns for r in settle],
                [r.compute_s for r in settle if r.seq],
                str(worker.restarts),
            )
        )
    return rows


def watchdog_row(ring_name: str, args: argparse.Namespace) -> list[str]:
    """Kill the monolithic worker ``KILLS`` times; time to the next report of a frame newer than
    the last one reported before the kill, and of a frame exposed after it."""
    config = EsvsConfig(sched="fifo", ring_name=ring_name, round_period_s=0.1)
    esvs = run_esvs(config, args.watchdog_duration, kills=KILLS)
    offset_ns = time.time_ns() - time.monotonic_ns()  # exposure times are wall clock
    newer, exposed = [], []
    for kill_ns in esvs.kills_ns:  # type: ignore[attr-defined]
        before = [exposure for sent, exposure in esvs.sent if sent <= kill_ns]
        after = [(sent, exposure) for sent, exposure in esvs.sent if sent > kill_ns]
        last = max(before, default=0)
        newer += [(min(s for s, e in after if e > last) - kill_ns) / 1e6] if any(e > last for _s, e in after) else []
        late = [s for s, e in after if e - offset_ns > kill_ns]
        exposed += [(min(late) - kill_ns) / 1e6] if late else []
    assert esvs.watchdog is not None

    def summary(delays: list[float]) -> list[str]:
        if not delays:
            return ["-", "-", "-"]
        return [f"{statistics.fmean(delays):.0f}", f"{max(delays):.0f}", " ".join(f"{d:.0f}" for d in delays)]

    return ["monolithic, 100 ms round", str(esvs.watchdog.restarts), *summary(newer), *summary(exposed)]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_cambada", description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=7.0, help="seconds per configuration")
    parser.add_argument("--round-period", type=float, default=0.05, help="ESVS round (CAMBADA: 50 ms frames)")
    parser.add_argument("--load", type=int, default=2, help="busy-loop processes in the background")
    parser.add_argument("--watchdog-duration", type=float, default=5.0, help="seconds of the kill run (0: skip)")
    args = parser.parse_args(argv)
    console = Console()
    console.print(machine_line("ESVS real-time", f"{args.load} busy loops"), markup=False, highlight=False)
    context = multiprocessing.get_context("spawn")
    frames = render_frames(FRAMES)
    ring_name = f"rascal-bench-{uuid.uuid4().hex[:10]}"
    stop = context.Event()
    end_s = time.monotonic() + len(SETUPS) * (args.duration + 5) + args.watchdog_duration + 10
    fps = CAMERA_RATE / args.round_period
    helpers = [context.Process(target=camera, args=(ring_name, frames, fps, stop))]
    helpers += [context.Process(target=busy, args=(stop, end_s)) for _ in range(args.load)]
    for helper in helpers:
        helper.start()
    try:
        table = Table(
            f"Inter-activation intervals (ms) under {args.load} busy loops, {args.duration:.0f} s each",
            [*INTERVAL_COLUMNS, "exec mean", "exec max", "restarts"],
        )
        for setup in SETUPS:
            for row in measure(setup, ring_name, args):
                table.add(*row)
        print_table(console, table)
        if args.watchdog_duration > 0:
            kills = Table(
                "Watchdog: SIGKILL of the vision worker -> next report of a newer frame, of one exposed after it (ms)",
                ["ESVS", "restarts", "newer mean", "max", "each", "exposed after mean", "max", "each"],
            )
            kills.add(*watchdog_row(ring_name, args))
            print_table(console, kills)
    finally:
        stop.set()
        for helper in helpers:
            helper.join(5)
            if helper.exitcode is None:
                helper.kill()
                helper.join()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
