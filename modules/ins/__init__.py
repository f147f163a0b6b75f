"""Inertial navigation: EKF or UKF (filterpy) fusing IMU, DGPS, speedometer and two magnetometers."""

from modules.ins.module import Ins as MODULE

__all__ = ["MODULE"]
