"""The simulated ESVS cameras: stereo pairs of the scenario world into a shared-memory frame ring."""

from modules.stereo_camera.module import StereoCamera as MODULE

__all__ = ["MODULE"]
