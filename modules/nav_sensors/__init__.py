"""Simulated navigation sensors: IMU, DGPS, speedometer and two magnetometers from the simulator's truth."""

from modules.nav_sensors.module import NavSensors as MODULE

__all__ = ["MODULE"]
