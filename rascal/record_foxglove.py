"""Foxglove-schema channels in a recording, converted while recording at a bounded rate.

Beside the raw channels the recorder writes the topics of :data:`rascal.foxglove_schemas.TOPICS`
(message encoding ``json``, a ``jsonschema`` schema each), so Foxglove's 3D, Map and Plot panels
open ``run.mcap`` as it is (layout: deploy/foxglove/rascal_layout.json).

The recorder's CPU is budgeted, so the tap decodes only what it draws and writes at fixed
periods of receive time, not per message: the navigation pose and obstacle descriptors are
decoded as they come (a ViewState places vehicle-frame obstacles with the pose of their
measurement time, exactly as ``rascal view`` does); the path, the map and GPS are kept raw and
decoded only when their topic is due. The corridor, when the course is known, is written once.
The output depends only on the messages and their receive times, so the JSON twins rewrite
after a run (rascal/record_twins.py) regenerates the same channels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from mcap.writer import Writer

from brain.corridor import Course
from protocol import channels
from protocol.codec import Opened, decode_body
from protocol.errors import ProtocolError
from protocol.messages import GpsFix, MapSnapshot, ObstacleList, Path, VehicleState
from rascal import foxglove_schemas as fx
from rascal.record_schema import JSON_ENCODING, JSON_SCHEMA_ENCODING
from rascal.view.state import OBSTACLE_CHANNELS, ViewState

NS = 1_000_000_000
_FOLLOWED: dict[str, type] = {
    channels.VEHICLE_STATE: VehicleState,
    **dict.fromkeys(OBSTACLE_CHANNELS, ObstacleList),
}
_KEPT_RAW = (channels.PATH, channels.MAP_SNAPSHOT, channels.GPS)


@dataclass(frozen=True)
class FoxgloveOptions:
    """What the tap draws and how often (periods of receive time)."""

    course: Course | None = None
    scene_period_s: float = 0.1  # transform, pose, obstacles, path, GPS: at most 10 Hz
    grid_period_s: float = 2.0  # the hazard map: the brain sends it at 1 Hz; a Grid is the biggest message

    def __post_init__(self) -> None:
        if not (self.scene_period_s > 0 and self.grid_period_s > 0):
            raise ValueError("foxglove periods must be positive")


class FoxgloveTap:
    """Feeds on the recorder's messages and writes foxglove-schema messages into its MCAP writer."""

    def __init__(self, writer: Writer, options: FoxgloveOptions) -> None:
        self.writer = writer
        self.options = options
        self.state = ViewState(options.course)
        self.messages = 0  # foxglove messages written
        self.skipped = 0  # inputs that did not decode, or outputs JSON cannot carry
        self._scene_ns = int(options.scene_period_s * NS)
        self._grid_ns = int(options.grid_period_s * NS)
        self._scene_due = 0
        self._grid_due = 0
        self._raw: dict[str, Opened] = {}  # newest path, map and GPS, decoded when due
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._corridor_written = options.course is None

    def feed(self, opened: Opened, recv_ns: int) -> None:
        """One recorded message; writes whatever topic it makes due."""
        channel = opened.channel
        followed = _FOLLOWED.get(channel)
        if followed is not None:
            msg = self._decode(opened, followed)
            if msg is not None:
                self.state.handle(channel, msg, opened.t_meas_ns, recv_ns)
        elif channel in _KEPT_RAW:
            self._raw[channel] = opened
        if recv_ns >= self._scene_due:
            self._scene_due = recv_ns + self._scene_ns
            self._scene(recv_ns)
        if recv_ns >= self._grid_due and channels.MAP_SNAPSHOT in self._raw:
            self._grid_due = recv_ns + self._grid_ns
            self._grid(recv_ns)

    def _scene(self, now: int) -> None:
        state = self.state
        if not self._corridor_written and state.course is not None:
            self._corridor_written = True
            self._write(fx.CORRIDOR_TOPIC, now, fx.corridor_scene(now, state.course))
        if state.vehicle is not None:
            self._write(fx.TF_TOPIC, now, fx.frame_transform(now, state.vehicle))
            self._write(fx.POSE_TOPIC, now, fx.pose_in_frame(now, state.vehicle))
        if state.obstacles:
            self._write(fx.OBSTACLES_TOPIC, now, fx.obstacle_scene(now, state.scene_view()["obstacles"]))
        path = self._take(channels.PATH, Path)
        if path is not None:
            self._write(fx.PATH_TOPIC, now, fx.path_scene(now, [(p.east_m, p.north_m) for p in path.points]))
        fix = self._take(channels.GPS, GpsFix)
        if fix is not None:
            self._write(fx.GPS_TOPIC, now, fx.location_fix(now, fix))

    def _grid(self, now: int) -> None:
        snapshot = self._take(channels.MAP_SNAPSHOT, MapSnapshot)
        if snapshot is not None:
            self._write(fx.MAP_TOPIC, now, fx.grid(now, snapshot))

    def _take(self, channel: str, expected: type) -> Any:
        """The newest raw message of ``channel`` decoded, once: None if none came since."""
        opened = self._raw.pop(channel, None)
        return None if opened is None else self._decode(opened, expected)

    def _decode(self, opened: Opened, expected: type) -> Any:
        try:
            msg = decode_body(opened.type_id, opened.body, opened.source_id)
        except ProtocolError:
            msg = None
        if not isinstance(msg, expected):  # undecodable, or a type this channel does not carry
            self.skipped += 1
            return None
        return msg

    def _write(self, topic: str, now: int, message: dict[str, Any] | None) -> None:
        if message is None:  # a map or fix that does not convert
            self.skipped += 1
            return
        try:
            data = fx.encode(message)
        except ValueError:  # a non-finite number in a path: JSON cannot carry it
            self.skipped += 1
            return
        self.writer.add_message(self._channel(topic), now, data, now)
        self.messages += 1

    def _channel(self, topic: str) -> int:
        channel_id = self._channels.get(topic)
        if channel_id is None:
            name = fx.TOPICS[topic]
            schema_id = self._schemas.get(name)
            if schema_id is None:
                schema_id = self._schemas[name] = self.writer.register_schema(
                    name, JSON_SCHEMA_ENCODING, fx.schema_bytes(name)
                )
            channel_id = self._channels[topic] = self.writer.register_channel(topic, JSON_ENCODING, schema_id)
        return channel_id
