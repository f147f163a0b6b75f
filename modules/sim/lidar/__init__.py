"""The simulated lidars: what each scanner would return from a true pose in the scenario world.

The scanners' geometry and what the vehicle makes of their returns are the lidar module's
(modules/lidar: scan.py, profile.py, sweep.py, cluster.py); this package only plays the world.
"""
