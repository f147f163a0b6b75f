"""The brain process: fusion, sensor health and planning (libraries in the top-level brain/)."""

from modules.brain.module import Brain as MODULE

__all__ = ["MODULE"]
