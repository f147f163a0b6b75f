"""The lidars: what a vehicle makes of its scanners' returns (scan.py, cluster.py, profile.py,
sweep.py). The ``lidar`` process is a simulated one (modules/sim/lidar/process.py): it plays the
scanners from the simulator's truth and publishes what they would."""

from modules.sim.lidar.process import Lidar as MODULE

__all__ = ["MODULE"]
