"""Local agent: a recurrent Q-network shared by all robots (parameter sharing).

Input per robot: its observation (own state, own waypoints, visible entities), optionally
the global state (QMIX (FULL)), its previous action and its TACI ``z^i``. Core: encoder ->
GRU -> Q head on ``[GRU output; z]`` (COPA's player). The same GRU
(:class:`~icco_torchrl.modules.gru.GRU`: ``nn.GRU``'s parameters in a form ``torch.compile``
traces) runs one step at collection time and a whole segment in one call at training time.

Sizes come from the caller: ``n_actions`` (the env's specs) and ``hidden`` always, required
keyword arguments declared once by the caller (the project's values:
:class:`~icco_torchrl.training.config.MethodConfig`), and either an
:class:`~icco_torchrl.envs.layout.ObsLayout` (a structured observation read by entity attention)
or ``obs_dim`` (any flat per-agent observation, read by an MLP). :func:`make_agent` forwards its
keyword arguments to :class:`RecurrentQNet`, so they are listed once, there.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import recurrent_mode

from icco_torchrl.modules.activations import ReLU, relu
from icco_torchrl.modules.encoders import MLPEncoder, make_encoder
from icco_torchrl.modules.gru import GRU
from icco_torchrl.modules.relative import STATE_ENCODERS, RelativeStateEncoder
from icco_torchrl.modules.tdmodule import TensorModule
from icco_torchrl.modules.waypoint_features import PATH_FEATURES, path_features

if TYPE_CHECKING:
    from icco_torchrl.envs.layout import ObsLayout


def keep_hidden(
    hidden: torch.Tensor, is_init: torch.Tensor | None, step_count: torch.Tensor | None
) -> torch.Tensor:
    """``hidden [..., N, H]`` zeroed where an episode starts: TorchRL's ``is_init``
    (``InitTracker``, ``[..., 1]`` or per agent ``[..., N, 1]``), else ``step_count == 0``
    (``[..., 1]``)."""
    if is_init is not None:
        keep = ~is_init.bool()
    elif step_count is not None:
        keep = step_count != 0
    else:
        raise KeyError(
            "the agent needs 'is_init' (TorchRL's InitTracker) or 'step_count' (StepCounter) to "
            "know where episodes start"
        )
    if keep.dim() < hidden.dim():
        keep = keep.unsqueeze(-1)
    return hidden * keep.to(hidden.dtype)


def _check_agent_args(layout, *, n_actions, state_encoder: str, waypoint_features: bool) -> None:
    """:class:`RecurrentQNet`'s checks of its arguments that do not depend on the encoder."""
    if state_encoder not in STATE_ENCODERS:
        raise ValueError(f"state_encoder must be one of {STATE_ENCODERS}, got {state_encoder!r}")
    if not isinstance(n_actions, int) or n_actions < 1:
        raise ValueError(
            f"n_actions must be a positive integer (the env's action count), got {n_actions!r}"
        )
    if waypoint_features and layout is None:
        raise ValueError(
            "waypoint_features reads the own waypoints of a structured observation: it needs a "
            "layout"
        )


class RecurrentQNet(nn.Module):
    """Q-values ``[..., N, n_actions]`` from observations, previous actions, z and a GRU state.

    Args:
        layout: the structured observation (entity tokens) of the resource-collection env, or None
            for a flat observation of ``obs_dim`` features.

    Keyword Args:
        n_actions: size of the discrete action space (the env's action spec ``.space.n``;
            required).
        hidden: width of the encoder, the GRU and the Q head (required).
        obs_dim: per-agent observation width when ``layout`` is None.
        state_dim: global state width, for ``full_state`` without a layout.
        z_dim: width of the coordinator's z the Q head reads (0, the default: no coordinator).
        full_state: the agent also reads the global state (QMIX (FULL)).
        encoder: ``"attention"`` (needs a layout; the default with one) or ``"mlp"`` (the
            default without).
        state_encoder: with ``full_state``: ``"flat"`` (state joins the own features) or
            ``"relative"``.
        waypoint_features: append the nearest own waypoint and the unit direction to the next one
            (:func:`~icco_torchrl.modules.waypoint_features.path_features`) to the own features;
            needs a layout.
        layer_norm: a LayerNorm on the GRU's input (after the observation and previous-action
            embedding, before its ReLU) and on the Q head's hidden layer (RLPD, PQN).
    """

    def __init__(
        self,
        layout: ObsLayout | None = None,
        *,
        n_actions: int,
        hidden: int,
        obs_dim: int | None = None,
        state_dim: int | None = None,
        z_dim: int = 0,
        full_state: bool = False,
        encoder: str | None = None,
        state_encoder: str = "flat",
        waypoint_features: bool = False,
        layer_norm: bool = False,
    ):
        super().__init__()
        _check_agent_args(
            layout,
            n_actions=n_actions,
            state_encoder=state_encoder,
            waypoint_features=waypoint_features,
        )
        self.hidden, self.z_dim, self.full_state, self.n_actions = (
            hidden,
            z_dim,
            full_state,
            n_actions,
        )
        self.waypoint_features = waypoint_features
        # the robot's own waypoints in its observation (read by the waypoint features)
        self._own_waypoints = layout.own_waypoints if layout is not None else None
        self.relative = full_state and state_encoder == "relative"
        self._make_encoder(layout, encoder, obs_dim=obs_dim, state_dim=state_dim)
        self._make_embedding(hidden, n_actions)
        # LayerNorm before the GRU's input and the head's ReLU (RLPD's order: Linear, norm,
        # activation); never on the GRU state. Identity without layer_norm.
        self.layer_norm = layer_norm
        self.trunk_norm = nn.LayerNorm(hidden) if layer_norm else nn.Identity()
        self.gru = GRU(hidden, hidden)
        head_in = hidden + z_dim  # COPA's player: the Q head reads [GRU output; z]
        self.head = nn.Sequential(
            nn.Linear(head_in, hidden),
            *([nn.LayerNorm(hidden)] if layer_norm else []),
            ReLU(),
            nn.Linear(hidden, n_actions),
        )

    def _make_encoder(self, layout, encoder, *, obs_dim, state_dim) -> None:
        """The observation encoder (``self.encoder``) and the width of the own features."""
        hidden, full_state = self.hidden, self.full_state
        wf = PATH_FEATURES if self.waypoint_features else 0
        if layout is None:  # a flat observation (any env): [obs; state] through an MLP
            if obs_dim is None:
                raise ValueError(
                    "RecurrentQNet needs a layout (structured observation) or obs_dim (flat "
                    "observation)"
                )
            if (encoder or "mlp") != "mlp" or self.relative:
                raise ValueError(
                    "a flat observation (no layout) is read by encoder='mlp' with "
                    "state_encoder='flat'"
                )
            if full_state and state_dim is None:
                raise ValueError("full_state without a layout needs state_dim")
            self.encoder = MLPEncoder(obs_dim + (state_dim if full_state else 0), hidden)
            self._own_dim = obs_dim  # the state goes after the whole observation
        elif (
            self.relative
        ):  # QMIX (FULL): every entity relative to the robot (the coordinator's encoder)
            self.encoder = RelativeStateEncoder(layout, hidden, extra_own=wf)
            self._own_dim = layout.own_dim
        else:  # flat: the global state joins the own token of the local-observation encoder
            extra = layout.state_dim if full_state else 0
            self.encoder = make_encoder(
                encoder or "attention",
                own_dim=layout.own_dim + wf + extra,
                n_entities=layout.n_entities,
                entity_dim=layout.entity_dim,
                hidden=hidden,
                flag_column=layout.visible_column,
            )
            self._own_dim = layout.own_dim

    def _make_embedding(self, hidden: int, n_actions: int) -> None:
        """The input embedding of the features and the previous action (``embed``,
        ``prev_action_embed``), initialised as one ``nn.Linear`` over their concatenation."""
        # embed([features; one_hot(prev_action)]) written as a linear map plus a per-action row:
        # the same function without building the one-hot and the concatenation.
        self.embed = nn.Linear(hidden, hidden)
        self.prev_action_embed = nn.Embedding(n_actions, hidden)
        bound = 1.0 / (hidden + n_actions) ** 0.5  # nn.Linear's init for the concatenated input
        nn.init.uniform_(self.embed.weight, -bound, bound)
        nn.init.uniform_(self.embed.bias, -bound, bound)
        nn.init.uniform_(self.prev_action_embed.weight, -bound, bound)

    def _path(self, obs):
        # own features are [x, y, vx, vy, carry, K relative waypoints] (ObsLayout)
        return path_features(obs[..., self._own_waypoints].unflatten(-1, (-1, 2)))

    def _features(self, obs, prev_action, state, z=None):
        x = self._encode(obs, state)
        x = self.embed(x) + self.prev_action_embed(prev_action.long())
        return relu(self.trunk_norm(x))

    def _encode(self, obs, state):
        if self.relative:
            return self.encoder(state, self._path(obs) if self.waypoint_features else None)
        own = [obs[..., : self._own_dim]]
        if self.waypoint_features:
            own.append(self._path(obs))
        if self.full_state:
            own.append(state.unsqueeze(-2).expand(*obs.shape[:-1], state.shape[-1]))
        if len(own) > 1:
            obs = torch.cat([*own, obs[..., self._own_dim :]], -1)
        return self.encoder(obs)

    def _q(self, h, z):
        return self.head(torch.cat([h, z], -1) if self.z_dim else h)

    def forward(self, obs, prev_action, hidden, step_count=None, z=None, state=None, is_init=None):
        """One step for ``[B, N, ...]`` inputs; the hidden state restarts at zero where an episode
        starts (``is_init``, else ``step_count == 0``).

        Under TorchRL's ``set_recurrent_mode(True)`` the inputs are sequences ``[S, L, N, ...]``:
        one GRU call from the hidden state of the first step; returns Q ``[S, L, N, A]`` and the
        hidden state after every step ``[S, L, N, H]``.
        """
        if recurrent_mode():

            def first(v):
                return None if v is None else v[:, 0]

            h0 = keep_hidden(hidden[:, 0], first(is_init), first(step_count))
            q, h = self.sequence(obs, prev_action, h0, z=z, state=state, return_hidden="all")
        else:
            q, h = self.step(obs, prev_action, keep_hidden(hidden, is_init, step_count), z, state)
        return q, h

    def step(self, obs, prev_action, hidden, z=None, state=None):
        """One step from ``hidden`` as given (no restart): Q ``[B, N, A]`` and the new hidden."""
        x = self._features(obs, prev_action, state, z)
        h = self.gru.step(x.reshape(-1, self.hidden), hidden.reshape(-1, self.hidden))
        h = h.reshape(x.shape)
        return self._q(h, z), h

    def sequence(
        self,
        obs,
        prev_action,
        hidden0,
        z=None,
        state=None,
        return_hidden: bool | str = False,
    ):
        """A segment in one GRU call: inputs ``[S, L, N, ...]``, ``hidden0 [S, N, H]`` ->
        Q ``[S, L, N, A]``, and with
        ``return_hidden`` the hidden state after the last step ``[S, N, H]``, or with
        ``return_hidden="all"`` after every step ``[S, L, N, H]``."""
        x = self._features(obs, prev_action, state, z)
        S, L, N, H = x.shape
        out, h_last = self.gru(
            x.permute(0, 2, 1, 3).reshape(S * N, L, H), hidden0.reshape(S * N, H)
        )
        h = out.reshape(S, N, L, H).permute(0, 2, 1, 3)
        q = self._q(h, z)
        if return_hidden == "all":
            return q, h
        return (q, h_last.reshape(S, N, H)) if return_hidden else q


def make_agent(
    layout: ObsLayout | None = None,
    *,
    obs_key=("agents", "observation"),
    state_key="state",
    action_key=("agents", "action"),
    step_count_key="step_count",
    is_init_key="is_init",
    **kwargs,
) -> TensorDictModule:
    """The agent as a TensorDictModule: ``kwargs`` are :class:`RecurrentQNet`'s (``n_actions`` and
    ``hidden`` required), the rest its keys.

    in:  ``obs_key``, ``(group, "prev_action")``, ``(group, "rnn_hidden")``, ``is_init_key``
         (TorchRL's ``InitTracker``) or, where absent, ``step_count_key``; [``(group, "z")``],
         [``state_key`` for full_state]
    out: ``(group, "action_value")``, ``("next", group, "rnn_hidden")``

    ``group`` is the action key's prefix. One step per call at collection; a whole sequence under
    TorchRL's ``set_recurrent_mode(True)`` (what :class:`~icco_torchrl.objectives.ICCOLoss` uses).
    """
    group = action_key[:-1] if isinstance(action_key, tuple) else ()
    net = RecurrentQNet(layout, **kwargs)
    in_keys = {
        "obs": obs_key,
        "prev_action": (*group, "prev_action"),
        "hidden": (*group, "rnn_hidden"),
        "step_count": step_count_key,
        "is_init": is_init_key,
    }  # forward argument -> tensordict key
    if net.z_dim:
        in_keys["z"] = (*group, "z")
    if net.full_state:
        in_keys["state"] = state_key
    return TensorModule(
        net, in_keys=in_keys, out_keys=[(*group, "action_value"), ("next", *group, "rnn_hidden")]
    )
