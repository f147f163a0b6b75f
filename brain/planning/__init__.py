"""The brain's planner: RASCAL's keep / re-plan / slow-down behaviour with Kratos' A* fallback.

Sans IO: `Planner.plan` takes the pose, the fused map (a `brain.grid.GridWindow` with hazard
probability and cost arrays) and the health monitor's speed limit, and returns a
`protocol.messages.Path` in a `PlanResult`.
"""

from brain.planning.config import PlannerConfig
from brain.planning.frame import CorridorFrame
from brain.planning.planner import PlanMode, Planner, PlanResult

__all__ = ["CorridorFrame", "PlanMode", "PlanResult", "Planner", "PlannerConfig"]
