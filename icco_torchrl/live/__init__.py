"""Driving a trained team live: a real-time loop that steps the team and takes instructions at any moment."""

from icco_torchrl.live.loop import LiveLoop, PlannerStatus, TickState

__all__ = ["LiveLoop", "PlannerStatus", "TickState"]
