"""Every simulated sensor's loop: one measurement per new true pose, as the scenario's faults allow."""

from __future__ import annotations

from modules.sim.sensing import SensedTruth
from modules.sim.world import FaultKind, SensorFault, World
from protocol import channels
from protocol.codec import Envelope
from protocol.messages import SimTruth
from rascal.runtime.rtdb import Latest

MS = 1_000_000
FAULTS = (
    SensorFault(("lidar_h_left",), FaultKind.NOISE, 10.0, 20.0, magnitude=3.0),
    SensorFault(("lidars",), FaultKind.STUCK, 20.0, 30.0),
    SensorFault(("lidar_h_left",), FaultKind.SILENCE, 30.0, 40.0),
    SensorFault(("lidar_h_left",), FaultKind.OUTAGE, 40.0, 50.0),
)


class Sensor:
    """A SensedTruth over a truth stream fed by hand, measuring (time, noise scale)."""

    def __init__(self) -> None:
        self.truth: Latest[SimTruth] = Latest(channels.SIM_TRUTH, 500 * MS)
        self.loop: SensedTruth[tuple[float, float]] = SensedTruth(self.truth, World(faults=FAULTS), "lidar_h_left")
        self.measured = 0

    def pose_at(self, t_s: float) -> None:
        t_ns = round(t_s * 1e3) * MS
        truth = SimTruth(0.0, 0.0, 0.0, 5.0, 0.0, 0.0, 5.0 * t_s, 0, scenario_time_s=t_s)
        self.truth.update(truth, Envelope(channels.SIM_TRUTH, 5, 0, t_ns, t_ns, t_ns, 0, 0, t_ns))

    def step(self, now_s: float) -> tuple[tuple[float, float], int] | None:
        def measure(truth: SimTruth, t_meas_ns: int, noise: float) -> tuple[float, float]:
            self.measured += 1
            return truth.scenario_time_s, noise

        return self.loop.step(round(now_s * 1e3) * MS, measure)


def test_one_measurement_per_new_pose_and_none_from_a_stale_one() -> None:
    sensor = Sensor()
    assert sensor.step(1.0) is None  # no truth yet
    sensor.pose_at(1.0)
    assert sensor.step(1.01) == ((1.0, 1.0), 1000 * MS)
    assert sensor.step(1.02) is None and sensor.measured == 1  # the same pose: no new measurement
    sensor.pose_at(2.0)
    assert sensor.step(2.6) is None  # 0.6 s old: stale


def test_the_faults_noise_stuck_silence_and_outage() -> None:
    sensor = Sensor()
    sensor.pose_at(15.0)
    assert sensor.step(15.0) == ((15.0, 3.0), 15_000 * MS) and sensor.loop.fault_names == "noise"
    sensor.pose_at(25.0)  # stuck ("lidars" names every lidar): the last output under the new stamp
    assert sensor.step(25.0) == ((15.0, 3.0), 25_000 * MS) and sensor.measured == 1
    assert sensor.loop.fault_names == "stuck"
    for t_s in (35.0, 45.0):  # silence, then an outage: nothing
        sensor.pose_at(t_s)
        assert sensor.step(t_s) is None
    sensor.pose_at(55.0)
    assert sensor.step(55.0) == ((55.0, 1.0), 55_000 * MS) and sensor.loop.fault_names == ""


def test_stuck_before_any_output_sends_nothing() -> None:
    sensor = Sensor()
    sensor.pose_at(25.0)
    assert sensor.step(25.0) is None and sensor.measured == 0
