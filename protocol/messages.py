"""Every message on the bus, declared once.

Units are in the field names (``_m``, ``_mps``, ``_rad``, ``_ns``...). Frames: ENU is the local
East-North-Up frame of the deployment's origin; VEHICLE is x forward, y left, z up from the rear
axle centre on the ground. Times are int64 nanoseconds of shared time. The fixed header (see
SPEC.md) already carries source, sequence, ``t_meas_ns`` and ``t_pub_ns``; bodies do not repeat
them. To evolve a message, append fields with defaults; never reorder, retype or remove.
"""

from __future__ import annotations

import enum
from typing import NamedTuple

from protocol.schema import message


class Frame(enum.IntEnum):
    VEHICLE = 0
    ENU = 1


class Sensor(enum.IntEnum):
    """Which sensor produced a descriptor (RASCAL: 2 horizontal + 2 vertical lidars, stereo)."""

    UNKNOWN = 0
    LIDAR_H_LEFT = 1
    LIDAR_H_RIGHT = 2
    LIDAR_V_LEFT = 3
    LIDAR_V_RIGHT = 4
    ESVS = 5
    SIM = 6
    SYNTHETIC = 7
    LIDAR_SWEEP = 8


class NavQuality(enum.IntEnum):
    INVALID = 0
    DEAD_RECKONING = 1
    GPS = 2
    DGPS = 3


class ModuleState(enum.IntEnum):
    STARTING = 0
    OK = 1
    DEGRADED = 2
    FAILED = 3
    STOPPING = 4


class Severity(enum.IntEnum):
    INFO = 0
    WARNING = 1
    ERROR = 2
    CRITICAL = 3


class TimeSyncKind(enum.IntEnum):
    REQUEST = 0
    REPLY = 1


class StopMode(enum.IntEnum):
    """Operator stop channel: RUN drives, PAUSE holds the vehicle stopped until RUN, ESTOP stops
    and stays stopped until the process restarts (DARPA's e-stop had the same two levels)."""

    RUN = 0
    PAUSE = 1
    ESTOP = 2


@message(type_id=1)
class TimeSync(NamedTuple):
    """NTP-style exchange. A client sends REQUEST with t1 (its local clock); the master answers
    REPLY to ``client_source_id`` echoing t1 with its receive (t2) and send (t3) times."""

    kind: int
    client_source_id: int
    t1_local_ns: int
    t2_master_ns: int = 0
    t3_master_ns: int = 0


@message(type_id=2)
class ModuleStatus(NamedTuple):
    """Heartbeat of one process (1 Hz), with its timing and health."""

    module: str
    state: int
    uptime_s: float
    loop_period_ns: int
    jitter_ns: int
    overruns: int
    restarts: int
    rx_rejected: int
    stale_inputs: tuple[str, ...]
    clock_state: int
    clock_offset_ns: int
    clock_error_bound_ns: int
    detail: str = ""
    cpu_pct: float = -1.0  # of one core over the last heartbeat period, children included; < 0 unknown


@message(type_id=3)
class HealthEvent(NamedTuple):
    """Something a module wants a human or the supervisor to know (stale input, restart...)."""

    module: str
    severity: int
    code: str
    text: str


@message(type_id=4)
class ConfigUpdate(NamedTuple):
    """Change one setting of a running module (``module`` is its name or ``name/instance``);
    ``value`` is text parsed by that setting's type, as on the command line (``--set key=value``)."""

    module: str
    key: str
    value: str


@message(type_id=10)
class ImuSample(NamedTuple):
    """Body-frame specific force and angular rate (x forward, y left, z up)."""

    accel_x_mps2: float
    accel_y_mps2: float
    accel_z_mps2: float
    gyro_x_radps: float
    gyro_y_radps: float
    gyro_z_radps: float


@message(type_id=11)
class GpsFix(NamedTuple):
    """WGS84 position fix with one-sigma accuracies."""

    lat_deg: float
    lon_deg: float
    alt_m: float
    std_east_m: float
    std_north_m: float
    std_up_m: float
    quality: int  # NavQuality
    satellites: int


@message(type_id=12)
class WheelSpeed(NamedTuple):
    """Speedometer."""

    speed_mps: float
    odometer_m: float


@message(type_id=13)
class MagHeading(NamedTuple):
    """One magnetometer's heading, clockwise from north as ENU yaw is counter-clockwise from east:
    yaw_rad = pi/2 - heading_from_north_rad."""

    magnetometer: int
    heading_from_north_rad: float
    std_rad: float


@message(type_id=20)
class VehicleState(NamedTuple):
    """Navigation solution in ENU. ``covariance`` is the row-major 5x5 covariance of
    [east_m, north_m, yaw_rad, speed_mps, yaw_rate_radps]."""

    east_m: float
    north_m: float
    up_m: float
    yaw_rad: float
    speed_mps: float
    vel_east_mps: float
    vel_north_mps: float
    yaw_rate_radps: float
    covariance: tuple[float, ...]
    quality: int  # NavQuality


class Obstacle(NamedTuple):
    """Compact object descriptor: an upright box in ``ObstacleList.frame``."""

    x_m: float
    y_m: float
    length_m: float
    width_m: float
    height_m: float
    yaw_rad: float
    confidence: float
    range_m: float


@message(type_id=21)
class ObstacleList(NamedTuple):
    sensor: int  # Sensor
    frame: int  # Frame
    obstacles: tuple[Obstacle, ...]


@message(type_id=22)
class SurfaceProfile(NamedTuple):
    """Vertical-lidar terrain: ground height along a forward scan line at ``lateral_m``."""

    sensor: int  # Sensor
    lateral_m: float
    ranges_m: tuple[float, ...]
    heights_m: tuple[float, ...]


class GroundStretch(NamedTuple):
    """A stretch of the ground line a sweeping lidar saw, as a box in the vehicle frame: level
    ground (``height_m`` 0), or ground at least ``height_m`` below (< 0) or above (> 0) the plane
    the vehicle stands on."""

    x_near_m: float
    x_far_m: float
    y_right_m: float
    y_left_m: float
    height_m: float


@message(type_id=24)
class GroundSweep(NamedTuple):
    """Sweeping-lidar terrain: where a scanner pitched down meets the ground ahead, right to left."""

    sensor: int  # Sensor
    stretches: tuple[GroundStretch, ...]


class LaneBorder(NamedTuple):
    """Border y = c0 + c1*x + c2*x^2 in the vehicle frame, valid for x in [x_min_m, x_max_m]."""

    side: int  # +1 left, -1 right
    c0_m: float
    c1: float
    c2_per_m: float
    x_min_m: float
    x_max_m: float
    confidence: float


@message(type_id=23)
class LaneBorders(NamedTuple):
    sensor: int  # Sensor
    borders: tuple[LaneBorder, ...]


class PathPoint(NamedTuple):
    east_m: float
    north_m: float
    speed_mps: float


@message(type_id=30)
class Path(NamedTuple):
    """Planned path in ENU with target speeds; ``path_id`` changes when the planner re-plans."""

    path_id: int
    points: tuple[PathPoint, ...]
    slow_mode: bool
    # Measurement time of the stalest obstacle picture this plan used: the oldest of the newest
    # descriptors of each live obstacle sensor. The first command after the path, minus this, is
    # the measurement-to-actuator latency. 0: unknown.
    t_input_ns: int = 0
    reverse: bool = False  # drive it backwards: points and speeds in the order of travel, speeds as magnitudes


@message(type_id=31)
class ActuatorCommand(NamedTuple):
    """Throttle and brake as fractions 0..1; steering angle of the front wheels, left positive.
    ``reverse`` selects the reverse gear; the vehicle changes gear only at a standstill."""

    throttle: float
    brake: float
    steering_rad: float
    stop_reason: str = ""
    reverse: bool = False


@message(type_id=32)
class StopCommand(NamedTuple):
    """E-stop / pause, honoured by control at once; ``mode`` is a StopMode."""

    mode: int
    reason: str


@message(type_id=40)
class MapSnapshot(NamedTuple):
    """The brain's bird's-eye map, low rate, for viewing and logs. ``cells`` is ``rows x cols``
    uint8 row-major (row 0 south, column 0 west) of hazard probability x 255, zlib-compressed;
    cell (r, c) has its south-west corner at (origin_east_m + c*res, origin_north_m + r*res)."""

    origin_east_m: float
    origin_north_m: float
    resolution_m: float
    rows: int
    cols: int
    cells: bytes


@message(type_id=90)
class SimTruth(NamedTuple):
    """Simulator only: the true vehicle state, for evaluation. Never consumed by the stack."""

    east_m: float
    north_m: float
    yaw_rad: float
    speed_mps: float
    yaw_rate_radps: float
    steering_rad: float
    progress_m: float
    collisions: int
    accel_mps2: float = 0.0
    corridor_exits: int = 0
    scenario_time_s: float = 0.0  # simulated time since the scenario started: fault schedules run on it
