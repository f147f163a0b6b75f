"""Simulated ESVS cameras: rectified stereo pairs of the scenario world with ground truth.

``render_pair(world, pose, rig, rng)`` (or a ``StereoRenderer`` held across frames) returns a
``StereoFrame``: left and right 8-bit grey images, the left image's true disparity (NaN on sky),
depth, and a label image (``LABEL_*`` classes, or obstacle index + 1). Simulation code only: it
reads the world's truth.
"""

from modules.sim.camera.render import (
    LABEL_GROUND,
    LABEL_HAZARD,
    LABEL_LANE_BORDER,
    LABEL_SKY,
    CameraConfig,
    StereoFrame,
    StereoRenderer,
    render_pair,
)

__all__ = [
    "LABEL_GROUND",
    "LABEL_HAZARD",
    "LABEL_LANE_BORDER",
    "LABEL_SKY",
    "CameraConfig",
    "StereoFrame",
    "StereoRenderer",
    "render_pair",
]
