"""Simulation referee: drive measures from the simulator's truth."""

from modules.referee.module import Referee as MODULE

__all__ = ["MODULE"]
