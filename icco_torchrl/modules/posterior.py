"""Variational posterior q_xi(z_t | zeta_t, s_t, v_t) of the consistency (CE) term.

It factorises over the segment that follows a broadcast (ICCO, Sec. IV):
``q ∝ q^(t)(z | s_t, a_t, v_t) · Π_k q^(k)(z | o_k, a_k, v_k)``. Every factor is a diagonal
Gaussian per robot. ``combine="product"`` multiplies them (precision-weighted Gaussian, the
exact reading of the formula); ``combine="sum"`` adds the factors' log-likelihoods (COPA's
code). Both are tested against hand computations.

``inputs="flat"`` reads the flat state, the joint one-hot action and a robot one-hot at the
broadcast step, and the flat observation after: one team size. ``inputs="tokens"`` reads any
team up to ``n_agents`` with weights that do not depend on it: robot i's broadcast-step factor
is an entity attention over the state seen from robot i (:mod:`~icco_torchrl.modules.relative`),
each robot token carrying that robot's one-hot action, queried by robot i's own features and
action (absent robots, all-zero tokens, left out); the later factors attend over the visible
entity tokens of robot i's observation, queried by its own features and action.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import nn

from icco_torchrl.modules.activations import ReLU
from icco_torchrl.modules.coordinator import LOGVAR_MAX, LOGVAR_MIN
from icco_torchrl.modules.encoders import EntityAttentionEncoder
from icco_torchrl.modules.relative import relative_dims, relative_present, relative_tokens

if TYPE_CHECKING:
    from icco_torchrl.envs.layout import ObsLayout

_LOG_2PI = math.log(2 * math.pi)
POSTERIOR_INPUTS = ("flat", "tokens")
# How the factors combine (``combine``; ``method.posterior`` chooses).
COMBINES = ("product", "sum")


def _gaussian_head(in_dim: int, hidden: int, z_dim: int) -> nn.Module:
    return nn.Sequential(
        nn.Linear(in_dim, hidden),
        ReLU(),
        nn.Linear(hidden, hidden),
        ReLU(),
        nn.Linear(hidden, 2 * z_dim),
    )


def _split(out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    loc, logvar = out.chunk(2, -1)
    return loc, (0.5 * logvar.clamp(LOGVAR_MIN, LOGVAR_MAX)).exp()


def diag_normal_log_prob(x, loc, scale):
    """log N(x; loc, diag scale^2), summed over the last dim."""
    return _normal_log_density(x, loc, scale).sum(-1)


def _normal_log_density(x, loc, scale):
    """Each dimension's log N(x; loc, scale^2)."""
    return -0.5 * ((x - loc) / scale) ** 2 - scale.log() - 0.5 * _LOG_2PI


def combine_log_prob(z, loc, scale, mask, combine: str):
    """log q(z) from factors ``loc/scale [S, K, N, Z]`` with ``mask [S, K]``; z ``[S, N, Z]`` ->
    ``[S, N]``.

    Every row must have at least one valid factor (the first, the broadcast step, always is).
    """
    m = mask.to(loc.dtype)[..., None, None]  # [S, K, 1, 1]
    if combine == "product":
        precision = (m / scale**2).sum(1)
        mean = (m * loc / scale**2).sum(1) / precision
        return diag_normal_log_prob(z, mean, precision.rsqrt())
    if combine == "sum":
        return (
            mask.to(loc.dtype)[..., None] * diag_normal_log_prob(z.unsqueeze(1), loc, scale)
        ).sum(1)
    raise ValueError(f"combine must be 'product' or 'sum', got {combine!r}")


def log_prob_terms(z, loc, scale, mask, combine: str):
    """The terms that add up to :func:`combine_log_prob` (over dims 1 and -1), each one
    log-density COPA's clamp bounds: ``[S, 1, N, Z]``, each dimension of the combined Gaussian
    (``"product"``), or ``[S, K, N, Z]``, each step's and dimension's factor (``"sum"``; masked
    steps 0)."""
    m = mask.to(loc.dtype)[..., None, None]  # [S, K, 1, 1]
    if combine == "product":
        precision = (m / scale**2).sum(1)
        mean = (m * loc / scale**2).sum(1) / precision
        return _normal_log_density(z, mean, precision.rsqrt()).unsqueeze(1)
    if combine == "sum":
        return m * _normal_log_density(z.unsqueeze(1), loc, scale)
    raise ValueError(f"combine must be 'product' or 'sum', got {combine!r}")


class Posterior(nn.Module):
    """Factors: global ``(state, joint action, robot id)`` at the broadcast step, local ``(o, a)``
    after.

    Sizes: ``n_actions`` (the env's action count), ``z_dim`` and ``hidden``, required keyword
    arguments declared once by the caller (the project's values:
    :class:`~icco_torchrl.training.config.MethodConfig`), and a ``layout``, or ``n_agents``,
    ``obs_dim`` and ``state_dim`` (flat observation and state of any env). ``inputs="tokens"`` (any
    team, see the module doc) needs the layout.
    """

    def __init__(
        self,
        layout: ObsLayout | None = None,
        *,
        n_actions: int,
        z_dim: int,
        hidden: int,
        combine: str,
        n_agents: int | None = None,
        obs_dim: int | None = None,
        state_dim: int | None = None,
        inputs: str = "flat",
    ):
        super().__init__()
        if combine not in COMBINES:
            raise ValueError(f"combine must be one of {COMBINES}, got {combine!r}")
        if inputs not in POSTERIOR_INPUTS:
            raise ValueError(f"posterior inputs must be one of {POSTERIOR_INPUTS}, got {inputs!r}")
        if inputs == "tokens" and layout is None:
            raise ValueError(
                "posterior inputs='tokens' reads state and entity tokens: it needs a layout"
            )
        self.layout, self.inputs = layout, inputs
        if layout is not None:
            n_agents, obs_dim, state_dim = layout.n_agents, layout.obs_dim, layout.state_dim
        elif None in (n_agents, obs_dim, state_dim):
            raise ValueError("Posterior needs a layout, or n_agents, obs_dim and state_dim")
        self.n_agents, self.n_actions, self.combine = n_agents, n_actions, combine
        if inputs == "tokens":
            own_dim, n_entities, entity_dim = relative_dims(layout)
            A = n_actions
            self.first_encoder = EntityAttentionEncoder(
                own_dim + A, n_entities, entity_dim + A, hidden, relative_present(layout) + A
            )
            self.later_encoder = EntityAttentionEncoder(
                layout.own_dim + A,
                layout.n_entities,
                layout.entity_dim,
                hidden,
                layout.visible_column,
            )
            self.first = _gaussian_head(hidden, hidden, z_dim)
            self.later = _gaussian_head(hidden, hidden, z_dim)
            return
        self.first = _gaussian_head(state_dim + n_agents * (n_actions + 1), hidden, z_dim)
        self.later = _gaussian_head(obs_dim + n_actions, hidden, z_dim)

    def factors(self, state, action, obs):
        """Segment ``state [S, T, D]``, ``action [S, T, N]``, ``obs [S, T, N, F]`` -> loc, scale
        ``[S, T, N, Z]``.

        Factor 0 reads the global state and joint action of the broadcast step; factor k >= 1
        reads robot i's own observation and action at step k.
        """
        S, T, N = action.shape
        onehot = nn.functional.one_hot(action.long(), self.n_actions).to(
            state.dtype
        )  # [S, T, N, A]
        if self.inputs == "tokens":
            return self._token_factors(state, onehot, obs)
        eye = torch.eye(N, device=state.device, dtype=state.dtype).expand(S, N, N)
        joint = onehot[:, 0].reshape(S, 1, -1).expand(S, N, -1)
        first = self.first(
            torch.cat([state[:, 0].unsqueeze(1).expand(S, N, -1), joint, eye], -1)
        ).unsqueeze(1)
        later = self.later(torch.cat([obs[:, 1:], onehot[:, 1:]], -1))
        return _split(torch.cat([first, later], 1))

    def _token_factors(self, state, onehot, obs):
        """:meth:`factors` of ``inputs="tokens"``: ``onehot [S, T, N, A]``."""
        L, A = self.layout, self.n_actions
        S, T, N = onehot.shape[:3]
        own_dim, E, entity_dim = relative_dims(L)
        rel = relative_tokens(state[:, 0], L)  # [S, N, own_dim + E * entity_dim]
        own, ents = rel[..., :own_dim], rel[..., own_dim:].unflatten(-1, (E, entity_dim))
        # every robot token carries its robot's action (before its present flag, the mask), the
        # other entities none
        acted = torch.cat([onehot[:, 0], onehot.new_zeros(S, E - N, A)], 1)  # [S, E, A]
        acted = acted.unsqueeze(1).expand(S, N, E, A)
        P = relative_present(L)
        ents = torch.cat([ents[..., :P], acted, ents[..., P:]], -1)
        first = self.first_encoder(torch.cat([own, onehot[:, 0], ents.flatten(-2)], -1))
        later_obs = obs[:, 1:]
        later = self.later_encoder(
            torch.cat([later_obs[..., : L.own_dim], onehot[:, 1:], later_obs[..., L.own_dim :]], -1)
        )
        return _split(torch.cat([self.first(first).unsqueeze(1), self.later(later)], 1))

    def forward(self, z, state, action, obs, mask):
        """log q(z | segment) ``[S, N]``; z ``[S, N, Z]`` (or ``[S, T, N, Z]``: its first step is
        scored).

        ``mask [S, T]`` marks the steps that belong to z's hold period (the broadcast step first).
        """
        if z.dim() == 4:
            z = z[:, 0]
        loc, scale = self.factors(state, action, obs)
        return combine_log_prob(z, loc, scale, mask, self.combine)

    def log_prob_terms(self, z, state, action, obs, mask):
        """:meth:`forward`'s log q as the terms that add up to it (:func:`log_prob_terms`):
        ``[S, 1, N, Z]`` (product) or ``[S, T, N, Z]`` (sum), what ``ce_clamp`` clamps."""
        if z.dim() == 4:
            z = z[:, 0]
        loc, scale = self.factors(state, action, obs)
        return log_prob_terms(z, loc, scale, mask, self.combine)


def make_posterior(layout: ObsLayout | None = None, **kwargs) -> Posterior:
    """The posterior for :class:`~icco_torchrl.objectives.ICCOLoss`: ``kwargs`` are
    :class:`Posterior`'s (``n_actions``, ``z_dim`` and ``hidden`` required).

    A plain module, not a TensorDictModule: it scores whole segments (z of the broadcast step,
    the segment's states, actions, observations and hold mask), which the loss reads through its
    own keys (``set_keys``) and passes to it; it writes nothing into a tensordict.
    """
    return Posterior(layout, **kwargs)
