"""The supervisor: starts one host's modules as processes and keeps them alive.

It is itself a module on the bus (it hears every heartbeat and reports what it does as
HealthEvents). A child that exits, or whose heartbeat has been silent for its
``heartbeat_timeout_s`` (hung: it gets SIGKILL first), is restarted: at once the first time,
then with a doubling back-off while it keeps failing within ``STABLE_S`` of its last start, so a
module that crashes on start cannot spin. Each child is told its restart count (``--restarts``),
which it reports in its own heartbeat. Each heartbeat's CPU (% of one core, children included)
is kept for the run's summary and held to the child's budget: over it for ``CPU_BUDGET_BEATS``
heartbeats in a row (10 s) is a WARNING HealthEvent ``cpu_budget``, once until it comes back under.

Each child gets its own module key file (``RUN_DIR/keys/LABEL.key``, owner-only, removed when the
run ends) as its ``RASCAL_KEY_FILE``: the MAC keys, the child's own signing key and the
deployment's authority table, derived from the master file the supervisor holds; never the master
nor another module's key. With a legacy key file (no ``signing_master``) children get that file,
as before command authority, and the supervisor warns once.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from protocol import channels
from protocol.auth import Keyring, write_keyring
from protocol.authority import Authority
from protocol.codec import Envelope
from protocol.messages import ModuleState, ModuleStatus, Severity
from rascal.runtime.deployment import SUPERVISOR_SOURCE_ID, Deployment, ModuleSpec
from rascal.runtime.module import RUN_DIR_ENV, Module, Runtime
from rascal.runtime.sdnotify import NOTIFY_SOCKET_ENV

CHECK_PERIOD_S = 0.05
STARTUP_GRACE_S = 15.0  # a fresh process imports numpy, OpenCV...: no heartbeat is expected before this
STABLE_S = 10.0  # a child that ran this long before failing restarts at once
FIRST_BACKOFF_S = 0.25
MAX_BACKOFF_S = 5.0
STOP_WAIT_S = 5.0
CPU_BUDGET_BEATS = 10


@dataclass
class CpuBooks:
    """One child's CPU over the run, from its heartbeats, against its budget."""

    budget_pct: float
    total_pct: float = 0.0
    beats: int = 0
    peak_pct: float = 0.0
    over_in_a_row: int = 0

    @property
    def mean_pct(self) -> float | None:
        return self.total_pct / self.beats if self.beats else None

    def add(self, cpu_pct: float) -> bool:
        """Book one heartbeat's CPU; True exactly when it completes a run of CPU_BUDGET_BEATS
        heartbeats over budget (it is said once per such run)."""
        self.total_pct += cpu_pct
        self.beats += 1
        self.peak_pct = max(self.peak_pct, cpu_pct)
        self.over_in_a_row = self.over_in_a_row + 1 if cpu_pct > self.budget_pct else 0
        return self.over_in_a_row == CPU_BUDGET_BEATS


@dataclass
class Child:
    """One supervised process and its books."""

    spec: ModuleSpec
    process: subprocess.Popen[bytes] | None = None
    started_s: float = 0.0
    restarts: int = 0
    failures_in_a_row: int = 0
    restart_due_s: float | None = None
    last_heartbeat_s: float | None = None
    status: ModuleStatus | None = None
    exits: list[str] = field(default_factory=list)  # why each restart happened
    cpu: CpuBooks = field(init=False)

    def __post_init__(self) -> None:
        self.cpu = CpuBooks(self.spec.cpu_budget_pct)

    @property
    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None


@dataclass(frozen=True)
class SupervisorConfig:
    """Not read from --set: the supervisor is built by ``rascal run`` with its deployment."""


class Supervisor(Module):
    """Starts this host's modules, restarts crashed or silent ones, stops them in order."""

    name = "supervisor"
    default_source_id = SUPERVISOR_SOURCE_ID
    Config = SupervisorConfig
    cpu_counts_children = False  # they report their own

    def __init__(
        self,
        runtime: Runtime,
        deployment: Deployment,
        host: str,
        log_dir: Path,
        env: dict[str, str] | None = None,
        extra: tuple[ModuleSpec, ...] = (),
    ) -> None:
        """``extra`` processes start first (and so stop last), before the deployment's own."""
        super().__init__(SupervisorConfig(), runtime)
        self.deployment = deployment
        self.log_dir = log_dir
        self.env = env if env is not None else dict(os.environ)
        self.children = [Child(spec) for spec in (*extra, *deployment.on_host(host))]
        self._by_source = {child.spec.source_id: child for child in self.children}
        self.key_dir = log_dir / "keys"
        keyring = runtime.bus.codec.keyring
        master = keyring.signing_master if keyring is not None else None
        # What the module key files are derived from; None when the key file cannot derive them.
        self._module_keys: tuple[Keyring, Authority] | None = None
        if keyring is not None and master is not None:
            authority = Authority.derive(deployment.authority, master)
            self._module_keys = (keyring, authority)
            # It holds the master, but knows the deployment: no forged time reply skews its clock
            # (and with it the pause it sends when the run ends).
            runtime.bus.enforce(authority)

    def on_start(self) -> None:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        keyring = self.bus.codec.keyring
        if keyring is not None and keyring.legacy:
            self.report(
                Severity.WARNING,
                "no_command_authority",
                "the key file has no signing_master: every module gets it whole and can forge commands "
                "(`rascal keygen` writes one with it)",
            )
        self.bus.subscribe(channels.MODULE_STATUS, self.on_status)
        for child in self.children:
            self._start(child)
        self.every(CHECK_PERIOD_S, self.check, priority=8)

    def on_stop(self) -> None:
        self.stop_children()
        shutil.rmtree(self.key_dir, ignore_errors=True)  # a run directory is shared and kept: keys are not

    def on_status(self, status: ModuleStatus, envelope: Envelope) -> None:
        child = self._by_source.get(envelope.source_id)
        if child is None:
            return
        child.last_heartbeat_s = time.monotonic()
        child.status = status
        if status.cpu_pct >= 0 and child.cpu.add(status.cpu_pct):
            self.report(
                Severity.WARNING,
                "cpu_budget",
                f"{child.spec.label} used more than its {child.cpu.budget_pct:g} % of one core for "
                f"{CPU_BUDGET_BEATS} s (now {status.cpu_pct:.0f} %)",
            )

    def check(self) -> None:
        now = time.monotonic()
        for child in self.children:
            if child.restart_due_s is not None:
                if now >= child.restart_due_s:
                    self._start(child)
                continue
            code = child.process.poll() if child.process is not None else None
            if code is not None:
                self._failed(child, f"exited with {_describe_exit(code)}", now)
            elif self._silent(child, now):
                assert child.process is not None
                child.process.kill()
                child.process.wait()
                self._failed(child, f"no heartbeat for {child.spec.heartbeat_timeout_s:.1f} s: killed", now)

    def stop_children(self) -> None:
        """SIGTERM in reverse start order (the time service last), then SIGKILL stragglers."""
        running = [child for child in reversed(self.children) if child.running]
        for child in running:
            assert child.process is not None
            child.process.terminate()
        deadline = time.monotonic() + STOP_WAIT_S
        for child in running:
            assert child.process is not None
            try:
                child.process.wait(timeout=max(0.05, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                child.process.kill()
                child.process.wait()
        for child in self.children:
            child.restart_due_s = None

    def status_detail(self) -> str:
        up = sum(child.running for child in self.children)
        restarts = sum(child.restarts for child in self.children)
        return f"{up}/{len(self.children)} modules up, {restarts} restarts"

    # -- internals ----------------------------------------------------------------------------

    def _silent(self, child: Child, now: float) -> bool:
        """No heartbeat from this process for its timeout (or, before its first, the start-up grace)."""
        heard = child.last_heartbeat_s if (child.last_heartbeat_s or 0.0) >= child.started_s else None
        if heard is None:
            return now - child.started_s > STARTUP_GRACE_S
        return now - heard > child.spec.heartbeat_timeout_s

    def _failed(self, child: Child, why: str, now: float) -> None:
        child.exits.append(why)
        quick = now - child.started_s < STABLE_S
        child.failures_in_a_row = child.failures_in_a_row + 1 if quick else 1
        backoff = 0.0 if child.failures_in_a_row <= 1 else FIRST_BACKOFF_S * 2 ** (child.failures_in_a_row - 2)
        backoff = min(backoff, MAX_BACKOFF_S)
        child.restart_due_s = now + backoff
        child.process = None
        self.report(
            Severity.ERROR,
            "module_restart",
            f"{child.spec.label} {why}; restarting" + (f" in {backoff:.2f} s" if backoff else ""),
        )

    def _start(self, child: Child) -> None:
        spec = child.spec
        if child.restart_due_s is not None:
            child.restarts += 1
        command = module_command(self.deployment, spec, child.restarts)
        env = module_environment(self.deployment, self.env)
        key_file = self.module_key_file(spec)
        if key_file is not None:
            env["RASCAL_KEY_FILE"] = str(key_file.resolve())
        env[RUN_DIR_ENV] = str(self.log_dir.resolve())  # where a module may leave run artefacts
        env.update(spec.environment())  # e.g. the deployment's link faults for this module
        log = (self.log_dir / f"{spec.label}.log").open("ab")
        nice = spec.nice
        child.process = subprocess.Popen(
            command,
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
            cwd=Path(__file__).resolve().parents[1],
            preexec_fn=(lambda: os.nice(nice)) if nice else None,
            start_new_session=True,  # Ctrl-C in the terminal reaches the supervisor, which stops them in order
        )
        log.close()
        child.started_s = time.monotonic()
        child.restart_due_s = None
        child.status = None

    def module_key_file(self, spec: ModuleSpec) -> Path | None:
        """``spec``'s module key file, written on its first start; None without a master to derive it."""
        if self._module_keys is None:
            return None
        keyring, authority = self._module_keys
        path = self.key_dir / f"{spec.label}.key"
        if not path.exists():
            self.key_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
            write_keyring(path, keyring.for_module(spec.source_id, authority), overwrite=True)
        return path


def module_command(deployment: Deployment, spec: ModuleSpec, restarts: int = 0) -> list[str]:
    """The command line of one module process of ``deployment``."""
    return [
        sys.executable,
        "-m",
        spec.python_module,
        "--bus",
        deployment.bus_on(spec.host),
        *spec.arguments(),
        "--restarts",
        str(restarts),
    ]


def module_environment(deployment: Deployment, base: dict[str, str]) -> dict[str, str]:
    """``base`` with the deployment's key file, and without a service manager's notification
    socket: only the process systemd started may notify it (``NotifyAccess=main``)."""
    env = {key: value for key, value in base.items() if key != NOTIFY_SOCKET_ENV}
    if deployment.key_file is not None:
        env["RASCAL_KEY_FILE"] = str(deployment.key_file)
    return env


def _describe_exit(code: int) -> str:
    if code < 0:
        try:
            return f"signal {signal.Signals(-code).name}"
        except ValueError:
            return f"signal {-code}"
    return f"status {code}"


def module_state(child: Child) -> str:
    """What the view shows for a child: its own reported state, or the supervisor's knowledge."""
    if child.restart_due_s is not None:
        return "RESTARTING"
    if not child.running:
        return "STOPPED"
    if child.status is None or (child.last_heartbeat_s or 0) < child.started_s:
        return "STARTING"
    return ModuleState(child.status.state).name
