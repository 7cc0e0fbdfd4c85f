"""Local agent: a recurrent Q-network shared by all robots (parameter sharing).

Input per robot: its observation (own state, own waypoints, visible entities), optionally
the global state (QMIX (FULL)), its previous action and its TACI ``z^i``. Core: encoder ->
GRU -> Q head on ``[GRU output; z]`` (COPA's player). The same ``nn.GRU`` runs one step at
collection time and a whole segment in one call at training time.
"""
from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from icco_torchrl.envs.resource_collection import N_ACTIONS, ObsLayout
from icco_torchrl.modules.encoders import make_encoder
from icco_torchrl.modules.relative import STATE_ENCODERS, RelativeStateEncoder
from icco_torchrl.modules.tdmodule import TensorModule


class RecurrentQNet(nn.Module):
    """Q-values ``[..., N, n_actions]`` from observations, previous actions, z and a GRU state."""

    def __init__(self, layout: ObsLayout, *, hidden: int = 64, z_dim: int = 0, full_state: bool = False,
                 encoder: str = "attention", n_actions: int = N_ACTIONS, state_encoder: str = "flat"):
        super().__init__()
        if state_encoder not in STATE_ENCODERS:
            raise ValueError(f"state_encoder must be one of {STATE_ENCODERS}, got {state_encoder!r}")
        self.hidden, self.z_dim, self.full_state, self.n_actions = hidden, z_dim, full_state, n_actions
        self.relative = full_state and state_encoder == "relative"
        if self.relative:  # QMIX (FULL): every entity relative to the robot (the coordinator's encoder)
            self.encoder = RelativeStateEncoder(layout, hidden)
        else:  # flat: the global state joins the own token of the local-observation encoder
            extra = layout.state_dim if full_state else 0
            self.encoder = make_encoder(encoder, own_dim=layout.own_dim + extra, n_entities=layout.n_entities,
                                        entity_dim=layout.entity_dim, hidden=hidden)
        self._own_dim = layout.own_dim
        # embed([features; one_hot(prev_action)]) written as a linear map plus a per-action row:
        # the same function without building the one-hot and the concatenation.
        self.embed = nn.Linear(hidden, hidden)
        self.prev_action_embed = nn.Embedding(n_actions, hidden)
        bound = 1.0 / (hidden + n_actions) ** 0.5  # nn.Linear's init for the concatenated input
        nn.init.uniform_(self.embed.weight, -bound, bound)
        nn.init.uniform_(self.embed.bias, -bound, bound)
        nn.init.uniform_(self.prev_action_embed.weight, -bound, bound)
        self.gru = nn.GRU(hidden, hidden, batch_first=True)
        self.head = nn.Sequential(nn.Linear(hidden + z_dim, hidden), nn.ReLU(), nn.Linear(hidden, n_actions))

    def _features(self, obs, prev_action, state):
        if self.relative:
            return torch.relu(self.embed(self.encoder(state)) + self.prev_action_embed(prev_action.long()))
        if self.full_state:
            state = state.unsqueeze(-2).expand(*obs.shape[:-1], state.shape[-1])
            obs = torch.cat([obs[..., : self._own_dim], state, obs[..., self._own_dim:]], -1)
        return torch.relu(self.embed(self.encoder(obs)) + self.prev_action_embed(prev_action.long()))

    def _q(self, h, z):
        return self.head(torch.cat([h, z], -1) if self.z_dim else h)

    def forward(self, obs, prev_action, hidden, step_count, z=None, state=None):
        """One step for ``[B, N, ...]`` inputs; the hidden state restarts at zero when step_count == 0."""
        hidden = hidden * (step_count != 0).unsqueeze(-1).to(hidden.dtype)
        return self.step(obs, prev_action, hidden, z, state)

    def step(self, obs, prev_action, hidden, z=None, state=None):
        """One step from ``hidden`` as given (no restart): Q ``[B, N, A]`` and the new hidden state."""
        x = self._features(obs, prev_action, state)
        g = self.gru  # one step of the same nn.GRU, without its sequence-call overhead
        h = torch.gru_cell(x.reshape(-1, self.hidden), hidden.reshape(-1, self.hidden), g.weight_ih_l0,
                           g.weight_hh_l0, g.bias_ih_l0, g.bias_hh_l0).reshape(x.shape)
        return self._q(h, z), h

    def sequence(self, obs, prev_action, hidden0, z=None, state=None, return_hidden: bool = False):
        """A segment in one GRU call: inputs ``[S, L, N, ...]``, ``hidden0 [S, N, H]`` -> Q ``[S, L, N, A]``
        (and, with ``return_hidden``, the hidden state after the last step, ``[S, N, H]``)."""
        x = self._features(obs, prev_action, state)
        S, L, N, H = x.shape
        out, h_last = self.gru(x.permute(0, 2, 1, 3).reshape(S * N, L, H), hidden0.reshape(1, S * N, H).contiguous())
        h = out.reshape(S, N, L, H).permute(0, 2, 1, 3)
        q = self._q(h, z)
        return (q, h_last.reshape(S, N, H)) if return_hidden else q


def make_agent(layout: ObsLayout, *, hidden: int = 64, z_dim: int = 0, full_state: bool = False,
               encoder: str = "attention", state_encoder: str = "flat", obs_key=("agents", "observation"),
               state_key="state", action_key=("agents", "action")) -> TensorDictModule:
    """The agent as a TensorDictModule for collection (one step).

    in:  ``obs_key``, ``("agents", "prev_action")``, ``("agents", "rnn_hidden")``, ``"step_count"``,
         [``("agents", "z")``], [``state_key`` for full_state]
    out: ``("agents", "action_value")``, ``("next", "agents", "rnn_hidden")``
    """
    group = action_key[:-1] if isinstance(action_key, tuple) else ()
    net = RecurrentQNet(layout, hidden=hidden, z_dim=z_dim, full_state=full_state, encoder=encoder,
                        state_encoder=state_encoder)
    in_keys = {"obs": obs_key, "prev_action": (*group, "prev_action"), "hidden": (*group, "rnn_hidden"),
               "step_count": "step_count"}  # forward argument -> tensordict key
    if z_dim:
        in_keys["z"] = (*group, "z")
    if full_state:
        in_keys["state"] = state_key
    return TensorModule(net, in_keys=in_keys,
                            out_keys=[(*group, "action_value"), ("next", *group, "rnn_hidden")])
