"""The ``stereo_camera`` process: the simulated ESVS cameras, stereo pairs of the scenario world
into a shared-memory frame ring (modules/sim/camera/)."""

from modules.sim.camera.process import StereoCamera as MODULE

__all__ = ["MODULE"]
