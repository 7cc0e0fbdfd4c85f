"""Language instructions: the planner that turns an instruction into waypoints, and the waypoint
source that drives an env with it (:class:`LLMSource`). The other waypoint sources (random walk,
quadrant reference, fixed waypoints) are the env's: :mod:`icco_torchrl.envs`."""

from icco_torchrl.instructions.llm import LLMPlanner, PlanResult, plan_waypoints
from icco_torchrl.instructions.sources import LLMSource

__all__ = ["LLMPlanner", "LLMSource", "PlanResult", "plan_waypoints"]
