"""The brain's bird's-eye hazard map: sensor fusion, hazard classification and the cost layer.

Sans-IO: :class:`HazardFusion` takes poses and descriptors with their ``t_meas_ns`` and gives the
planner a :class:`CostMap` (a GridWindow plus float32 ``hazard_probability`` and ``cost``).
"""

from brain.fusion.cost import CostConfig, CostMap, build_cost_map
from brain.fusion.fusion import FusionConfig, FusionStats, HazardFusion
from brain.fusion.poses import PoseHistory
from brain.fusion.sensors import DEFAULT_SENSOR_MODELS, SensorClass, SensorModel
from brain.fusion.snapshot import SnapshotError, decode_snapshot, encode_snapshot
from brain.pose import Pose

__all__ = [
    "DEFAULT_SENSOR_MODELS",
    "CostConfig",
    "CostMap",
    "FusionConfig",
    "FusionStats",
    "HazardFusion",
    "Pose",
    "PoseHistory",
    "SensorClass",
    "SensorModel",
    "SnapshotError",
    "build_cost_map",
    "decode_snapshot",
    "encode_snapshot",
]
