"""The global state seen from each robot: entity tokens relative to it, read by entity attention.

The env's global state lists every robot, resource and invader with *absolute* coordinates. A
network that must answer "where is the resource nearest to robot i" from absolute coordinates
has to learn a subtraction and a norm before anything else; single-head attention cannot even
express "nearest" (its logits are linear in the token). Here each robot gets the same entities
as tokens ``[dx, dy, distance, vx, vy, type (robot, resource, invader, home), flag, defended,
waypoints relative to robot i (robots only, 2K), present]`` (present: :func:`relative_present`),
plus home as an entity, and its own
features ``[x, y, vx, vy, carry, defended, own waypoints relative to itself (2K)]``. The
distance feature lets the attention logit prefer near entities. Same information as the flat
state, a representation the networks learn from quickly (measured in
``experiments/four_quadrants/README.md``).

Any team up to ``n_agents``: an absent robot's state token is all zeros, its type flags included,
so :meth:`~icco_torchrl.envs.layout.ObsLayout.robot_mask` reads who is present off the state
itself, and an untyped token (an absent robot) is left out of every attention, as an inactive
invader is. A team padded with absent robots gives its present robots the features of the same
team unpadded. Every column is read by its name in :class:`~icco_torchrl.envs.layout.ObsLayout`.

Used by the coordinator (``method.state_encoder=relative``) and by QMIX (FULL)'s agents, so the
full-information baseline reads the state through the same encoder as ICCO's coordinator.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

from icco_torchrl.modules.encoders import EntityAttentionEncoder

if TYPE_CHECKING:
    from icco_torchrl.envs.layout import ObsLayout

STATE_ENCODERS = ("relative", "flat")


def relative_dims(layout: ObsLayout) -> tuple[int, int, int]:
    """``(own_dim, n_entities, entity_dim)`` of :func:`relative_tokens`."""
    K2 = 2 * layout.n_waypoints
    return 6 + K2, layout.state_tokens + 1, 12 + K2


def relative_present(layout: ObsLayout) -> int:
    """The column of a relative token's present flag (the robot attends to the entity): after its
    waypoints, the token's last."""
    return relative_dims(layout)[2] - 1


def relative_tokens(state: torch.Tensor, layout: ObsLayout) -> torch.Tensor:
    """``[..., state_dim]`` -> per robot ``[..., N, own_dim + n_entities * entity_dim]``."""
    N, T, D = layout.n_agents, layout.state_tokens, layout.state_token_dim
    POS, VEL, TYPE, WP = layout.POSITION, layout.VELOCITY, layout.TYPE, layout.waypoints
    FLAG_DEFENDED = slice(layout.FLAG, layout.DEFENDED + 1)  # adjacent columns: flag, defended
    tok = layout.tokens(state)  # [..., T, D]
    me = tok[..., :N, :]  # [..., N, D]
    my_pos = me[..., POS]
    lead = tok.shape[:-2]
    # Entities: the T state tokens then home (the origin), each seen from every robot.
    home = torch.zeros(*lead, 1, D, dtype=state.dtype, device=state.device)
    ents = torch.cat([tok, home], -2)  # [..., T+1, D]
    rel = ents[..., None, :, POS] - my_pos[..., :, None, :]  # [..., N, T+1, 2]
    dist = rel.norm(dim=-1, keepdim=True)
    kind = torch.cat([ents[..., TYPE], torch.zeros_like(ents[..., :1])], -1)  # [..., T+1, 4]
    kind[..., -1, 3] = 1.0  # home
    # present: inactive invaders (flag 0), absent robots (an untyped, all-zero token) and the
    # robot itself are left out of the attention
    is_invader = ents[..., layout.INVADER : layout.INVADER + 1] > 0
    typed = (kind != 0).any(-1, keepdim=True).to(kind.dtype)  # 0: no type (an absent robot)
    present = torch.where(is_invader, ents[..., layout.FLAG : layout.FLAG + 1], typed)
    present = present.unsqueeze(-3).expand(*lead, N, T + 1, 1).clone()  # [..., N, T+1, 1]
    present[..., torch.arange(N), torch.arange(N), 0] = 0.0
    wp = ents[..., WP].unflatten(-1, (-1, 2))  # [..., T+1, K, 2]
    is_robot = (ents[..., layout.ROBOT : layout.ROBOT + 1] > 0).unsqueeze(-1)
    wp_rel = torch.where(
        is_robot.unsqueeze(-4), wp.unsqueeze(-4) - my_pos[..., :, None, None, :], 0.0
    )
    shared = torch.cat([ents[..., VEL], kind, ents[..., FLAG_DEFENDED]], -1)
    tokens = torch.cat(
        [
            rel,
            dist,
            shared.unsqueeze(-3).expand(*lead, N, T + 1, shared.shape[-1]),
            wp_rel.flatten(-2),
            present,
        ],
        -1,
    )  # present at relative_present(layout)
    own_wp = me[..., WP].unflatten(-1, (-1, 2)) - my_pos.unsqueeze(-2)
    own = torch.cat([me[..., POS], me[..., VEL], me[..., FLAG_DEFENDED], own_wp.flatten(-2)], -1)
    return torch.cat([own, tokens.flatten(-2)], -1)  # own: [..., N, own_dim]


class RelativeStateEncoder(nn.Module):
    """Per-robot features ``[..., N, hidden]`` from the flat global state (see the module doc)."""

    def __init__(self, layout: ObsLayout, hidden: int, extra_own: int = 0):
        super().__init__()
        self.layout = layout
        own_dim, n_entities, entity_dim = relative_dims(layout)
        self.net = EntityAttentionEncoder(
            own_dim + extra_own, n_entities, entity_dim, hidden, relative_present(layout)
        )
        self.own_dim = own_dim

    def forward(self, state: torch.Tensor, extra_own: torch.Tensor | None = None) -> torch.Tensor:
        x = relative_tokens(state, self.layout)
        if extra_own is not None:  # more own features (an agent's observation) before the tokens
            x = torch.cat([x[..., : self.own_dim], extra_own, x[..., self.own_dim :]], -1)
        return self.net(x)
