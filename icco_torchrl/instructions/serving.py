"""Plans served as the instruction the team trained on.

The team trained on waypoints that start at each robot's position and are redrawn every
waypoint interval (paper Sec. IV-C; ``env.params.waypoint_interval``). A planner (a language
model or the offline rule planner) answers once per instruction with a *route* per robot: the
points it planned, the last one the robot's formation *slot*. Handing those points to the team
once and keeping them fails a person watching: past the route's middle the instruction reward's
direction (nearest waypoint to its nearest neighbour) points back, and even the perfect one-step
follower stalls there (``experiments/language/serving``). So the route is *served*: at every
waypoint refresh, on the env's clock, each robot gets K fresh waypoints that

- start at its current position,
- advance along what is left of its route in steps of ``step`` metres (clipped to the training
  walk's scale, as the paper clips the LLM's vectors "to prevent the LLM outputs from becoming
  out-of-distribution relative to the training data"),
- and collapse onto the slot on arrival.

:func:`~icco_torchrl.envs.routes.serve_routes` is that rule, batched over envs and robots in
pure torch (no Python loop over either); :class:`PlanServer` holds the routes of the plan in
force and serves them. Everything that drives a team by language uses it: the language protocol
and ``icco instruct`` (:class:`~icco_torchrl.instructions.sources.LLMSource`), ``icco live`` and
the robot bridge (:class:`~icco_torchrl.live.loop.LiveLoop`).
"""

from __future__ import annotations

import torch

from icco_torchrl.envs.routes import DEFAULT_STEP, check_step, routes_from_plan, serve_routes


class PlanServer:
    """The routes of the plan in force and the rule that serves them (module docstring).

    ``routes`` are ``[B, N, R, 2]`` on the env's device (None until a plan is set). :meth:`serve`
    gives the waypoints for robots at ``pos``; :attr:`slots` ``[B, N, 2]`` are the routes' ends.
    """

    def __init__(self, n_waypoints: int, step: float = DEFAULT_STEP):
        if isinstance(n_waypoints, bool) or not isinstance(n_waypoints, int) or n_waypoints < 2:
            raise ValueError(f"n_waypoints must be an integer >= 2, got {n_waypoints!r}")
        self.n_waypoints, self.step = n_waypoints, check_step(step)
        self.routes: torch.Tensor | None = None

    def set_plan(self, start: torch.Tensor, planned: torch.Tensor) -> None:
        """The plan in force from now: robots at ``start`` ``[B, N, 2]`` got ``planned``
        ``[B, N, K', 2]`` (any K' >= 1; the last point is the slot)."""
        self.routes = routes_from_plan(start, planned.to(start))  # the robots' dtype, once

    @property
    def slots(self) -> torch.Tensor | None:
        return None if self.routes is None else self.routes[..., -1, :]

    def serve(self, pos: torch.Tensor) -> torch.Tensor:
        """Waypoints ``[B, N, K, 2]`` for robots at ``pos`` ``[B, N, 2]``."""
        if self.routes is None:
            raise RuntimeError("no plan to serve yet: call set_plan first")
        return serve_routes(pos, self.routes, self.n_waypoints, self.step)
