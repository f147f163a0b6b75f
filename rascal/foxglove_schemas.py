"""Foxglove's well-known message types as JSON: their JSON Schemas and builders from rascal's data.

One conversion for both consumers: the recorder writes these as MCAP channels with message
encoding ``json`` and a ``jsonschema`` schema (rascal/recording.py), and the live bridge of
``rascal view --foxglove`` logs the same JSON on the same topics (rascal/view/foxglove_bridge.py).
Foxglove recognises a channel by its schema name (``foxglove.SceneUpdate``...), decodes bytes
fields declared ``"contentEncoding": "base64"`` and reads enums as integers.

Topics (all in frame ``enu``; the vehicle is frame ``vehicle``): see :data:`TOPICS`.
"""

from __future__ import annotations

import base64
import json
import math
import zlib
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from brain.corridor import Course
from protocol.messages import GpsFix, MapSnapshot, NavQuality, VehicleState

FRAME = "enu"
VEHICLE_FRAME = "vehicle"
GPS_FRAME = "gps"
OBSTACLE_HEIGHT_M = 1.0
OBSTACLE_LIFETIME_NS = 1_000_000_000  # a sensor that falls silent has its boxes taken off the scene
NS = 1_000_000_000
MAX_GRID_CELLS = 4096 * 4096  # as brain.fusion.snapshot: a small zlib body must not inflate without bound

MAP_TOPIC = "/rascal/map"
OBSTACLES_TOPIC = "/rascal/obstacles"
CORRIDOR_TOPIC = "/rascal/corridor"
PATH_TOPIC = "/rascal/path"
POSE_TOPIC = "/rascal/pose"
GPS_TOPIC = "/rascal/gps"
TF_TOPIC = "/tf"
TOPICS = {
    MAP_TOPIC: "foxglove.Grid",
    OBSTACLES_TOPIC: "foxglove.SceneUpdate",
    CORRIDOR_TOPIC: "foxglove.SceneUpdate",
    PATH_TOPIC: "foxglove.SceneUpdate",
    POSE_TOPIC: "foxglove.PoseInFrame",
    GPS_TOPIC: "foxglove.LocationFix",
    TF_TOPIC: "foxglove.FrameTransform",
}
SENSOR_RGB = {
    "lidar_h_left": (1.0, 0.62, 0.11),
    "lidar_h_right": (1.0, 0.82, 0.4),
    "lidar_v_left": (0.78, 0.49, 1.0),
    "lidar_v_right": (0.88, 0.67, 1.0),
    "lidar_sweep": (0.55, 0.9, 0.45),
    "esvs": (0.3, 0.79, 0.94),
}
CORRIDOR_RGB = (0.6, 0.6, 0.6)
BAND_RGB = (0.35, 0.45, 0.55)
PATH_RGB = (0.2, 0.9, 0.3)
RGB = tuple[float, float, float]

# -- the schemas -------------------------------------------------------------------------------

_NUMBER = {"type": "number"}
_COUNT = {"type": "integer", "minimum": 0}
_BOOL = {"type": "boolean"}
_TEXT = {"type": "string"}
_BYTES = {"type": "string", "contentEncoding": "base64"}


def _object(title: str, **properties: Mapping[str, Any]) -> dict[str, Any]:
    """A foxglove object type: every field named is required, as Foxglove's own schemas have it."""
    return {"title": title, "type": "object", "properties": dict(properties), "required": list(properties)}


def _array(items: Mapping[str, Any]) -> dict[str, Any]:
    return {"type": "array", "items": dict(items)}


def _enum(title: str, *names: str) -> dict[str, Any]:
    # Foxglove reads an enum as oneOf integer constants, each titled with its name.
    return {"title": title, "oneOf": [{"title": name, "const": value} for value, name in enumerate(names)]}


_TIME = {
    "type": "object",
    "title": "time",
    "properties": {"sec": _COUNT, "nsec": {**_COUNT, "maximum": NS - 1}},
    "required": ["sec", "nsec"],
}
_DURATION = {
    **_TIME,
    "title": "duration",
    "properties": {"sec": {"type": "integer"}, "nsec": _TIME["properties"]["nsec"]},
}
_VECTOR2 = _object("foxglove.Vector2", x=_NUMBER, y=_NUMBER)
_VECTOR3 = _object("foxglove.Vector3", x=_NUMBER, y=_NUMBER, z=_NUMBER)
_POINT3 = _object("foxglove.Point3", x=_NUMBER, y=_NUMBER, z=_NUMBER)
_QUATERNION = _object("foxglove.Quaternion", x=_NUMBER, y=_NUMBER, z=_NUMBER, w=_NUMBER)
_POSE = _object("foxglove.Pose", position=_VECTOR3, orientation=_QUATERNION)
_COLOR = _object("foxglove.Color", r=_NUMBER, g=_NUMBER, b=_NUMBER, a=_NUMBER)
_KEY_VALUE = _object("foxglove.KeyValuePair", key=_TEXT, value=_TEXT)
_SIZED = {"pose": _POSE, "size": _VECTOR3}
_POINTS = {"points": _array(_POINT3), "color": _COLOR, "colors": _array(_COLOR), "indices": _array(_COUNT)}
_ENTITY = _object(
    "foxglove.SceneEntity",
    timestamp=_TIME,
    frame_id=_TEXT,
    id=_TEXT,
    lifetime=_DURATION,
    frame_locked=_BOOL,
    metadata=_array(_KEY_VALUE),
    arrows=_array(
        _object(
            "foxglove.ArrowPrimitive",
            pose=_POSE,
            shaft_length=_NUMBER,
            shaft_diameter=_NUMBER,
            head_length=_NUMBER,
            head_diameter=_NUMBER,
            color=_COLOR,
        )
    ),
    cubes=_array(_object("foxglove.CubePrimitive", **_SIZED, color=_COLOR)),
    spheres=_array(_object("foxglove.SpherePrimitive", **_SIZED, color=_COLOR)),
    cylinders=_array(
        _object("foxglove.CylinderPrimitive", **_SIZED, bottom_scale=_NUMBER, top_scale=_NUMBER, color=_COLOR)
    ),
    lines=_array(
        _object(
            "foxglove.LinePrimitive",
            type=_enum("foxglove.LineType", "LINE_STRIP", "LINE_LOOP", "LINE_LIST"),
            pose=_POSE,
            thickness=_NUMBER,
            scale_invariant=_BOOL,
            **_POINTS,
        )
    ),
    triangles=_array(_object("foxglove.TriangleListPrimitive", pose=_POSE, **_POINTS)),
    texts=_array(
        _object(
            "foxglove.TextPrimitive",
            pose=_POSE,
            billboard=_BOOL,
            font_size=_NUMBER,
            scale_invariant=_BOOL,
            color=_COLOR,
            text=_TEXT,
        )
    ),
    models=_array(
        _object(
            "foxglove.ModelPrimitive",
            pose=_POSE,
            scale=_VECTOR3,
            color=_COLOR,
            override_color=_BOOL,
            url=_TEXT,
            media_type=_TEXT,
            data=_BYTES,
        )
    ),
)
_DELETION = _object(
    "foxglove.SceneEntityDeletion",
    timestamp=_TIME,
    type=_enum("foxglove.SceneEntityDeletionType", "MATCHING_ID", "ALL"),
    id=_TEXT,
)
_NUMERIC_TYPE = _enum(
    "foxglove.NumericType", "UNKNOWN", "UINT8", "INT8", "UINT16", "INT16", "UINT32", "INT32", "FLOAT32", "FLOAT64"
)
UINT8 = 1
SCHEMAS: dict[str, dict[str, Any]] = {
    "foxglove.SceneUpdate": _object("foxglove.SceneUpdate", deletions=_array(_DELETION), entities=_array(_ENTITY)),
    "foxglove.FrameTransform": _object(
        "foxglove.FrameTransform",
        timestamp=_TIME,
        parent_frame_id=_TEXT,
        child_frame_id=_TEXT,
        translation=_VECTOR3,
        rotation=_QUATERNION,
    ),
    "foxglove.PoseInFrame": _object("foxglove.PoseInFrame", timestamp=_TIME, frame_id=_TEXT, pose=_POSE),
    "foxglove.Grid": _object(
        "foxglove.Grid",
        timestamp=_TIME,
        frame_id=_TEXT,
        pose=_POSE,
        column_count=_COUNT,
        cell_size=_VECTOR2,
        row_stride=_COUNT,
        cell_stride=_COUNT,
        fields=_array(_object("foxglove.PackedElementField", name=_TEXT, offset=_COUNT, type=_NUMERIC_TYPE)),
        data=_BYTES,
    ),
    "foxglove.LocationFix": _object(
        "foxglove.LocationFix",
        timestamp=_TIME,
        frame_id=_TEXT,
        latitude=_NUMBER,
        longitude=_NUMBER,
        altitude=_NUMBER,
        position_covariance={**_array(_NUMBER), "minItems": 9, "maxItems": 9},
        position_covariance_type=_enum(
            "foxglove.PositionCovarianceType", "UNKNOWN", "APPROXIMATED", "DIAGONAL_KNOWN", "KNOWN"
        ),
    ),
}
DIAGONAL_KNOWN = 2


def schema_bytes(name: str) -> bytes:
    """The JSON Schema document of a foxglove type, for an MCAP or WebSocket ``jsonschema`` schema."""
    document = {"$schema": "https://json-schema.org/draft/2020-12/schema", **SCHEMAS[name]}
    return json.dumps(document, separators=(",", ":")).encode()


# -- the messages ------------------------------------------------------------------------------


def timestamp(t_ns: int) -> dict[str, int]:
    t_ns = max(t_ns, 0)
    return {"sec": t_ns // NS, "nsec": t_ns % NS}


def _xyz(x: float, y: float, z: float) -> dict[str, float]:
    return {"x": x, "y": y, "z": z}


def yaw_quaternion(yaw_rad: float) -> dict[str, float]:
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw_rad / 2), "w": math.cos(yaw_rad / 2)}


def pose(east: float, north: float, yaw_rad: float = 0.0, up: float = 0.0) -> dict[str, Any]:
    return {"position": _xyz(east, north, up), "orientation": yaw_quaternion(yaw_rad)}


def _color(rgb: RGB, alpha: float = 1.0) -> dict[str, float]:
    return {"r": rgb[0], "g": rgb[1], "b": rgb[2], "a": alpha}


def _line(points: Iterable[tuple[float, float]], rgb: RGB, thickness: float) -> dict[str, Any]:
    """A line strip on the ground, ``thickness`` in screen pixels."""
    return {
        "type": 0,  # LINE_STRIP
        "pose": pose(0.0, 0.0),
        "thickness": thickness,
        "scale_invariant": True,
        "points": [_xyz(east, north, 0.0) for east, north in points],
        "color": _color(rgb),
        "colors": [],
        "indices": [],
    }


def _entity(
    t_ns: int, entity_id: str, *, lifetime_ns: int = 0, cubes: Sequence[Any] = (), lines: Sequence[Any] = ()
) -> dict[str, Any]:
    lifetime = {"sec": lifetime_ns // NS, "nsec": lifetime_ns % NS}
    return {
        "timestamp": timestamp(t_ns), "frame_id": FRAME, "id": entity_id, "lifetime": lifetime,
        "frame_locked": False, "metadata": [], "arrows": [], "cubes": list(cubes), "spheres": [],
        "cylinders": [], "lines": list(lines), "triangles": [], "texts": [], "models": [],
    }  # fmt: skip


def _scene(*entities: dict[str, Any]) -> dict[str, Any]:
    return {"deletions": [], "entities": list(entities)}


def obstacle_scene(t_ns: int, obstacles: Mapping[str, Sequence[Mapping[str, float]]]) -> dict[str, Any]:
    """One entity per sensor, a cube per box; boxes as :meth:`rascal.view.state.ViewState.scene_view`
    gives them (``e``, ``n``, ``l``, ``w``, ``yaw`` in ENU)."""
    entities = []
    for sensor, boxes in obstacles.items():
        rgb = SENSOR_RGB.get(sensor, (1.0, 1.0, 1.0))
        cubes = [
            {
                "pose": pose(box["e"], box["n"], box["yaw"], OBSTACLE_HEIGHT_M / 2),
                "size": _xyz(max(box["l"], 0.1), max(box["w"], 0.1), OBSTACLE_HEIGHT_M),
                "color": _color(rgb, 0.8),
            }
            for box in boxes
        ]
        entities.append(_entity(t_ns, sensor, lifetime_ns=OBSTACLE_LIFETIME_NS, cubes=cubes))
    return _scene(*entities)


def corridor_scene(t_ns: int, course: Course) -> dict[str, Any]:
    """The RDDF centre line and each segment's band edges (offset by its half width)."""
    east, north, half = list(course.east_m), list(course.north_m), list(course.half_width_m)
    lines = [_line(zip(east, north, strict=True), CORRIDOR_RGB, 1.0)]
    for i, width in enumerate(half):
        de, dn = east[i + 1] - east[i], north[i + 1] - north[i]
        norm = math.hypot(de, dn) or 1.0
        oe, on = -dn / norm * float(width), de / norm * float(width)
        for side in (1.0, -1.0):
            ends = [(east[j] + side * oe, north[j] + side * on) for j in (i, i + 1)]
            lines.append(_line(ends, BAND_RGB, 2.0))
    return _scene(_entity(t_ns, "corridor", lines=lines))


def path_scene(t_ns: int, points: Iterable[tuple[float, float]]) -> dict[str, Any]:
    """The planned path as a line strip (replaced by each new plan)."""
    return _scene(_entity(t_ns, "path", lines=[_line(points, PATH_RGB, 3.0)]))


def frame_transform(t_ns: int, vehicle: VehicleState) -> dict[str, Any]:
    """``enu`` -> ``vehicle`` from the navigation solution."""
    return {
        "timestamp": timestamp(t_ns),
        "parent_frame_id": FRAME,
        "child_frame_id": VEHICLE_FRAME,
        "translation": _xyz(vehicle.east_m, vehicle.north_m, 0.0),
        "rotation": yaw_quaternion(vehicle.yaw_rad),
    }


def pose_in_frame(t_ns: int, vehicle: VehicleState) -> dict[str, Any]:
    return {
        "timestamp": timestamp(t_ns),
        "frame_id": FRAME,
        "pose": pose(vehicle.east_m, vehicle.north_m, vehicle.yaw_rad),
    }


def grid_cells(snapshot: MapSnapshot) -> bytes | None:
    """The inflated cells of a snapshot, or None where they are not ``rows x cols`` bytes."""
    cells = snapshot.rows * snapshot.cols
    if not (0 < cells <= MAX_GRID_CELLS and snapshot.rows > 0):
        return None
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(snapshot.cells, cells + 1)
    except zlib.error:
        return None
    return raw if len(raw) == cells and inflater.eof else None


def grid(t_ns: int, snapshot: MapSnapshot) -> dict[str, Any] | None:
    """The hazard map as a Grid of one uint8 field ``hazard`` (probability x 255), row 0 south;
    None for a snapshot that does not decode."""
    cells = grid_cells(snapshot)
    values = (snapshot.origin_east_m, snapshot.origin_north_m, snapshot.resolution_m)
    if cells is None or not all(math.isfinite(v) for v in values) or not snapshot.resolution_m > 0:
        return None
    return {
        "timestamp": timestamp(t_ns),
        "frame_id": FRAME,
        "pose": pose(snapshot.origin_east_m, snapshot.origin_north_m),
        "column_count": snapshot.cols,
        "cell_size": {"x": snapshot.resolution_m, "y": snapshot.resolution_m},
        "row_stride": snapshot.cols,
        "cell_stride": 1,
        "fields": [{"name": "hazard", "offset": 0, "type": UINT8}],
        "data": base64.b64encode(cells).decode("ascii"),
    }


def location_fix(t_ns: int, fix: GpsFix) -> dict[str, Any] | None:
    """A GPS fix for Foxglove's Map panel; None for one without a position."""
    if fix.quality == NavQuality.INVALID or not all(math.isfinite(v) for v in fix[:6]):
        return None
    variances = (fix.std_east_m**2, fix.std_north_m**2, fix.std_up_m**2)
    covariance = [variances[row] if row == col else 0.0 for row in range(3) for col in range(3)]
    return {
        "timestamp": timestamp(t_ns),
        "frame_id": GPS_FRAME,
        "latitude": fix.lat_deg,
        "longitude": fix.lon_deg,
        "altitude": fix.alt_m,
        "position_covariance": covariance,
        "position_covariance_type": DIAGONAL_KNOWN,
    }


def encode(message: Mapping[str, Any]) -> bytes:
    """A message's JSON bytes; ValueError for a non-finite number (JSON has none)."""
    return json.dumps(message, separators=(",", ":"), allow_nan=False).encode()
