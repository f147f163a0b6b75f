"""Shared builders for the fusion tests: navigation states, descriptors and a map with one pose."""

from __future__ import annotations

import math

import numpy as np

from brain.fusion import CostMap, FusionConfig, HazardFusion
from brain.grid import GridWindow
from protocol.messages import Frame, NavQuality, Obstacle, ObstacleList, Sensor, VehicleState

MS = 1_000_000


def state(
    east: float, north: float, yaw: float, speed: float = 0.0, yaw_rate: float = 0.0, yaw_std: float = 0.0
) -> VehicleState:
    """A navigation state; its covariance claims ``yaw_std`` of heading and nothing else."""
    covariance = [0.0] * 25
    covariance[12] = yaw_std**2
    return VehicleState(
        east,
        north,
        0.0,
        yaw,
        speed,
        speed * math.cos(yaw),
        speed * math.sin(yaw),
        yaw_rate,
        tuple(covariance),
        NavQuality.DGPS,
    )


def box(x: float, y: float, size: float = 1.0, confidence: float = 0.86, yaw: float = 0.0) -> Obstacle:
    return Obstacle(x, y, size, size, 0.7, yaw, confidence, math.hypot(x, y))


def obstacles(sensor: Sensor, *items: Obstacle, frame: Frame = Frame.VEHICLE) -> ObstacleList:
    return ObstacleList(sensor, frame, tuple(items))


def parked(east: float = 100.0, north: float = 50.0, yaw: float = 0.0, **config: float) -> HazardFusion:
    """A map whose vehicle stands still at (east, north, yaw) from t = 0."""
    fusion = HazardFusion(FusionConfig(**config))
    fusion.add_pose(0, state(east, north, yaw))
    return fusion


def enu_of(east: float, north: float, yaw: float, x: float, y: float) -> tuple[float, float]:
    """ENU of vehicle-frame (x, y) for a vehicle at (east, north, yaw)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return east + c * x - s * y, north + s * x + c * y


def cells_near(window: GridWindow, east: float, north: float, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Index arrays of the cells whose centres lie within ``radius`` of a point."""
    grid_east, grid_north = window.cell_centres()
    return np.nonzero(np.hypot(grid_east - east, grid_north - north) <= radius)


def probability_at(cost_map: CostMap, east: float, north: float) -> float:
    row, col = cost_map.window.cell_of(east, north)
    return float(cost_map.hazard_probability[row, col])
