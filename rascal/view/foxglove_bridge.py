"""The view for Foxglove: the same ViewState published through foxglove-sdk's live WebSocket server.

The topics, their foxglove schemas and the conversion are those of the recordings
(rascal/foxglove_schemas.py): JSON messages with ``jsonschema`` schemas, in frame ``enu``
(the vehicle is frame ``vehicle``). A live view has no GPS fix to show: ``/rascal/gps`` is a
recording's only.

foxglove-sdk is an optional dependency (``pip install -e '.[foxglove]'``). Its server runs on its
own threads and drops a slow client's oldest messages, so logging never blocks the bus loop. It
checks neither Host nor Origin, so it listens at an unguessable loopback address behind a
:class:`~rascal.view.guard.WebSocketGuard` that does, on the advertised port.
"""

from __future__ import annotations

from typing import Any

from rascal import foxglove_schemas as fx
from rascal.view.guard import Access, WebSocketGuard, unguessable_loopback
from rascal.view.state import ViewState

try:
    import foxglove
except ImportError as exc:  # pragma: no cover - depends on the optional extra
    raise ImportError("rascal view --foxglove needs foxglove-sdk: pip install -e '.[foxglove]'") from exc

CORRIDOR_PERIOD_S = 1.0  # re-sent so a client that connects late still gets it
TOPICS = {topic: name for topic, name in fx.TOPICS.items() if topic != fx.GPS_TOPIC}


class FoxgloveBridge:
    """A foxglove-sdk server, reached through a guard on ``host:port``, with the topics above, in its own context."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, access: Access | None = None) -> None:
        self.context = foxglove.Context()
        hidden = unguessable_loopback()
        self.server = foxglove.start_server(name="rascal", host=hidden, port=0, context=self.context)
        try:
            self.guard = WebSocketGuard(host, port, (hidden, self.server.port), access or Access.of(host))
        except OSError:
            self.server.stop()
            raise
        self.url = f"ws://{host}:{self.guard.port}"
        self.channels = {topic: _channel(topic, name, self.context) for topic, name in TOPICS.items()}
        self._corridor: dict[str, Any] | None = None
        self._corridor_due_ns = 0
        self._map_seq = 0
        self._path: Any = None

    def course(self, state: ViewState) -> None:
        """Build the corridor's scene once (the course does not change during a run)."""
        if state.course is not None:
            self._corridor = fx.corridor_scene(state.now_ns, state.course)

    def frame(self, state: ViewState) -> None:
        """Publish what changed since the last frame, stamped with the view's time."""
        now = state.now_ns
        if self._corridor is not None and now >= self._corridor_due_ns:
            self._log(fx.CORRIDOR_TOPIC, self._corridor, now)
            self._corridor_due_ns = now + int(CORRIDOR_PERIOD_S * 1e9)
        vehicle = state.vehicle
        if vehicle is not None:
            self._log(fx.TF_TOPIC, fx.frame_transform(now, vehicle), now)
            self._log(fx.POSE_TOPIC, fx.pose_in_frame(now, vehicle), now)
        if state.path is not None and state.path is not self._path:
            self._path = state.path
            self._log(fx.PATH_TOPIC, fx.path_scene(now, [(p.east_m, p.north_m) for p in state.path.points]), now)
        self._log(fx.OBSTACLES_TOPIC, fx.obstacle_scene(now, state.scene_view()["obstacles"]), now)
        if state.map is not None and state.map_seq != self._map_seq:
            self._map_seq = state.map_seq
            self._log(fx.MAP_TOPIC, fx.grid(now, state.map), now)

    def _log(self, topic: str, message: dict[str, Any] | None, now: int) -> None:
        if message is None:
            return
        try:
            data = fx.encode(message)
        except ValueError:  # a non-finite number (in a path): JSON cannot carry it
            return
        self.channels[topic].log(data, log_time=now)

    def close(self) -> None:
        self.server.stop()  # first: the relays end as their upstream closes
        self.guard.close()


def _channel(topic: str, name: str, context: foxglove.Context) -> foxglove.Channel:
    schema = foxglove.Schema(name=name, encoding="jsonschema", data=fx.schema_bytes(name))
    return foxglove.Channel(topic, schema=schema, message_encoding="json", context=context)
