"""Instruction sources: waypoints for the robots, from a random walk, a quadrant reference or language."""

from icco_torchrl.instructions.llm import LLMPlanner, PlanResult, plan_waypoints
from icco_torchrl.instructions.sources import (
    FixedSource,
    InstructionSource,
    LLMSource,
    QuadrantSource,
    RandomWalkSource,
)

__all__ = [
    "FixedSource",
    "InstructionSource",
    "LLMPlanner",
    "LLMSource",
    "PlanResult",
    "QuadrantSource",
    "RandomWalkSource",
    "plan_waypoints",
]
