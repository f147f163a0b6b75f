"""Synthetic obstacle source."""

from modules.beacon.beacon import Beacon as MODULE

__all__ = ["MODULE"]
