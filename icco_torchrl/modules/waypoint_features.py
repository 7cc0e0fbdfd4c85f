"""The two quantities the instruction reward is made of, read off a robot's own relative waypoints.

``r_inst = scale * (e_cossim + dist_coef * e_dist)``
(:func:`icco_torchrl.envs._kernels.instruction_reward`) scores this step's displacement against the
direction from the waypoint nearest to the robot to the second-nearest one, and the distance to the
nearest. Both are in the observation already (the K waypoints relative to the robot), but only
through an argmin and a difference that a small network has to discover under the noise of the task
rewards. :func:`path_features` hands them over directly: the nearest waypoint (relative, 2 numbers)
and the unit path direction (2). It is a fixed function of the observation (no new information),
switched on by ``method.waypoint_features`` (experiments/recipe/README.md measures what it buys).
"""

from __future__ import annotations

import torch

PATH_FEATURES = (
    4  # nearest waypoint (x, y) relative to the robot, unit direction nearest -> second-nearest
)


def path_features(rel_wp: torch.Tensor) -> torch.Tensor:
    """``[..., K, 2]`` waypoints relative to the robot -> ``[..., 4]``: nearest waypoint, unit path
    direction.

    Ties go to the lower waypoint index, as in the env's reward; a zero path gives a zero direction.
    """
    if rel_wp.shape[-2] < 2 or rel_wp.shape[-1] != 2:
        raise ValueError(
            f"path_features needs [..., K>=2, 2] relative waypoints, got {tuple(rel_wp.shape)}"
        )
    d = rel_wp.square().sum(-1)  # [..., K]
    nearest = d.argmin(-1, keepdim=True)  # [..., 1]
    second = d.scatter(-1, nearest, float("inf")).argmin(-1, keepdim=True)
    take = lambda i: rel_wp.gather(-2, i.unsqueeze(-1).expand(*i.shape, 2)).squeeze(-2)  # noqa: E731
    near = take(nearest)
    path = take(second) - near
    unit = path / path.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    return torch.cat([near, unit], -1)
