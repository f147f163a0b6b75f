"""Where the rolling window sits: ahead of the vehicle, turned to the heading's axis, moved in jumps.

The window is axis-aligned in ENU (brain/grid.py), so it cannot rotate with the vehicle. Its
centre is put ``lead_m`` ahead of the vehicle, but never so far that the vehicle comes closer
than ``margin_m`` to an edge. With the default 96 m square, a 40 m lead and 3 m between moves, the
window reaches at least 85 m ahead and 5 m behind on every heading. A rectangular window (the
planner benchmark's 120 x 30 m) lays its long side along whichever axis, east or north, the
heading is nearer to, switching only 10 degrees past the diagonal so that a vehicle driving
near 45 degrees does not flip it back and forth. Moving the window copies every layer, so it
moves only once its ideal centre is ``recentre_m`` away (or its orientation should change).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from brain.grid import GridWindow
from brain.pose import Pose

HYSTERESIS_RAD = math.radians(10.0)


@dataclass(frozen=True)
class WindowPlacement:
    east_m: float  # extent along east (along the long axis's choice when turning)
    north_m: float  # extent along north
    resolution_m: float
    lead_m: float  # window centre this far ahead of the vehicle...
    recentre_m: float  # move once the ideal centre is this far from the current one
    margin_m: float = 5.0  # ...but the vehicle at least this far inside every edge
    turn_with_heading: bool = True  # a rectangle lays its long side along the heading's nearer axis

    def __post_init__(self) -> None:
        if not (self.east_m > 0 and self.north_m > 0 and self.resolution_m > 0):
            raise ValueError("window extents and resolution must be positive")
        if self.lead_m < 0 or not self.resolution_m <= self.recentre_m < self.margin_m:
            raise ValueError("need lead_m >= 0 and one cell <= recentre_m < margin_m")
        if 2 * self.margin_m >= min(self.east_m, self.north_m):
            raise ValueError("margin_m must be less than half the window's shorter side")

    def place(self, pose: Pose, current: GridWindow | None = None) -> GridWindow:
        width, height = self._extents(pose, current)
        east, north = self._centre(pose, width, height)
        return GridWindow.centred(east, north, width, height, self.resolution_m)

    def needs_move(self, current: GridWindow, pose: Pose) -> bool:
        width, height = self._extents(pose, current)
        if (round(height / self.resolution_m), round(width / self.resolution_m)) != current.shape:
            return True
        east, north = self._centre(pose, width, height)
        centre_east = current.origin_east_m + current.cols * current.resolution_m / 2
        centre_north = current.origin_north_m + current.rows * current.resolution_m / 2
        return math.hypot(east - centre_east, north - centre_north) > self.recentre_m

    def _extents(self, pose: Pose, current: GridWindow | None) -> tuple[float, float]:
        """(east, north) extents: the long side along the axis nearer the heading."""
        long_side, short_side = max(self.east_m, self.north_m), min(self.east_m, self.north_m)
        if not self.turn_with_heading or long_side == short_side:
            return self.east_m, self.north_m
        off_east = math.atan2(abs(math.sin(pose.yaw_rad)), abs(math.cos(pose.yaw_rad)))  # 0..pi/2
        along_east = off_east < math.pi / 4
        if current is not None and abs(off_east - math.pi / 4) < HYSTERESIS_RAD:
            along_east = current.cols >= current.rows  # near the diagonal: keep what we have
        return (long_side, short_side) if along_east else (short_side, long_side)

    def _centre(self, pose: Pose, width: float, height: float) -> tuple[float, float]:
        reach_east, reach_north = width / 2 - self.margin_m, height / 2 - self.margin_m
        ahead_east = min(max(self.lead_m * math.cos(pose.yaw_rad), -reach_east), reach_east)
        ahead_north = min(max(self.lead_m * math.sin(pose.yaw_rad), -reach_north), reach_north)
        return pose.east_m + ahead_east, pose.north_m + ahead_north
