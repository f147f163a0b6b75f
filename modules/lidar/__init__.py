"""Simulated lidars: two horizontal (obstacles) and two vertical (ground profile) scanners."""

from modules.lidar.module import Lidar as MODULE

__all__ = ["MODULE"]
