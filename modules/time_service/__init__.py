"""Shared time service (the master)."""

from modules.time_service.service import TimeService as MODULE

__all__ = ["MODULE"]
