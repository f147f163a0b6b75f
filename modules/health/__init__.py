"""Health monitor: silent modules and stale inputs become HealthEvents."""

from modules.health.monitor import HealthMonitor as MODULE

__all__ = ["MODULE"]
