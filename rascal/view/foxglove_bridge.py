"""The view for Foxglove: the same ViewState published through foxglove-sdk's live WebSocket server.

Topics (all in frame ``enu``; the vehicle is frame ``vehicle``):

* ``/rascal/map`` Grid: the brain's hazard map, one uint8 ``hazard`` field (probability x 255);
* ``/rascal/obstacles`` SceneUpdate: a cube per obstacle, one entity per sensor, coloured by it;
* ``/rascal/corridor`` SceneUpdate: the RDDF centre line and each segment's band edges;
* ``/rascal/path`` PosesInFrame: the planned path, each pose facing along it;
* ``/tf`` FrameTransform: ``enu`` -> ``vehicle`` from the navigation solution.

foxglove-sdk is an optional dependency (``pip install -e '.[foxglove]'``). Its server runs on its
own threads and drops a slow client's oldest messages, so logging never blocks the bus loop. It
checks neither Host nor Origin, so it listens at an unguessable loopback address behind a
:class:`~rascal.view.guard.WebSocketGuard` that does, on the advertised port.
"""

from __future__ import annotations

import math
import zlib
from typing import Any

from rascal.view.guard import Access, WebSocketGuard, unguessable_loopback
from rascal.view.state import ViewState

try:
    import foxglove
    from foxglove import channels as fc
    from foxglove import messages as fm
except ImportError as exc:  # pragma: no cover - depends on the optional extra
    raise ImportError("rascal view --foxglove needs foxglove-sdk: pip install -e '.[foxglove]'") from exc

FRAME = "enu"
VEHICLE_FRAME = "vehicle"
OBSTACLE_HEIGHT_M = 1.0
CORRIDOR_PERIOD_S = 1.0  # re-sent so a client that connects late still gets it
SENSOR_RGB = {
    "lidar_h_left": (1.0, 0.62, 0.11),
    "lidar_h_right": (1.0, 0.82, 0.4),
    "lidar_v_left": (0.78, 0.49, 1.0),
    "lidar_v_right": (0.88, 0.67, 1.0),
    "lidar_sweep": (0.55, 0.9, 0.45),
    "esvs": (0.3, 0.79, 0.94),
}
TOPICS = {
    "/rascal/map": "foxglove.Grid",
    "/rascal/obstacles": "foxglove.SceneUpdate",
    "/rascal/corridor": "foxglove.SceneUpdate",
    "/rascal/path": "foxglove.PosesInFrame",
    "/tf": "foxglove.FrameTransform",
}


def _stamp(t_ns: int) -> fm.Timestamp:
    return fm.Timestamp(sec=t_ns // 1_000_000_000, nsec=t_ns % 1_000_000_000)


def _yaw(yaw_rad: float) -> fm.Quaternion:
    return fm.Quaternion(x=0.0, y=0.0, z=math.sin(yaw_rad / 2), w=math.cos(yaw_rad / 2))


def _pose(east: float, north: float, yaw_rad: float = 0.0, up: float = 0.0) -> fm.Pose:
    return fm.Pose(position=fm.Vector3(x=east, y=north, z=up), orientation=_yaw(yaw_rad))


def _line(points: list[tuple[float, float]], rgb: tuple[float, float, float], thickness: float) -> fm.LinePrimitive:
    return fm.LinePrimitive(
        type=fm.LinePrimitiveLineType.LineStrip,
        pose=_pose(0.0, 0.0),
        thickness=thickness,
        scale_invariant=True,
        points=[fm.Point3(x=e, y=n, z=0.0) for e, n in points],
        color=fm.Color(r=rgb[0], g=rgb[1], b=rgb[2], a=1.0),
    )


def _headed(points: list[tuple[float, float]]) -> list[tuple[float, float, float]]:
    """Each point with the heading of the path through it (central differences, one-sided at the ends)."""
    last = len(points) - 1
    headed = []
    for i, (east, north) in enumerate(points):
        (e0, n0), (e1, n1) = points[max(i - 1, 0)], points[min(i + 1, last)]
        headed.append((east, north, math.atan2(n1 - n0, e1 - e0)))
    return headed


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
        ctx = self.context
        self.map = fc.GridChannel("/rascal/map", context=ctx)
        self.obstacles = fc.SceneUpdateChannel("/rascal/obstacles", context=ctx)
        self.corridor = fc.SceneUpdateChannel("/rascal/corridor", context=ctx)
        self.path = fc.PosesInFrameChannel("/rascal/path", context=ctx)
        self.tf = fc.FrameTransformChannel("/tf", context=ctx)
        self._corridor: fm.SceneUpdate | None = None
        self._corridor_due_ns = 0
        self._map_seq = 0

    def course(self, state: ViewState) -> None:
        """Build the corridor's scene once (the course does not change during a run)."""
        course = state.course
        if course is None:
            return
        east, north, half = list(course.east_m), list(course.north_m), list(course.half_width_m)
        lines = [_line(list(zip(east, north, strict=True)), (0.6, 0.6, 0.6), 1.0)]
        for i, width in enumerate(half):  # each segment's band edges, offset by its half width
            de, dn = east[i + 1] - east[i], north[i + 1] - north[i]
            norm = math.hypot(de, dn) or 1.0
            oe, on = -dn / norm * width, de / norm * width
            for side in (1.0, -1.0):
                ends = [(east[j] + side * oe, north[j] + side * on) for j in (i, i + 1)]
                lines.append(_line(ends, (0.35, 0.45, 0.55), 2.0))
        entity = fm.SceneEntity(frame_id=FRAME, id="corridor", lines=lines)
        self._corridor = fm.SceneUpdate(entities=[entity])

    def frame(self, state: ViewState) -> None:
        """Publish what changed since the last frame, stamped with the view's time."""
        now = state.now_ns
        if self._corridor is not None and now >= self._corridor_due_ns:
            self.corridor.log(self._corridor, log_time=now)
            self._corridor_due_ns = now + int(CORRIDOR_PERIOD_S * 1e9)
        vehicle = state.vehicle
        if vehicle is not None:
            transform = fm.FrameTransform(
                timestamp=_stamp(now),
                parent_frame_id=FRAME,
                child_frame_id=VEHICLE_FRAME,
                translation=fm.Vector3(x=vehicle.east_m, y=vehicle.north_m, z=0.0),
                rotation=_yaw(vehicle.yaw_rad),
            )
            self.tf.log(transform, log_time=now)
        if state.path is not None:
            poses = [_pose(e, n, yaw) for e, n, yaw in _headed([(p.east_m, p.north_m) for p in state.path.points])]
            self.path.log(fm.PosesInFrame(timestamp=_stamp(now), frame_id=FRAME, poses=poses), log_time=now)
        self.obstacles.log(self._obstacle_scene(state, now), log_time=now)
        if state.map is not None and state.map_seq != self._map_seq:
            self._map_seq = state.map_seq
            self.map.log(self._grid(state, now), log_time=now)

    def _obstacle_scene(self, state: ViewState, now: int) -> fm.SceneUpdate:
        scene: dict[str, Any] = state.scene_view()
        entities = []
        for sensor, boxes in scene["obstacles"].items():
            r, g, b = SENSOR_RGB.get(sensor, (1.0, 1.0, 1.0))
            cubes = [
                fm.CubePrimitive(
                    pose=_pose(box["e"], box["n"], box["yaw"], OBSTACLE_HEIGHT_M / 2),
                    size=fm.Vector3(x=max(box["l"], 0.1), y=max(box["w"], 0.1), z=OBSTACLE_HEIGHT_M),
                    color=fm.Color(r=r, g=g, b=b, a=0.8),
                )
                for box in boxes
            ]
            entities.append(fm.SceneEntity(timestamp=_stamp(now), frame_id=FRAME, id=sensor, cubes=cubes))
        return fm.SceneUpdate(entities=entities)

    def _grid(self, state: ViewState, now: int) -> fm.Grid:
        snapshot = state.map
        assert snapshot is not None  # checked by the caller; ViewState only keeps decodable ones
        return fm.Grid(
            timestamp=_stamp(now),
            frame_id=FRAME,
            pose=_pose(snapshot.origin_east_m, snapshot.origin_north_m),
            column_count=snapshot.cols,
            cell_size=fm.Vector2(x=snapshot.resolution_m, y=snapshot.resolution_m),
            row_stride=snapshot.cols,
            cell_stride=1,
            fields=[fm.PackedElementField(name="hazard", offset=0, type=fm.PackedElementFieldNumericType.Uint8)],
            data=zlib.decompress(snapshot.cells),
        )

    def close(self) -> None:
        self.server.stop()  # first: the relays end as their upstream closes
        self.guard.close()
