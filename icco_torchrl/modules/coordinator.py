"""Coordinator g_phi(s_t, v_t) -> N(mu, sigma) per robot: the TACI z broadcast to the agents.

It reads the global state (which carries every robot's waypoints) as tokens, lets each
robot token attend over all tokens, and emits a diagonal Gaussian per robot (log-variance
clamped to [-10, 0] as in COPA). During rollouts z is redrawn every ``period`` steps (when
``step_count % period == 0``) and held in between; the noise is kept in the TensorDict so the
loss can rebuild the very z the agents acted on, with gradient (reparameterisation).

Its sizes (``z_dim``, ``hidden``) and ``period`` are required keyword arguments, declared once by
the caller (the project's values: :class:`~icco_torchrl.training.config.MethodConfig`);
:func:`make_coordinator` forwards its keyword arguments to :class:`Coordinator`, so they are
listed once, there (see :mod:`icco_torchrl.modules`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, exploration_type

from icco_torchrl.modules.activations import ReLU
from icco_torchrl.modules.encoders import EntityAttentionEncoder
from icco_torchrl.modules.relative import STATE_ENCODERS, RelativeStateEncoder
from icco_torchrl.modules.tdmodule import TensorModule

if TYPE_CHECKING:
    from icco_torchrl.envs.layout import ObsLayout

LOGVAR_MIN, LOGVAR_MAX = -10.0, 0.0


class StateTokenEncoder(nn.Module):
    """Per-robot features ``[..., N, hidden]`` from the flat global state.

    ``attention``: each robot's state token queries all state tokens (single-head entity
    attention, as in the agents' encoder; needs a layout), absent robots' (all-zero, untyped)
    tokens left out, so it reads any team up to ``n_agents``. ``mlp``: the flat state through an
    MLP to N outputs (a layout, or ``n_agents`` and ``state_dim`` for any env; one team size).
    """

    def __init__(
        self,
        layout: ObsLayout | None,
        hidden: int,
        kind: str = "attention",
        *,
        n_agents: int | None = None,
        state_dim: int | None = None,
    ):
        super().__init__()
        if layout is None and (kind != "mlp" or n_agents is None or state_dim is None):
            raise ValueError(
                "a state without a layout is read by encoder='mlp' and needs n_agents and state_dim"
            )
        self.kind, self.hidden = kind, hidden
        self.n_agents = layout.n_agents if layout is not None else n_agents
        self.layout = layout
        if kind == "attention":
            self.n_tokens, self.token_dim = layout.state_tokens, layout.state_token_dim
            self.net = EntityAttentionEncoder(self.token_dim, self.n_tokens, self.token_dim, hidden)
        elif kind == "mlp":
            width = layout.state_dim if layout is not None else state_dim
            self.net = nn.Sequential(
                nn.Linear(width, hidden),
                ReLU(),
                nn.Linear(hidden, self.n_agents * hidden),
                ReLU(),
            )
        else:
            raise ValueError(f"encoder must be 'attention' or 'mlp', got {kind!r}")

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        if self.kind == "mlp":
            return self.net(state).unflatten(-1, (self.n_agents, self.hidden))
        robots = state[..., : self.n_agents * self.token_dim].unflatten(
            -1, (self.n_agents, self.token_dim)
        )
        every = state.unsqueeze(-2).expand(*state.shape[:-1], self.n_agents, state.shape[-1])
        # a token of no type (an absent robot's, all zeros) is attended by no one
        typed = self.layout.typed(state)  # [..., T]
        return self.net(torch.cat([robots, every], -1), typed.unsqueeze(-2))


class Coordinator(nn.Module):
    """Gaussian TACI per robot; ``forward`` is the rollout step (sample/hold), ``distribution`` the
    net.

    Args:
        layout: the resource-collection state (any encoder), or None for a flat global state of
            ``state_dim`` features (``encoder="mlp"``, ``state_encoder="flat"``).

    Keyword Args:
        z_dim: width of z per robot (required).
        hidden: width of the state encoder (required).
        period: z is redrawn every ``period`` steps and held in between (required, >= 1).
        encoder: ``"attention"`` (needs a layout; the default with one) or ``"mlp"`` (the default
            without).
        state_encoder: ``"flat"`` (absolute state tokens) or ``"relative"`` (entities seen from
            each robot; needs a layout).
        init_logvar: initial bias of z's log-variance (0: std ~1; required, a method's choice).
        n_agents, state_dim: the team size and state width without a layout.
        threshold: adaptive broadcast (COPA's beta); 0 sends every ``period`` steps.

    Any team up to ``n_agents`` with ``state_encoder="relative"`` or ``encoder="attention"``:
    absent robots (all-zero state tokens) are left out of every robot's attention, so a present
    robot's z is the one it has in the same team unpadded, and the weights do not depend on
    ``n_agents`` (a state dict loads into a coordinator of another team size).
    """

    def __init__(
        self,
        layout: ObsLayout | None = None,
        *,
        z_dim: int,
        hidden: int,
        period: int,
        encoder: str | None = None,
        state_encoder: str = "flat",
        init_logvar: float,
        n_agents: int | None = None,
        state_dim: int | None = None,
        threshold: float = 0.0,
    ):
        super().__init__()
        if period < 1:
            raise ValueError(f"period must be >= 1, got {period}")
        if not threshold >= 0:
            raise ValueError(f"broadcast threshold must be >= 0, got {threshold}")
        if state_encoder not in STATE_ENCODERS:
            raise ValueError(
                f"state_encoder must be one of {STATE_ENCODERS}, got {state_encoder!r}"
            )
        if layout is None and state_encoder == "relative":
            raise ValueError(
                "state_encoder='relative' reads the resource-collection state: it needs a layout"
            )
        self.z_dim, self.period, self.threshold = z_dim, period, float(threshold)
        self.layout = layout
        encoder = encoder or ("attention" if layout is not None else "mlp")
        # relative: entities seen from each robot (modules/relative.py); flat: absolute state tokens
        self.encoder = (
            RelativeStateEncoder(layout, hidden)
            if state_encoder == "relative"
            else StateTokenEncoder(layout, hidden, encoder, n_agents=n_agents, state_dim=state_dim)
        )
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
        """Redraw z where ``step_count % period == 0`` (mean when exploration is deterministic);
        returns ``(z, noise, sent)``.

        With ``threshold`` (COPA's adaptive broadcast, beta) robot i receives the new draw only
        where it moved more than ``threshold`` (L2) from the z it holds, or at an episode's first
        step; otherwise it keeps its z (and the noise behind it). ``sent [B, N, 1]`` marks the
        robots that received a z this step. ``step_count [B, 1]`` (TorchRL's ``StepCounter``);
        ``state [B, ...]``, trailing dims flattened.
        """
        if step_count is None:
            raise KeyError(
                "the coordinator needs 'step_count' (add TorchRL's StepCounter transform to the "
                "env)"
            )
        if state.dim() > step_count.dim():
            state = state.flatten(step_count.dim() - 1)
        fresh = (step_count % self.period == 0).unsqueeze(-1)  # [B, 1, 1]
        if state.device.type == "cpu" and not torch.compiler.is_compiling() and not fresh.any():
            # every env holds its z: skip the network (on GPU this test would sync)
            return z_prev, noise_prev, torch.zeros_like(z_prev[..., :1], dtype=torch.bool)
        loc, scale = self.distribution(state)
        if exploration_type() in (ExplorationType.RANDOM, None):
            noise = torch.randn_like(loc)
        else:
            noise = torch.zeros_like(loc)
        draw = loc + scale * noise
        send = fresh.expand(*draw.shape[:-1], 1)
        if self.threshold > 0:
            moved = (draw - z_prev).norm(dim=-1, keepdim=True) > self.threshold
            send = send & (moved | (step_count == 0).unsqueeze(-1))
        return torch.where(send, draw, z_prev), torch.where(send, noise, noise_prev), send


def gaussian_entropy(scale: torch.Tensor) -> torch.Tensor:
    """Closed-form entropy of a diagonal Gaussian, summed over the last dim."""
    return (0.5 * math.log(2 * math.pi * math.e) + scale.log()).sum(-1)


def make_coordinator(
    layout: ObsLayout | None = None,
    *,
    state_key="state",
    group="agents",
    step_count_key="step_count",
    **kwargs,
) -> TensorDictModule:
    """The coordinator as a TensorDictModule for rollouts: ``kwargs`` are :class:`Coordinator`'s
    (``z_dim``, ``hidden`` and ``period`` required), the rest its keys.

    in:  ``state_key`` (any trailing shape, flattened), ``step_count_key`` (TorchRL's
         ``StepCounter``), ``(group, "z")`` and ``(group, "z_noise")`` (held values)
    out: ``(group, "z")``, ``(group, "z_noise")``, ``(group, "z_sent")`` (the robots that
         received a new z this step; the distribution itself: ``module.distribution(state)``)
    """
    return TensorModule(
        Coordinator(layout, **kwargs),
        in_keys={
            "state": state_key,
            "step_count": step_count_key,
            "z_prev": (group, "z"),
            "noise_prev": (group, "z_noise"),
        },
        out_keys=[(group, "z"), (group, "z_noise"), (group, "z_sent")],
    )
