"""Client library for the ESVS stereo vision system as a device on the bus (see README.md)."""

from esvs_client.client import DEFAULT_SOURCE_ID, EsvsClient, LaneReport, ObstacleReport

__all__ = ["DEFAULT_SOURCE_ID", "EsvsClient", "LaneReport", "ObstacleReport"]
