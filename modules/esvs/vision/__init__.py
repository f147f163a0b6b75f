"""ESVS vision: one stereo pair in, ObstacleList and LaneBorders (VEHICLE frame) out.

``process(left, right, rig)`` runs the whole pipeline (pipeline.py); the stages are separate
modules: disparity, band (rows matched and 3D points), obstacle_points (Kratos' Algorithm 1),
clusters (descriptors), lane_heat and lane_fit (Kratos' lane detection).
"""

from modules.esvs.vision.pipeline import STAGES, Stats, VisionParams, process

__all__ = ["STAGES", "Stats", "VisionParams", "process"]
