"""Instruction sources: waypoints for the robots, from a random walk, a quadrant reference or language."""
from icco_torchrl.instructions.llm import LLMPlanner, PlanResult, plan_waypoints

__all__ = ["LLMPlanner", "PlanResult", "plan_waypoints"]
