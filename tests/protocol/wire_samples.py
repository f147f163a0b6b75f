"""Shared fixtures for the protocol tests: realistic messages, fixed keys, hand-built datagrams.

A plain module (not a conftest): pytest puts this directory on ``sys.path`` for the test
modules beside it, so they ``import wire_samples``.
"""

from __future__ import annotations

import functools
import hashlib
import itertools
import math
import typing
import zlib
from typing import Any

from protocol import channels
from protocol import messages as m
from protocol.auth import Keyring
from protocol.codec import FLAG_SIGNED, HEADER, MAGIC, VERSION
from protocol.schema import registered

T0_NS = 1_700_000_000_000_000_000
WRONG_KEY = bytes(range(200, 232))


def key_bytes(key_id: int) -> bytes:
    """The deployment's (deterministic, test-only) secret for ``key_id``."""
    return hashlib.sha256(f"rascal test key {key_id}".encode()).digest()


def keyring(*key_ids: int, active: int | None = None) -> Keyring:
    """The deployment keyring holding ``key_ids`` (default: just 1), signing with ``active``
    (default: the first id)."""
    ids = key_ids or (1,)
    return Keyring({key_id: key_bytes(key_id) for key_id in ids}, ids[0] if active is None else active)


def _obstacles(count: int) -> tuple[m.Obstacle, ...]:
    return tuple(
        m.Obstacle(
            x_m=4.0 + 0.75 * i,
            y_m=-3.5 + 0.125 * (i % 57),
            length_m=0.9 + 0.01 * (i % 7),
            width_m=0.6,
            height_m=0.4 + 0.02 * (i % 11),
            yaw_rad=-math.pi + 0.05 * (i % 120),
            confidence=0.25 + (i % 4) / 5,
            range_m=math.hypot(4.0 + 0.75 * i, -3.5 + 0.125 * (i % 57)),
        )
        for i in range(count)
    )


def _path(count: int) -> tuple[m.PathPoint, ...]:
    return tuple(m.PathPoint(east_m=512.25 + 0.5 * i, north_m=-88.0 + 0.3 * i, speed_mps=6.7) for i in range(count))


# One realistic instance per registered type, plus variants with empty and defaulted fields.
SAMPLES: list[Any] = [
    m.TimeSync(kind=m.TimeSyncKind.REQUEST, client_source_id=17, t1_local_ns=T0_NS + 123_456),
    m.TimeSync(m.TimeSyncKind.REPLY, 17, T0_NS + 123_456, T0_NS + 180_000, T0_NS + 181_500),
    m.ModuleStatus(
        module="planner",
        state=m.ModuleState.OK,
        uptime_s=3605.25,
        loop_period_ns=50_000_000,
        jitter_ns=180_000,
        overruns=2,
        restarts=1,
        rx_rejected=14,
        stale_inputs=("GPS", "OBSTACLES_ESVS"),
        clock_state=2,
        clock_offset_ns=-1_500,
        clock_error_bound_ns=25_000,
        detail="replanning at 10 Hz",
    ),
    m.ModuleStatus("gps_driver", m.ModuleState.STARTING, 0.5, 100_000_000, 0, 0, 0, 0, (), 0, 0, 2**62),
    m.HealthEvent(module="esvs", severity=m.Severity.WARNING, code="STALE_INPUT", text="VEHICLE_STATE 412 ms old"),
    m.HealthEvent("supervisor", m.Severity.CRITICAL, "RESTART", "lidar_h_left exited 139; restart 3/5 — ünïcödé"),
    m.ImuSample(0.12, -0.03, 9.806, 0.001, -0.0004, 0.21),
    m.GpsFix(
        lat_deg=35.0533,
        lon_deg=-117.5694,
        alt_m=712.4,
        std_east_m=0.35,
        std_north_m=0.41,
        std_up_m=0.9,
        quality=m.NavQuality.DGPS,
        satellites=11,
    ),
    m.WheelSpeed(speed_mps=7.85, odometer_m=48_211.375),
    m.MagHeading(magnetometer=2, heading_from_north_rad=1.234, std_rad=0.035),
    m.VehicleState(
        east_m=1523.75,
        north_m=-402.125,
        up_m=3.5,
        yaw_rad=0.785,
        speed_mps=8.2,
        vel_east_mps=5.8,
        vel_north_mps=5.79,
        yaw_rate_radps=-0.02,
        covariance=tuple(0.04 if r == c else 0.001 * (r + c) for r in range(5) for c in range(5)),
        quality=m.NavQuality.GPS,
    ),
    m.ObstacleList(sensor=m.Sensor.LIDAR_H_LEFT, frame=m.Frame.VEHICLE, obstacles=_obstacles(12)),
    m.ObstacleList(m.Sensor.ESVS, m.Frame.ENU, ()),
    m.SurfaceProfile(
        sensor=m.Sensor.LIDAR_V_RIGHT,
        lateral_m=-0.8,
        ranges_m=tuple(2.0 + 0.25 * i for i in range(80)),
        heights_m=tuple(0.01 * math.sin(i / 5) for i in range(80)),
    ),
    m.GroundSweep(
        sensor=m.Sensor.LIDAR_SWEEP,
        stretches=(
            m.GroundStretch(x_near_m=36.7, x_far_m=36.9, y_right_m=-20.1, y_left_m=-7.1, height_m=0.0),
            m.GroundStretch(37.4, 39.2, -7.2, -5.2, -0.13),
            m.GroundStretch(36.7, 36.9, 7.1, 20.1, 0.0),
        ),
    ),
    m.GroundSweep(m.Sensor.LIDAR_SWEEP, ()),
    m.LaneBorders(
        sensor=m.Sensor.ESVS,
        borders=(
            m.LaneBorder(side=1, c0_m=1.9, c1=0.01, c2_per_m=-0.0004, x_min_m=2.0, x_max_m=35.0, confidence=0.8),
            m.LaneBorder(side=-1, c0_m=-1.7, c1=0.012, c2_per_m=-0.0003, x_min_m=2.0, x_max_m=28.5, confidence=0.6),
        ),
    ),
    m.Path(path_id=981, points=_path(40), slow_mode=False),
    m.Path(982, (), True),
    m.ActuatorCommand(throttle=0.35, brake=0.0, steering_rad=-0.12),
    m.ActuatorCommand(0.0, 1.0, 0.0, "ESTOP: obstacle at 3.1 m"),
    m.ConfigUpdate(module="esvs", key="round_period_s", value="0.033"),
    m.StopCommand(mode=m.StopMode.PAUSE, reason="operator"),
    m.StopCommand(m.StopMode.ESTOP, ""),
    m.MapSnapshot(-60.0, -15.0, 0.2, 2, 3, zlib.compress(bytes([0, 10, 255, 0, 0, 128]))),
    m.SimTruth(
        east_m=1523.9,
        north_m=-402.0,
        yaw_rad=0.79,
        speed_mps=8.19,
        yaw_rate_radps=-0.021,
        steering_rad=-0.11,
        progress_m=2210.5,
        collisions=0,
    ),
]

# Messages over one 1400 B datagram, so they travel as fragments.
BIG_SAMPLES: list[Any] = [
    m.ObstacleList(m.Sensor.LIDAR_H_RIGHT, m.Frame.VEHICLE, _obstacles(150)),  # ~11 KB
    m.Path(983, _path(1200), False),  # ~33 KB
    m.SurfaceProfile(m.Sensor.LIDAR_V_LEFT, 0.8, tuple(float(i) for i in range(300)), (0.0,) * 300),
]

# The first declared channel of each message type.
CHANNEL_OF: dict[type, str] = {}
for _name, _cls in channels.CHANNEL_TYPES.items():
    CHANNEL_OF.setdefault(_cls, _name)


def type_id_of(cls: type) -> int:
    return next(info.type_id for info in registered() if info.cls is cls)


_seq = itertools.count(1)


def seal(
    body: bytes,
    *,
    keys: Keyring | None,
    channel: bytes = b"IMU",
    type_id: int = 10,
    source_id: int = 42,
    seq: int | None = None,
    t_meas_ns: int = T0_NS,
    t_pub_ns: int = T0_NS,
    key_id: int | None = None,
    flags: int | None = None,
    channel_len: int | None = None,
    version: int = VERSION,
    magic: bytes = MAGIC,
) -> bytes:
    """Build a message by hand (any body, any header field), signed with ``keys`` if given."""
    head = HEADER.pack(
        magic,
        version,
        (FLAG_SIGNED if keys else 0) if flags is None else flags,
        type_id,
        source_id,
        (keys.active if keys else 0) if key_id is None else key_id,
        len(channel) if channel_len is None else channel_len,
        0,
        next(_seq) if seq is None else seq,
        t_meas_ns,
        t_pub_ns,
    )
    data = head + channel + body
    return data + keys.sign(data) if keys else data


def assert_well_formed(msg: Any) -> None:
    """What the decoder promises: the declared class all the way down, declared field types,
    and only finite floats."""
    cls = type(msg)
    assert hasattr(cls, "_fields"), f"{msg!r} is not a NamedTuple"
    hints = _hints(cls)
    assert len(msg) == len(cls._fields)
    for name in cls._fields:
        _assert_value(getattr(msg, name), hints[name], f"{cls.__name__}.{name}")


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _assert_value(value: Any, tp: Any, where: str) -> None:
    if tp is float:
        assert isinstance(value, float | int) and math.isfinite(value), f"{where} = {value!r}"
    elif typing.get_origin(tp) is tuple:
        assert isinstance(value, tuple), f"{where} = {value!r}"
        (item, _ellipsis) = typing.get_args(tp)
        for index, element in enumerate(value):
            if hasattr(item, "_fields"):
                assert type(element) is item, f"{where}[{index}] = {element!r}"
                assert_well_formed(element)
            else:
                _assert_value(element, item, f"{where}[{index}]")
    else:
        assert isinstance(value, tp), f"{where} = {value!r}"
