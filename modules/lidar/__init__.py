"""The lidars: what a vehicle makes of its scanners' returns (scan.py, cluster.py, profile.py,
sweep.py). The ``lidar`` process is a simulated one (modules/sim/lidar/process.py): it plays the
scanners from the simulator's truth and publishes what they would."""

from typing import Any


def __getattr__(name: str) -> Any:
    # Looked up on use: the simulated process imports this package's modules, so importing it
    # here, eagerly, would be a cycle whenever the process is imported first.
    if name == "MODULE":
        from modules.sim.lidar.process import Lidar

        return Lidar
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
