"""The viewer on the bus: a module that feeds a ViewState from the live bus and publishes its
frames to the page (and, optionally, to Foxglove), as ``rascal view`` or under ``rascal run --view``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from brain.corridor import Course
from brain.course_config import load_course
from protocol.codec import Envelope, Opened
from rascal.runtime.config import setting
from rascal.runtime.deployment import Deployment, ModuleSpec
from rascal.runtime.module import Module, Runtime
from rascal.view.guard import Access
from rascal.view.server import FrameHub, ViewServer, ViewServerError
from rascal.view.state import DRAWN_CHANNELS, ViewState

VIEWER_SOURCE_ID = 7
TRAIL_PERIOD_S = 1.0
HEALTH_PERIOD_S = 0.5


@dataclass(frozen=True)
class ViewerConfig:
    host: str = setting("127.0.0.1", "address the page is served on (loopback unless you mean otherwise)")
    port: int = setting(8090, "HTTP port of the page (0: any free port)")
    allowed_hosts: tuple[str, ...] = setting((), "host names the page may be reached by besides IPs and localhost")
    course: str = setting("", "RDDF file whose corridor is drawn (empty: none)")
    origin: str = setting("", "ENU origin 'lat,lon[,alt]' overriding the course's first waypoint")
    frame_rate_hz: float = setting(10.0, "frames per second pushed to the page")
    foxglove: bool = setting(False, "also serve Foxglove's live WebSocket protocol (needs foxglove-sdk)")
    foxglove_port: int = setting(8765, "port of the Foxglove server")


class Publisher:
    """Turns a ViewState into the page's topics (and Foxglove's), skipping what did not change."""

    def __init__(self, state: ViewState, hub: FrameHub, foxglove: Any = None, source: str = "live") -> None:
        """``source`` is what the page says it shows: "live", or the recording's name."""
        self.state = state
        self.hub = hub
        self.foxglove = foxglove
        self._map_seq = 0
        hub.publish("course", {**state.course_view(), "source": source})
        if foxglove is not None:
            foxglove.course(state)

    def frame(self) -> None:
        state = self.state
        self.hub.publish("scene", state.scene_view())
        if state.map_seq != self._map_seq:
            self._map_seq = state.map_seq
            self.hub.publish("map", state.map_view())
        if self.foxglove is not None:
            self.foxglove.frame(state)

    def trail(self) -> None:
        self.hub.publish("trail", self.state.trail_view())

    def health(self, rejected: dict[str, int]) -> None:
        self.hub.publish("health", self.state.health_view(rejected))


def open_outputs(config: ViewerConfig) -> tuple[ViewServer, Any]:
    """The page's server (started) and, if asked for, the Foxglove bridge."""
    if not config.frame_rate_hz > 0:
        raise ValueError(f"frame_rate_hz must be positive, got {config.frame_rate_hz}")
    access = Access.of(config.host, config.allowed_hosts)
    server = ViewServer(FrameHub(), config.host, config.port, access)
    server.start()
    foxglove = None
    if config.foxglove:
        try:
            from rascal.view.foxglove_bridge import FoxgloveBridge

            foxglove = FoxgloveBridge(config.host, config.foxglove_port, access)
        except Exception as exc:  # ImportError, or whatever foxglove-sdk raises for a port it cannot bind
            server.close()
            raise ViewServerError(f"cannot serve Foxglove on {config.host}:{config.foxglove_port}: {exc}") from None
    return server, foxglove


def course_of(config: ViewerConfig) -> Course | None:
    """The course to draw, or None; a file that cannot be read is one clear line (SystemExit)."""
    if not config.course:
        return None
    try:
        return load_course(config.course, config.origin)
    except (OSError, ValueError) as exc:
        raise SystemExit(f"viewer: course {config.course}: {exc}") from None


class Viewer(Module):
    """Serves a live bird's-eye view of the bus: map, corridor, vehicle, path, obstacles, health."""

    name = "viewer"
    default_source_id = VIEWER_SOURCE_ID
    Config = ViewerConfig

    def __init__(self, config: ViewerConfig, runtime: Runtime) -> None:
        super().__init__(config, runtime)
        self.state = ViewState(course_of(config))
        self.server: ViewServer | None = None
        self.foxglove: Any = None

    def on_start(self) -> None:
        try:
            self.server, self.foxglove = open_outputs(self.config)
        except ViewServerError as exc:
            raise SystemExit(f"viewer: {exc}") from None
        self.publisher = Publisher(self.state, self.server.hub, self.foxglove)
        print(f"viewer: {self.server.url}" + (f" and Foxglove on {self.foxglove.url}" if self.foxglove else ""),
              flush=True)  # fmt: skip
        self.bus.subscribe_raw(self.on_any)
        for channel in DRAWN_CHANNELS:
            self.bus.subscribe(channel, self.on_message)
        self.every(1.0 / self.config.frame_rate_hz, self.publisher.frame, priority=2)
        self.every(TRAIL_PERIOD_S, self.publisher.trail, priority=1)
        self.every(HEALTH_PERIOD_S, self.health, priority=1)

    def on_any(self, opened: Opened, _data: bytes, recv_ns: int) -> None:
        self.state.count(opened.channel, recv_ns)

    def on_message(self, msg: Any, envelope: Envelope) -> None:
        self.state.handle(envelope.channel, msg, envelope.t_meas_ns, envelope.recv_ns)

    def health(self) -> None:
        self.state.now_ns = max(self.state.now_ns, self.now_ns())  # ages grow while the bus is silent
        rejected: dict[str, int] = {}
        for (_source, reason), count in self.bus.rejects.items():
            rejected[reason] = rejected.get(reason, 0) + count
        self.publisher.health(rejected)

    def on_stop(self) -> None:
        if self.server is not None:
            self.server.close()
        if self.foxglove is not None:
            self.foxglove.close()

    def status_detail(self) -> str:
        url = self.server.url if self.server else "not serving"
        detail = f"{url}; {len(self.state.modules)} modules heard, map {self.state.map_seq}"
        refused = self.server.refusals.snapshot() if self.server else {}
        return f"{detail}; refused {refused}" if refused else detail


def viewer_spec(deployment: Deployment, host: str, port: int) -> ModuleSpec:
    """The viewer as one more supervised process of ``rascal run --view``, drawing the run's course."""
    settings = {"port": str(port), "course": str(deployment.course or ""), "origin": deployment.origin}
    return ModuleSpec(
        label="viewer",
        module="viewer",
        host=host,
        source_id=VIEWER_SOURCE_ID,
        heartbeat_timeout_s=5.0,
        settings=settings,
        entry="rascal.view",
    )
