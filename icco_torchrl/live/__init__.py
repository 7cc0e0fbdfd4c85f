"""Driving a trained team live: a real-time loop that steps the team and takes instructions at any moment."""
from icco_torchrl.live.loop import LiveLoop, PlannerStatus

__all__ = ["LiveLoop", "PlannerStatus"]
