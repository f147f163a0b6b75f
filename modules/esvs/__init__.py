"""ESVS: the stereo vision system (simulated cameras, vision pipeline, real-time round, watchdog)."""

from modules.esvs.module import Esvs as MODULE

__all__ = ["MODULE"]
