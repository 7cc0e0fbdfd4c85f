"""Routes served as waypoints: the rule that turns a robot's route into the K waypoints of the
instruction the team trained on, batched over envs and robots in pure torch.

At every waypoint refresh a robot gets K waypoints that start at its current position, advance
along what is left of its route ``step`` metres apart and collapse onto the route's last point
(its slot) on arrival. The plan server (:mod:`icco_torchrl.instructions.serving`) serves planned
routes with it; the env serves straight training routes to a random slot with the same rule
(``waypoint_route_prob``).

    >>> import torch
    >>> routes = torch.tensor([[[0.0, 0.0], [1.0, 0.0]]])  # one robot: from (0, 0) to (1, 0)
    >>> serve_routes(torch.tensor([[0.0, 0.0]]), routes, n_waypoints=4, step=0.3)
    tensor([[[0.3000, 0.0000],
             [0.6000, 0.0000],
             [0.9000, 0.0000],
             [1.0000, 0.0000]]])
    >>> serve_routes(torch.tensor([[0.7, 0.4]]), routes, n_waypoints=2, step=0.3)  # off the route
    tensor([[[0.8800, 0.1600],
             [1.0000, 0.0000]]])
"""

from __future__ import annotations

import torch

# Metres between served waypoints. The training walk's increments are N(0, sigma^2 I) per axis
# (sigma = 0.19 m, one robot step): a step of 0.25 m is their mean length, and it keeps the
# robot (up to 0.19 m a step, 4 steps a refresh) short of the last waypoint within a refresh, so
# the instruction reward's direction never points back. Measured against 0.19, 0.35 and 0.5 m:
# experiments/language/serving/README.md.
DEFAULT_STEP = 0.25


def check_step(step: float) -> float:
    """``step`` as a float, or a ``ValueError`` of one line."""
    if isinstance(step, bool) or not isinstance(step, (int, float)) or not step > 0:
        raise ValueError(f"the serving step must be a number of metres > 0, got {step!r}")
    return float(step)


def routes_from_plan(start: torch.Tensor, planned: torch.Tensor) -> torch.Tensor:
    """Routes ``[..., K + 1, 2]``: each robot's position when it was planned for (``start``
    ``[..., 2]``), then the planner's points ``[..., K, 2]``, the last one its slot."""
    return torch.cat([start.unsqueeze(-2).to(planned), planned], dim=-2)


def serve_routes(
    pos: torch.Tensor, routes: torch.Tensor, n_waypoints: int, step: float = DEFAULT_STEP
) -> torch.Tensor:
    """K waypoints ``[..., K, 2]`` for robots at ``pos`` ``[..., 2]`` on ``routes``
    ``[..., R, 2]`` (``R >= 1``; the last point is the slot).

    Where the robot is on its route is the point of the route nearest to it (the later segment
    on a tie, so a robot on a corner counts as past it). Its waypoints then run from its
    position to the next route point and on along the route, ``step`` metres apart, and stop at
    the slot: a robot within ``step`` of its slot gets K copies of it.
    """
    step = check_step(step)
    if routes.shape[-2] == 1:
        return routes.expand(*routes.shape[:-2], n_waypoints, 2).clone()
    a, b = routes[..., :-1, :], routes[..., 1:, :]  # the route's segments [..., R-1, 2]
    ab, ap = b - a, pos.unsqueeze(-2) - a
    t = ((ap * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
    gap = (ap - t.unsqueeze(-1) * ab).norm(dim=-1)  # [..., R-1]
    n_seg = gap.shape[-1]
    # argmin of the reversed distances: the later segment wins a tie.
    segment = n_seg - 1 - gap.flip(-1).argmin(-1, keepdim=True)  # [..., 1]
    # What is left: the robot, then the route's points after its segment (the slot repeated).
    after = (segment + torch.arange(1, n_seg + 1, device=pos.device)).clamp_max(n_seg)
    rest = routes.gather(-2, after.unsqueeze(-1).expand(*after.shape, 2))
    path = torch.cat([pos.unsqueeze(-2), rest], dim=-2)  # [..., R, 2]
    length = (path[..., 1:, :] - path[..., :-1, :]).norm(dim=-1)  # [..., R-1]
    reach = length.cumsum(-1)
    wanted = step * torch.arange(1, n_waypoints + 1, device=pos.device, dtype=pos.dtype)
    wanted = wanted.expand(*reach.shape[:-1], n_waypoints).contiguous()
    i = torch.searchsorted(reach.contiguous(), wanted).clamp_max(n_seg - 1)  # [..., K]
    before = torch.where(i > 0, reach.gather(-1, (i - 1).clamp_min(0)), torch.zeros_like(wanted))
    frac = ((wanted - before) / length.gather(-1, i).clamp_min(1e-12)).clamp(0.0, 1.0)
    start = path.gather(-2, i.unsqueeze(-1).expand(*i.shape, 2))
    end = path.gather(-2, (i + 1).unsqueeze(-1).expand(*i.shape, 2))
    points = start + frac.unsqueeze(-1) * (end - start)
    beyond = (wanted >= reach[..., -1:]).unsqueeze(-1)  # past the route's end: the slot
    return torch.where(beyond, path[..., -1:, :], points)
