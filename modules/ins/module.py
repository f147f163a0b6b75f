"""The navigation process: sensor messages in, VehicleState out at the IMU's pace (100 Hz).

Every measurement goes to the filter with its own ``t_meas_ns`` (the filter buffers and replays,
see navigator.py). The solution is published after each IMU step, stamped with that step's time;
if the IMU falls silent nothing is published, so consumers see VEHICLE_STATE go stale rather than
a solution that pretends to be current. Changes of navigation quality, GPS rejections and
re-acquisitions are HealthEvents.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from brain.course_config import DEFAULT_COURSE, load_course
from modules.ins.cores import FILTERS
from modules.ins.navigator import InsFilter
from protocol import channels
from protocol.codec import Envelope
from protocol.messages import GpsFix, ImuSample, MagHeading, NavQuality, Severity, WheelSpeed
from rascal.runtime.config import setting
from rascal.runtime.module import Module, Runtime
from rascal.runtime.ports import Port

# Ages after which an input counts as stale in the heartbeat: a few missed samples at each rate.
IMU_MAX_AGE_S = 0.05
GPS_MAX_AGE_S = 1.0
SPEED_MAX_AGE_S = 0.2
MAG_MAX_AGE_S = 0.5

QUALITY_SEVERITY = {
    NavQuality.DGPS: Severity.INFO,
    NavQuality.GPS: Severity.INFO,
    NavQuality.DEAD_RECKONING: Severity.WARNING,
    NavQuality.INVALID: Severity.ERROR,
}


@dataclass(frozen=True)
class InsConfig:
    filter: str = setting("ekf", "estimator: ekf (extended Kalman) or ukf (unscented, sigma points)")
    course: str = setting(str(DEFAULT_COURSE), "RDDF file whose first waypoint is the ENU origin")
    origin: str = setting("", "ENU origin 'lat,lon[,alt]' overriding the course's first waypoint")
    rate_hz: float = setting(100.0, "VehicleState rate; at most the IMU rate (one solution per IMU step)")


class Ins(Module):
    """INS/GPS navigation: IMU, DGPS, speedometer and two magnetometers fused into VehicleState."""

    name = "ins"
    default_source_id = 11
    Config = InsConfig
    interface = (
        Port("in", "`IMU`", "ImuSample", "100 Hz", "0.05 s (heartbeat)"),
        Port("in", "`GPS`", "GpsFix", "10 Hz", "1.0 s (heartbeat)"),
        Port("in", "`WHEEL_SPEED`", "WheelSpeed", "50 Hz", "0.2 s (heartbeat)"),
        Port("in", "`MAG_HEADING`", "MagHeading (two units)", "2 x 20 Hz", "0.5 s (heartbeat)"),
        Port(
            "out",
            "`VEHICLE_STATE`",
            "VehicleState: pose, speed, yaw rate, 5x5 covariance, quality",
            "one per IMU step (`rate_hz` 100)",
        ),
        Port(
            "out",
            "`HEALTH`",
            "`nav_quality` on every quality change; `gps_rejected`, `gps_reacquired` (1 Hz summary)",
            "on event",
        ),
        Port("out", "`MODULE_STATUS`", "ModuleStatus", "1 Hz"),
    )

    def __init__(self, config: InsConfig, runtime: Runtime) -> None:
        super().__init__(config, runtime)
        self.published = 0
        self._last_published_ns: int | None = None
        self._quality = NavQuality.INVALID
        self._rejected_reported = 0
        self._reacquisitions_reported = 0

    def on_start(self) -> None:
        config = self.config
        if config.filter not in FILTERS:
            raise ValueError(f"ins: filter must be one of {FILTERS}, not {config.filter!r}")
        if not config.rate_hz > 0:
            raise ValueError(f"ins: rate_hz must be positive, got {config.rate_hz}")
        self.filter = InsFilter(load_course(config.course, config.origin).origin, kind=config.filter)
        # Publish at most once per period, with 1 ms of slack for the IMU's own jitter.
        self.period_ns = int(1e9 / config.rate_hz) - 1_000_000
        bus = self.bus
        bus.subscribe(channels.IMU, self.on_imu)
        bus.subscribe(channels.GPS, self.on_gps)
        bus.subscribe(channels.WHEEL_SPEED, self.on_speed)
        bus.subscribe(channels.MAG_HEADING, self.on_mag)
        for channel, max_age_s in (
            (channels.IMU, IMU_MAX_AGE_S),
            (channels.GPS, GPS_MAX_AGE_S),
            (channels.WHEEL_SPEED, SPEED_MAX_AGE_S),
            (channels.MAG_HEADING, MAG_MAX_AGE_S),
        ):
            self.input(channel, max_age_s)
        self.every(1.0, self.report_quality, priority=2)

    def on_imu(self, msg: ImuSample, envelope: Envelope) -> None:
        nav = self.filter
        nav.on_imu(msg, envelope.t_meas_ns)
        t_ns = nav.t_ns
        if t_ns is None or t_ns != envelope.t_meas_ns:
            return  # not initialised yet, or a sample older than the state (counted by the filter)
        if self._last_published_ns is not None and t_ns - self._last_published_ns < self.period_ns:
            return
        state = nav.state(t_ns)
        self.bus.publish(channels.VEHICLE_STATE, state, t_meas_ns=t_ns)
        self._last_published_ns = t_ns
        self.published += 1
        if state.quality != self._quality:
            self._quality_changed(NavQuality(state.quality))

    def on_gps(self, msg: GpsFix, envelope: Envelope) -> None:
        self.filter.on_gps(msg, envelope.t_meas_ns)

    def on_speed(self, msg: WheelSpeed, envelope: Envelope) -> None:
        self.filter.on_speed(msg, envelope.t_meas_ns)

    def on_mag(self, msg: MagHeading, envelope: Envelope) -> None:
        self.filter.on_mag(msg, envelope.t_meas_ns)

    def report_quality(self) -> None:
        """Once a second: GPS rejections and re-acquisitions since the last report, and a quality
        change even when no IMU step publishes it (the quality decays with time alone)."""
        nav = self.filter
        rejected = nav.gps_rejected - self._rejected_reported
        if rejected:
            self.report(Severity.WARNING, "gps_rejected", f"{rejected} GPS fixes failed the innovation gate")
            self._rejected_reported = nav.gps_rejected
        if nav.reacquisitions > self._reacquisitions_reported:
            self._reacquisitions_reported = nav.reacquisitions
            self.report(
                Severity.WARNING,
                "gps_reacquired",
                f"GPS disagreed for over {nav.params.reacquire_after_s:.0f} s: position reset to it "
                f"(re-acquisition {nav.reacquisitions})",
            )
        quality = nav.quality(self.now_ns()) if nav.initialised else NavQuality.INVALID
        if quality != self._quality:
            self._quality_changed(quality)

    def _quality_changed(self, quality: NavQuality) -> None:
        before, self._quality = self._quality, quality
        self.report(QUALITY_SEVERITY[quality], "nav_quality", f"navigation {before.name} -> {quality.name}")

    def status_detail(self) -> str:
        nav = self.filter
        if not nav.initialised:
            return f"{self.config.filter}: waiting for GPS and a compass heading"
        P = nav.P
        sigma_m = math.sqrt(max(0.0, P[0, 0] + P[1, 1]))
        return (
            f"{self.config.filter} {self._quality.name}: sigma {sigma_m:.2f} m, sent {self.published}; "
            f"gps rejected {nav.gps_rejected}, reacquired {nav.reacquisitions}, replayed {nav.replayed}, "
            f"late {nav.late_rejected}"
        )
