"""Inertial navigation: an EKF fusing IMU, DGPS, speedometer and two magnetometers (``ekf.InsEkf``)."""
