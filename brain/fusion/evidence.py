"""The map's evidence: one log-odds layer per sensor class and a lane layer, on a rolling window.

Log-odds 0 is "unknown" (hazard probability 0.5). Detections add, clear views subtract, each
clamped to [minimum, maximum] so that no amount of old evidence outweighs a few new observations.
Every layer fades toward 0 with a half-life (temporal validity: what was seen a while ago and
not since is gradually forgotten). The fused hazard log-odds sums the classes, plus a bonus for
every further class that independently supports a hazard in the cell: agreement between
different sensor types confirms faster than repetition by one. One class's clear view does not
veto another's detection (each kind of sensor sees different hazards).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from brain.fusion.raster import Stamp
from brain.grid import GridWindow, roll_into

Layer = NDArray[np.float32]


class EvidenceLayers:
    """``classes`` log-odds layers plus the lane layer (0 inside the lane .. 1 surely outside)."""

    def __init__(self, window: GridWindow, classes: int, minimum: float, maximum: float) -> None:
        if not minimum < 0 < maximum:
            raise ValueError(f"evidence bounds must straddle 0, got [{minimum}, {maximum}]")
        self.window = window
        self.minimum = np.float32(minimum)
        self.maximum = np.float32(maximum)
        self.evidence = np.zeros((classes, *window.shape), dtype=np.float32)
        self.lane = np.zeros(window.shape, dtype=np.float32)

    def roll(self, window: GridWindow) -> None:
        """Move onto ``window``: cells both cover keep their evidence, new cells are unknown."""
        self.evidence = np.stack([roll_into(layer, self.window, window, fill=0.0) for layer in self.evidence])
        self.lane = roll_into(self.lane, self.window, window, fill=0.0)
        self.window = window

    def decay(self, factors: ArrayLike, lane_factor: float) -> None:
        """Fade each class by its own factor (one per layer) and the lane layer by ``lane_factor``."""
        self.evidence *= np.asarray(factors, dtype=np.float32).reshape(-1, 1, 1)
        self.lane *= np.float32(lane_factor)

    def add(self, sensor_class: int, stamp: Stamp) -> None:
        """Add a message's log-odds (drawn on ``stamp``) to one class, within the bounds."""
        stamp.add_to(self.evidence[sensor_class], float(self.minimum), float(self.maximum))

    def add_capped(self, sensor_class: int, stamp: Stamp, cap: float) -> None:
        """Add a message's log-odds to one class, raising no cell above ``cap``: evidence that a
        hazard may be there, never by itself that it is."""
        stamp.add_capped_to(self.evidence[sensor_class], min(cap, float(self.maximum)))

    def mark_lane(self, stamp: Stamp, belief: float, outside: bool) -> None:
        """Cells drawn on ``stamp`` are outside the lane (or inside it) with ``belief`` 0..1."""
        touched = stamp.touched()
        if touched is None:
            return
        box, drawn = touched
        cells = self.lane[box]
        if outside:
            np.maximum(cells, np.float32(belief), out=cells, where=drawn)
        else:
            np.minimum(cells, np.float32(1.0 - belief), out=cells, where=drawn)
        stamp.clear()

    def fused_log_odds(self, agreement_min: float, agreement_log_odds: float, support_log_odds: float) -> Layer:
        """Hazard log-odds per cell: the classes' sum, plus ``agreement_log_odds`` for each class
        beyond the first whose evidence exceeds ``agreement_min``. A class's clear view (its
        negative evidence) counts against another class's detection less the stronger that is,
        not at all from ``support_log_odds`` up: the horizontal lidars passing over a low rock
        say nothing about the rock stereo saw."""
        total = self.evidence[0].copy()
        for layer in self.evidence[1:]:
            total += layer
        if len(self.evidence) == 1:
            return total
        negative = np.minimum(self.evidence[0], np.float32(0.0))
        for layer in self.evidence[1:]:
            negative += np.minimum(layer, np.float32(0.0))
        # positive = total - negative; fused = total - negative * min(1, positive / support)
        release = total - negative
        release *= np.float32(1.0 / support_log_odds)
        np.minimum(release, np.float32(1.0), out=release)
        release *= negative
        total -= release
        if agreement_log_odds:
            threshold = np.float32(agreement_min)
            supporting = (self.evidence[0] > threshold).view(np.int8).copy()
            for layer in self.evidence[1:]:
                supporting += (layer > threshold).view(np.int8)
            for count in range(2, len(self.evidence) + 1):
                np.add(total, np.float32(agreement_log_odds), out=total, where=supporting >= count)
        return total
