"""The ``nav_sensors`` process: IMU, DGPS, speedometer and two magnetometers, simulated from the
simulator's truth (modules/sim/nav/)."""

from modules.sim.nav.process import NavSensors as MODULE

__all__ = ["MODULE"]
