"""Channel names, the message type each carries, and the channel -> UDP port mapping.

A channel is declared here once with its type; publishing or subscribing a declared channel
with another type is a local error. Undeclared channels may be used with an explicit type.
"""

from __future__ import annotations

import zlib

from protocol import messages as m

TIME_SYNC = "TIME_SYNC"
MODULE_STATUS = "MODULE_STATUS"
HEALTH = "HEALTH"
IMU = "IMU"
GPS = "GPS"
WHEEL_SPEED = "WHEEL_SPEED"
MAG_HEADING = "MAG_HEADING"
VEHICLE_STATE = "VEHICLE_STATE"
OBSTACLES_LIDAR = "OBSTACLES_LIDAR"
OBSTACLES_ESVS = "OBSTACLES_ESVS"
OBSTACLES_BEACON = "OBSTACLES_BEACON"
SURFACE_PROFILE = "SURFACE_PROFILE"
GROUND_SWEEP = "GROUND_SWEEP"
LANE_BORDERS = "LANE_BORDERS"
PATH = "PATH"
ACTUATOR_COMMAND = "ACTUATOR_COMMAND"
SIM_TRUTH = "SIM_TRUTH"
CONFIG = "CONFIG"
STOP = "STOP"
MAP_SNAPSHOT = "MAP_SNAPSHOT"

CHANNEL_TYPES: dict[str, type] = {
    TIME_SYNC: m.TimeSync,
    MODULE_STATUS: m.ModuleStatus,
    HEALTH: m.HealthEvent,
    IMU: m.ImuSample,
    GPS: m.GpsFix,
    WHEEL_SPEED: m.WheelSpeed,
    MAG_HEADING: m.MagHeading,
    VEHICLE_STATE: m.VehicleState,
    OBSTACLES_LIDAR: m.ObstacleList,
    OBSTACLES_ESVS: m.ObstacleList,
    OBSTACLES_BEACON: m.ObstacleList,
    SURFACE_PROFILE: m.SurfaceProfile,
    GROUND_SWEEP: m.GroundSweep,
    LANE_BORDERS: m.LaneBorders,
    PATH: m.Path,
    ACTUATOR_COMMAND: m.ActuatorCommand,
    SIM_TRUTH: m.SimTruth,
    CONFIG: m.ConfigUpdate,
    STOP: m.StopCommand,
    MAP_SNAPSHOT: m.MapSnapshot,
}

# The smallest span at which every declared channel has a port of its own: a subscriber's socket
# then wakes only for the channel it asked for (at 16, SIM_TRUTH at 100 Hz woke control, INS and
# the brain through the port it shared with PATH, MAG_HEADING and LANE_BORDERS).
DEFAULT_PORT_SPAN = 67


def port_offset(channel: str, span: int = DEFAULT_PORT_SPAN) -> int:
    """Offset from the bus base port for ``channel``: CRC-32 (zlib/IEEE) of its ASCII name mod
    span. Spreading channels over ports lets the kernel filter what a subscriber never asked for."""
    return zlib.crc32(channel.encode("ascii")) % span


def type_for(channel: str, explicit: type | None = None) -> type:
    declared = CHANNEL_TYPES.get(channel)
    if explicit is not None and declared is not None and explicit is not declared:
        raise TypeError(f"channel {channel} carries {declared.__name__}, not {explicit.__name__}")
    if explicit is None and declared is None:
        raise KeyError(f"channel {channel!r} is not declared in protocol.channels; pass its message type")
    return explicit or declared  # type: ignore[return-value]
