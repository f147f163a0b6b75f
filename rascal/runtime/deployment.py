"""Deployment files: which modules run on which host, with what settings, on which bus.

One TOML file per deployment (``deploy/localhost.toml`` is the default)::

    [deployment]
    name = "localhost"
    bus = "udpm://239.255.76.67:7667?ttl=0"   # every module's bus URL
    key_file = ""                             # empty: $RASCAL_KEY_FILE or the per-user key
    scenario = "scenarios/mojave.toml"        # simulated modules' world (paths relative to this file)
    course = "scenarios/mojave.rddf"          # the RDDF every ENU module plans and navigates in
    origin = ""                               # "lat,lon[,alt]"; empty: the course's first waypoint

    [vehicle]                                 # optional: the vehicle's footprint and steering
    width_m = 1.2                             #   (brain/vehicle.py), for every module that holds it

    [hosts.brainbox]                          # optional; without hosts every module is local
    address = "10.0.0.2"                      # this host's LAN address: its iface= on an off-host bus

    [modules.lidar_h_left]                    # one table per process; the key is its label
    module = "lidar"                          # package under modules/ (default: the label)
    host = "brainbox"                         # required when hosts are declared
    source_id = 21                            # default: the module's own
    nice = 0                                  # scheduling: higher runs later (0..19)
    heartbeat_timeout_s = 3.0                 # the supervisor restarts a module this quiet
    cpu_budget_pct = 4.0                      # % of one core, children included (default: per module)
    set = { sensor = "lidar_h_left" }         # config overrides, as --set KEY=VALUE

    [[faults]]                                # link faults on receivers (protocol/faults.py)
    channels = "OBSTACLES_.*"                 # + loss_pct, delay_ms, jitter_ms, duplicate_pct,
    loss_pct = 20                             #   reorder_pct, reorder_ms, corrupt_pct, seed, sources
    modules = ["brain"]                       # receivers (default: every module); or to_hosts = [...]
    from_hosts = ["sensorbox"]                # senders: from_hosts / from_modules (default: any)

    [authority]                               # who may publish on the governed channels (optional)
    ACTUATOR_COMMAND = ["control"]            # module labels, "operator" (rascal stop|pause|resume),
    STOP = ["operator", "supervisor"]         #   "supervisor" (every host's), or source ids 1..65535

A module whose configuration has ``scenario``, ``course`` or ``origin`` settings gets the
deployment's unless its ``set`` table overrides them, so every process shares one frame; in the
same way, ``[vehicle]`` sets the ``vehicle`` section of the simulator, control, the brain's
planner and the referee, so all four drive, steer, plan and judge one vehicle. Errors
name the file and the key. Each module's fault rules reach it as ``$RASCAL_FAULTS``, with the
rule's seed mixed with the module's source id (repeatable, yet modules lose different datagrams).
A governed channel that ``[authority]`` does not name gets its default (``DEFAULT_AUTHORITY``):
every module of the package that publishes it, or the operator and the supervisors.
"""

from __future__ import annotations

import dataclasses
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, urlencode, urlsplit

from protocol import channels
from protocol.authority import GOVERNED_CHANNELS, OPERATOR_SOURCE_ID
from protocol.faults import FAULTS_ENV, FaultConfigError, FaultRule, format_rules, rule_from_mapping
from rascal.runtime.config import (
    FINITE,
    ConfigError,
    build_config,
    flatten_values,
    given,
    merge_values,
    nest,
    required,
    setting,
    shared_sections,
)
from rascal.runtime.launch import module_class

DEFAULT_DEPLOYMENT = Path(__file__).resolve().parents[2] / "deploy" / "localhost.toml"
SHARED_SETTINGS = ("scenario", "course", "origin")
# Tables of the deployment that set a section in every module holding one (brain/vehicle.py's
# VehicleGeometry: the simulator, control, the planner and the referee all read [vehicle]).
SHARED_TABLES = ("vehicle",)
LOCALHOST = "localhost"
FAULT_SELECTORS = ("modules", "to_hosts", "from_modules", "from_hosts")
# Each host's own processes (supervisor, recorder) get source ids offset by this per host, in
# declaration order: two senders sharing a source id would break each other's replay windows.
HOST_SOURCE_ID_STRIDE = 100
SUPERVISOR_SOURCE_ID = 9  # each host's supervisor: this, offset per host
OPERATOR = "operator"  # the operator's tools: protocol.authority.OPERATOR_SOURCE_ID
SUPERVISOR = "supervisor"  # every host's supervisor (it pauses the vehicle when a run ends)
# Who may publish on each governed channel unless [authority] says: these words, or every module
# of the package named (its default source id when the deployment runs none).
DEFAULT_AUTHORITY: dict[str, tuple[str, ...]] = {
    channels.ACTUATOR_COMMAND: ("control",),
    channels.PATH: ("brain",),
    channels.STOP: (OPERATOR, SUPERVISOR),
    channels.CONFIG: (OPERATOR, SUPERVISOR),
    channels.TIME_SYNC: ("time_service",),
}
# What each module may use, in % of one core with its children, before the supervisor warns
# (over it for CPU_BUDGET_BEATS heartbeats in a row): each measured mean in the default demo with
# room for the busiest stretches. The measured means sum to about 80 %, the vehicle's own side
# (esvs, ins, brain, control, health) to about 45 % (docs/PERFORMANCE.md).
DEFAULT_CPU_BUDGET_PCT: dict[str, float] = {
    "brain": 25.0,
    "esvs": 20.0,  # with its vision workers and their fork server
    "stereo_camera": 12.0,
    "ins": 8.0,
    "sim": 5.0,
    "nav_sensors": 5.0,
    "viewer": 5.0,
    "recorder": 4.0,
    "control": 4.0,
    "lidar": 3.0,  # the sweeping lidar, at 37.5 Hz, gets more in deploy/localhost.toml
    "health": 3.0,
    "referee": 3.0,
    "supervisor": 3.0,
    "time_service": 1.0,
}
OTHER_CPU_BUDGET_PCT = 10.0
# Labels (and, for systemd units, hosts and names) become file, directory and unit names: a
# conservative charset, never starting with "." or "-" (so never "." or ".."), bounded.
SAFE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")
SAFE_NAME_RULE = "1-64 of A-Z a-z 0-9 _ . -, not starting with . or -"


class DeploymentError(ValueError):
    """A deployment file that cannot be used; the message names the file and key."""


@dataclass(frozen=True)
class ModuleSpec:
    label: str
    module: str
    host: str
    source_id: int
    nice: int = 0
    heartbeat_timeout_s: float = 3.0
    settings: dict[str, str] = field(default_factory=dict)
    entry: str = ""  # the Python module to run, when it is not modules.<module> (the recorder)
    faults: tuple[FaultRule, ...] = ()  # link faults on this module's receive side
    cpu_budget: float | None = None  # % of one core; None: the module's default

    @property
    def cpu_budget_pct(self) -> float:
        if self.cpu_budget is not None:
            return self.cpu_budget
        return DEFAULT_CPU_BUDGET_PCT.get(self.module, OTHER_CPU_BUDGET_PCT)

    @property
    def python_module(self) -> str:
        return self.entry or f"modules.{self.module}"

    def arguments(self) -> list[str]:
        """Command-line arguments after ``python -m modules.<module>`` (bus and key excluded)."""
        args = ["--source-id", str(self.source_id)]
        for key, value in self.settings.items():
            args += ["--set", f"{key}={value}"]
        return args

    def environment(self) -> dict[str, str]:
        """Environment variables this module's process needs beyond the supervisor's own."""
        return {FAULTS_ENV: format_rules(self.faults)} if self.faults else {}


@dataclass(frozen=True)
class Deployment:
    path: Path
    name: str
    bus: str
    key_file: Path | None
    scenario: Path | None
    course: Path | None
    origin: str
    hosts: dict[str, str]  # name -> address
    modules: tuple[ModuleSpec, ...]
    authority: dict[str, tuple[int, ...]]  # governed channel -> source ids that may publish on it

    def on_host(self, host: str) -> tuple[ModuleSpec, ...]:
        if host not in self.hosts:
            raise DeploymentError(f"{self.path}: no host {host!r}; hosts: {sorted(self.hosts)}")
        return tuple(spec for spec in self.modules if spec.host == host)

    def bus_on(self, host: str) -> str:
        """The bus URL for ``host``'s processes: a bus that leaves the host (udpm, ttl > 0) goes
        out through that host's own address, so one file serves every host."""
        address = self.hosts.get(host, "")
        parts = urlsplit(self.bus)
        query = dict(parse_qsl(parts.query, keep_blank_values=True))
        if parts.scheme != "udpm" or not address or query.get("ttl", "0") in ("", "0"):
            return self.bus
        query["iface"] = address
        return parts._replace(query=urlencode(query, safe=",")).geturl()

    def host_source_id(self, host: str, base: int) -> int:
        """``base`` (the supervisor's or recorder's id) made unique to ``host``."""
        return base + HOST_SOURCE_ID_STRIDE * list(self.hosts).index(host)

    def spec(self, label: str) -> ModuleSpec:
        for spec in self.modules:
            if spec.label == label:
                return spec
        raise KeyError(label)


@dataclass(frozen=True, kw_only=True)
class DeploymentTable:
    name: str | None = setting(None, "the deployment's name (default: the file's)")
    bus: str = required("every module's bus URL")
    key_file: str = setting("", "empty: $RASCAL_KEY_FILE or the per-user key")
    scenario: str = setting("", "simulated modules' world (relative to this file)")
    course: str = setting("", "the RDDF every ENU module plans and navigates in")
    origin: str = setting("", "lat,lon[,alt]; empty: the course's first waypoint")


@dataclass(frozen=True)
class HostTable:
    address: str = setting("", "this host's LAN address: its iface= on an off-host bus")


@dataclass(frozen=True)
class ModuleTable:
    module: str | None = setting(None, "package under modules/ (default: the label)")
    host: str | None = setting(None, "required when hosts are declared")
    source_id: int | None = setting(None, "default: the module's own", within=(1, 0xFFFF))
    nice: int = setting(0, "scheduling: higher runs later", within=(0, 19))
    heartbeat_timeout_s: float = setting(3.0, "the supervisor restarts a module this quiet", within=FINITE)
    cpu_budget_pct: float | None = setting(None, "% of one core, children included (default: per module)")
    set: dict[str, Any] = setting({}, "config overrides, as --set KEY=VALUE")


@dataclass(frozen=True, kw_only=True)
class DeploymentFile:
    """A deployment file's tables, checked by rascal.runtime.config as module settings are."""

    deployment: DeploymentTable = required("the bus and the shared settings")
    vehicle: dict[str, Any] = setting({}, "brain/vehicle.py's VehicleGeometry, for every module holding one")
    hosts: dict[str, HostTable] = setting({}, "without hosts every module is local")
    modules: dict[str, ModuleTable] = required("one table per process; the key is its label")
    faults: Any = setting([], "link faults on receivers (protocol/faults.py), a table or [[faults]]")
    authority: dict[str, list[Any]] = setting({}, "who may publish on each governed channel")


def load_deployment(path: str | Path = DEFAULT_DEPLOYMENT) -> Deployment:
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DeploymentError(f"{path}: deployment file not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise DeploymentError(f"{path}: not valid TOML: {exc}") from exc
    try:
        return _Parser(path).deployment(build_config(DeploymentFile, doc, ""))
    except (ConfigError, FaultConfigError) as exc:
        raise DeploymentError(f"{path}: {exc}") from None


class _Parser:
    """What the declaration cannot say: defaults and checks that depend on other tables."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.base = path.resolve().parent

    def deployment(self, file: DeploymentFile) -> Deployment:
        head = file.deployment
        hosts = {name: table.address for name, table in file.hosts.items()}
        explicit_hosts = bool(hosts)
        if not explicit_hosts:
            hosts = {LOCALHOST: "127.0.0.1"}
        shared = {
            "scenario": self.path_or_none(head.scenario, "scenario"),
            "course": self.path_or_none(head.course, "course"),
            "origin": head.origin,
        }
        self.shared_tables = {name: getattr(file, name) for name in SHARED_TABLES}
        self.checked_tables: set[str] = set()
        if not file.modules:
            raise ConfigError("modules: a deployment needs at least one module")
        specs = [self.module(label, table, hosts, explicit_hosts, shared) for label, table in file.modules.items()]
        seen: dict[int, str] = {}
        for spec in specs:
            if spec.source_id in seen:
                raise ConfigError(
                    f"modules.{spec.label}.source_id: {spec.source_id} is already used by {seen[spec.source_id]}"
                )
            seen[spec.source_id] = spec.label
        specs = self.faults(file.faults, specs, hosts)
        return Deployment(
            self.path,
            self.path.stem if head.name is None else head.name,
            head.bus,
            self.path_or_none(head.key_file, "key_file"),
            shared["scenario"],  # type: ignore[arg-type]
            shared["course"],  # type: ignore[arg-type]
            shared["origin"],  # type: ignore[arg-type]
            hosts,
            tuple(specs),
            self.authority(file.authority, specs, hosts),
        )

    def check_shared(self, name: str, section_class: type) -> None:
        """A shared table's mistakes are named once, as the table's, not as each module's."""
        if name not in self.checked_tables:
            build_config(section_class, self.shared_tables[name], name)
            self.checked_tables.add(name)

    def module(
        self, label: str, table: ModuleTable, hosts: dict[str, str], explicit_hosts: bool, shared: dict[str, Any]
    ) -> ModuleSpec:
        where = f"modules.{label}"
        if SAFE_NAME.fullmatch(label) is None:
            # A label names the module's log file in the run directory, and its systemd unit.
            raise ConfigError(f"modules: {label!r} cannot be a module label ({SAFE_NAME_RULE})")
        name = label if table.module is None else table.module
        try:
            cls = module_class(name)
        except SystemExit as exc:
            raise ConfigError(f"{where}.module: {exc}") from None
        if explicit_hosts:
            host = given(table.host, f"{where}.host")
            if host not in hosts:
                raise ConfigError(f"{where}.host: {host!r} is not declared under [hosts]: {sorted(hosts)}")
        else:
            host = LOCALHOST if table.host is None else table.host
            if host != LOCALHOST:
                raise ConfigError(f"{where}.host: {host!r} is not declared: add a [hosts.{host}] table")
        config_fields = {f.name for f in dataclasses.fields(cls.Config)}
        values = {k: shared[k] for k in SHARED_SETTINGS if k in config_fields and shared[k] not in (None, "")}
        values = {k: str(v) for k, v in values.items()}
        for table_name, table_values in self.shared_tables.items():
            for path, section_class in shared_sections(cls.Config, table_name).items():
                self.check_shared(table_name, section_class)
                values = merge_values(values, nest(path, table_values))
        values = merge_values(values, table.set)
        build_config(cls.Config, values, f"{where}.set")
        settings = {key: _setting_text(value) for key, value in flatten_values(values).items()}
        if table.heartbeat_timeout_s < 1.5:
            raise ConfigError(f"{where}.heartbeat_timeout_s: must exceed the 1 s heartbeat period (>= 1.5)")
        budget = table.cpu_budget_pct
        if budget is not None and not 0 < budget <= 1000:
            raise ConfigError(f"{where}.cpu_budget_pct: expected a share of one core in (0, 1000] %, got {budget}")
        source_id = cls.default_source_id if table.source_id is None else table.source_id
        return ModuleSpec(
            label, name, host, source_id, table.nice, table.heartbeat_timeout_s, settings, cpu_budget=budget
        )

    def faults(self, value: Any, specs: list[ModuleSpec], hosts: dict[str, str]) -> list[ModuleSpec]:
        """Give each module the ``[[faults]]`` rules whose receivers include it."""
        tables = [value] if isinstance(value, dict) else value
        if not isinstance(tables, list) or not all(isinstance(table, dict) for table in tables):
            raise ConfigError("faults: expected a table or an array of tables ([[faults]])")
        by_label = {spec.label: spec for spec in specs}
        rules: dict[str, list[FaultRule]] = {spec.label: [] for spec in specs}
        for index, table in enumerate(tables):
            where = f"faults[{index}]"
            rule = rule_from_mapping({k: v for k, v in table.items() if k not in FAULT_SELECTORS}, where)
            receivers = self.names(table, where, "modules", by_label) or list(by_label)
            to_hosts = self.names(table, where, "to_hosts", hosts)
            if to_hosts:
                receivers = [label for label in receivers if by_label[label].host in to_hosts]
            from_modules = self.names(table, where, "from_modules", by_label)
            from_hosts = self.names(table, where, "from_hosts", hosts)
            if from_modules or from_hosts:
                senders = {by_label[label].source_id for label in from_modules}
                senders |= {spec.source_id for spec in specs if spec.host in from_hosts}
                if not senders:
                    raise ConfigError(f"{where}.from_hosts: no modules run on {from_hosts}")
                rule = dataclasses.replace(rule, sources=tuple(sorted(senders | set(rule.sources))))
            for label in receivers:
                seed = rule.seed * 0x10000 + by_label[label].source_id
                rules[label].append(dataclasses.replace(rule, seed=seed))
        return [dataclasses.replace(spec, faults=tuple(rules[spec.label])) for spec in specs]

    def authority(
        self, table: dict[str, Any], specs: list[ModuleSpec], hosts: dict[str, str]
    ) -> dict[str, tuple[int, ...]]:
        """Each governed channel's publishers as source ids: ``table``'s labels, words and ids, else
        the channel's default."""
        unknown = sorted(set(table) - set(GOVERNED_CHANNELS))
        if unknown:
            raise ConfigError(f"authority.{unknown[0]}: not a governed channel; governed: {list(GOVERNED_CHANNELS)}")
        by_label = {spec.label: spec.source_id for spec in specs}
        words = {
            OPERATOR: (OPERATOR_SOURCE_ID,),
            SUPERVISOR: tuple(SUPERVISOR_SOURCE_ID + HOST_SOURCE_ID_STRIDE * index for index in range(len(hosts))),
        }
        resolved: dict[str, tuple[int, ...]] = {}
        for channel in GOVERNED_CHANNELS:
            ids: list[int] = []
            if channel not in table:
                for name in DEFAULT_AUTHORITY[channel]:
                    # A package the deployment does not run (e.g. a time service started by hand)
                    # is trusted at its default source id: else nobody could be.
                    ids += (
                        words.get(name, ())
                        or [spec.source_id for spec in specs if spec.module == name]
                        or [module_class(name).default_source_id]
                    )
            else:
                for name in table[channel]:
                    ids += self.publisher(name, channel, by_label, words)
            resolved[channel] = tuple(sorted(set(ids)))
        return resolved

    def publisher(
        self, name: Any, channel: str, by_label: dict[str, int], words: dict[str, tuple[int, ...]]
    ) -> tuple[int, ...]:
        if isinstance(name, int) and not isinstance(name, bool) and 0 < name < 0x10000:
            return (name,)
        if isinstance(name, str) and name in words:
            return words[name]
        if isinstance(name, str) and name in by_label:
            return (by_label[name],)
        raise ConfigError(
            f"authority.{channel}: {name!r} is no module label {sorted(by_label)}, {OPERATOR!r}, {SUPERVISOR!r}"
            " or source id 1..65535"
        )

    def names(self, table: dict[str, Any], where: str, key: str, known: dict[str, Any]) -> list[str]:
        value = table.get(key, [])
        if not isinstance(value, list) or not all(isinstance(item, str) for item in value):
            raise ConfigError(f"{where}.{key}: expected a list of names, got {value!r}")
        for name in value:
            if name not in known:
                raise ConfigError(f"{where}.{key}: {name!r} is not declared: {sorted(known)}")
        return value

    def path_or_none(self, text: str, key: str) -> Path | None:
        if not text:
            return None
        resolved = (self.base / text).resolve()
        if not resolved.exists():
            raise ConfigError(f"deployment.{key}: {resolved} does not exist")
        return resolved


def _setting_text(value: Any) -> str:
    """A TOML value as ``--set`` text (booleans lower-case, as the config parser reads them)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return ",".join(_setting_text(item) for item in value)
    return str(value)
