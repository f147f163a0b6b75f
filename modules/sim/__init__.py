"""Simulated world and vehicle: the scenario, the dynamics, and the truth they produce."""

from modules.sim.simulator import Simulator as MODULE

__all__ = ["MODULE"]
