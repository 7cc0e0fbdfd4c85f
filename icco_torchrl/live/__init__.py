"""Driving a trained team live: a real-time loop that steps the team and takes instructions at
any moment, a web page to watch and steer it, and a bridge to real robots."""

from icco_torchrl.live.loop import LiveLoop, PlannerStatus, TickState

__all__ = ["LiveLoop", "PlannerStatus", "TickState"]
