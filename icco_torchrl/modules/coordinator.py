"""Coordinator g_phi(s_t, v_t) -> N(mu, sigma) per robot: the TACI z broadcast to the agents.

It reads the global state (which carries every robot's waypoints) as tokens, lets each
robot token attend over all tokens, and emits a diagonal Gaussian per robot (log-variance
clamped to [-10, 0] as in COPA). During rollouts z is redrawn every ``period`` steps (when
``step_count % period == 0``) and held in between; the noise is kept in the TensorDict so the
loss can rebuild the very z the agents acted on, with gradient (reparameterisation).
"""
from __future__ import annotations

import math

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, exploration_type

from icco_torchrl.envs.resource_collection import ObsLayout
from icco_torchrl.modules.encoders import EntityAttentionEncoder
from icco_torchrl.modules.relative import STATE_ENCODERS, RelativeStateEncoder
from icco_torchrl.modules.tdmodule import TensorModule

LOGVAR_MIN, LOGVAR_MAX = -10.0, 0.0


class StateTokenEncoder(nn.Module):
    """Per-robot features ``[..., N, hidden]`` from the flat global state.

    ``attention``: each robot's state token queries all state tokens (single-head entity
    attention, as in the agents' encoder). ``mlp``: the flat state through an MLP to N outputs.
    """

    def __init__(self, layout: ObsLayout, hidden: int, kind: str = "attention"):
        super().__init__()
        self.kind, self.n_agents, self.hidden = kind, layout.n_agents, hidden
        self.n_tokens, self.token_dim = layout.state_tokens, layout.state_token_dim
        if kind == "attention":
            self.net = EntityAttentionEncoder(self.token_dim, self.n_tokens, self.token_dim, hidden, masked=False)
        elif kind == "mlp":
            self.net = nn.Sequential(nn.Linear(layout.state_dim, hidden), nn.ReLU(),
                                     nn.Linear(hidden, self.n_agents * hidden), nn.ReLU())
        else:
            raise ValueError(f"encoder must be 'attention' or 'mlp', got {kind!r}")

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        if self.kind == "mlp":
            return self.net(state).unflatten(-1, (self.n_agents, self.hidden))
        robots = state[..., : self.n_agents * self.token_dim].unflatten(-1, (self.n_agents, self.token_dim))
        every = state.unsqueeze(-2).expand(*state.shape[:-1], self.n_agents, state.shape[-1])
        return self.net(torch.cat([robots, every], -1))


class Coordinator(nn.Module):
    """Gaussian TACI per robot; ``forward`` is the rollout step (sample/hold), ``distribution`` the net."""

    def __init__(self, layout: ObsLayout, *, z_dim: int = 32, hidden: int = 64, period: int = 4,
                 encoder: str = "attention", state_encoder: str = "flat", init_logvar: float = 0.0):
        super().__init__()
        if period < 1:
            raise ValueError(f"period must be >= 1, got {period}")
        if state_encoder not in STATE_ENCODERS:
            raise ValueError(f"state_encoder must be one of {STATE_ENCODERS}, got {state_encoder!r}")
        self.z_dim, self.period = z_dim, period
        # relative: entities seen from each robot (modules/relative.py); flat: absolute state tokens
        self.encoder = (RelativeStateEncoder(layout, hidden) if state_encoder == "relative"
                        else StateTokenEncoder(layout, hidden, encoder))
        self.loc = nn.Linear(hidden, z_dim)
        self.logvar = nn.Linear(hidden, z_dim)
        # The initial noise level of z: at 0 (std ~1) z starts as mostly noise and the agents learn
        # to ignore it; a lower start lets the TD loss use z from the first updates.
        nn.init.constant_(self.logvar.bias, init_logvar)

    def distribution(self, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(loc, scale)``, each ``[..., N, z_dim]``."""
        h = self.encoder(state)
        logvar = self.logvar(h).clamp(LOGVAR_MIN, LOGVAR_MAX)
        return self.loc(h), (0.5 * logvar).exp()

    def forward(self, state, step_count, z_prev, noise_prev):
        """Redraw z where ``step_count % period == 0`` (mean when exploration is deterministic)."""
        fresh = (step_count % self.period == 0).unsqueeze(-1)                     # [B, 1, 1]
        if state.device.type == "cpu" and not torch.compiler.is_compiling() and not fresh.any():
            return z_prev, noise_prev  # every env holds its z: skip the network (on GPU this test would sync)
        loc, scale = self.distribution(state)
        if exploration_type() in (ExplorationType.RANDOM, None):
            noise = torch.randn_like(loc)
        else:
            noise = torch.zeros_like(loc)
        noise = torch.where(fresh, noise, noise_prev)
        z = torch.where(fresh, loc + scale * noise, z_prev)
        return z, noise


def gaussian_entropy(scale: torch.Tensor) -> torch.Tensor:
    """Closed-form entropy of a diagonal Gaussian, summed over the last dim."""
    return (0.5 * math.log(2 * math.pi * math.e) + scale.log()).sum(-1)


def make_coordinator(layout: ObsLayout, *, z_dim: int = 32, hidden: int = 64, period: int = 4,
                     encoder: str = "attention", state_encoder: str = "flat", init_logvar: float = 0.0,
                     state_key="state", group="agents") -> TensorDictModule:
    """The coordinator as a TensorDictModule for rollouts.

    in:  ``state_key``, ``"step_count"``, ``(group, "z")`` and ``(group, "z_noise")`` (held values)
    out: ``(group, "z")``, ``(group, "z_noise")`` (the distribution itself: ``module.distribution(state)``)
    """
    net = Coordinator(layout, z_dim=z_dim, hidden=hidden, period=period, encoder=encoder,
                      state_encoder=state_encoder, init_logvar=init_logvar)
    return TensorModule(
        net, in_keys={"state": state_key, "step_count": "step_count", "z_prev": (group, "z"),
                      "noise_prev": (group, "z_noise")},
        out_keys=[(group, "z"), (group, "z_noise")])
