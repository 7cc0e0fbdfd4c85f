"""Observation encoders shared by the local agents, the coordinator and the posterior.

Entity attention (COPA's choice) reads a set of entity tokens with a visibility mask, so it
does not care about entity order and can later handle other team sizes. The MLP encoder
reads the flat vector: smaller and faster, but tied to the layout it was trained on.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from icco_torchrl.modules.activations import ReLU, relu


class EntityAttentionEncoder(nn.Module):
    """One "self" token attends over entity tokens; returns ``[..., hidden]``.

    Input ``x = [own (own_dim), tokens (n_entities * entity_dim)]``. With ``flag_column`` a token
    whose feature in that column (its visibility flag, as the caller's layout names it:
    ``ObsLayout.visible_column`` for an observation's entities) is 0 is left out;
    ``visible [..., n_entities]`` (bool) gives the mask instead, for tokens that carry no flag.
    With nothing visible the attention read-out is 0.

    Keys and values are linear in the raw tokens, so the attention is evaluated in token space:
    ``q . (W_k t) = (W_k^T q) . t`` and ``sum_e w_e (W_v t_e + b_v) = W_v (sum_e w_e t_e) +
    b_v sum_e w_e``. Same function as projecting every token, without the
    ``[.., n_entities, hidden]`` tensors (the update is several times faster). The keys carry no
    bias: ``q . b_k`` is the same for every token and softmax ignores a constant shift.
    """

    def __init__(
        self,
        own_dim: int,
        n_entities: int,
        entity_dim: int,
        hidden: int,
        flag_column: int | None = None,
    ):
        super().__init__()
        self.own_dim, self.n_entities, self.entity_dim, self.flag_column = (
            own_dim,
            n_entities,
            entity_dim,
            flag_column,
        )
        self.own = nn.Linear(own_dim, hidden)
        self.key = nn.Linear(entity_dim, hidden, bias=False)
        self.value = nn.Linear(entity_dim, hidden)
        self.query = nn.Linear(hidden, hidden)
        self.out = nn.Sequential(nn.Linear(2 * hidden, hidden), ReLU())
        self.scale = 1.0 / math.sqrt(hidden)

    def forward(self, x: torch.Tensor, visible: torch.Tensor | None = None) -> torch.Tensor:
        own, tokens = x[..., : self.own_dim], x[..., self.own_dim :]
        tokens = tokens.unflatten(-1, (self.n_entities, self.entity_dim))
        h = relu(self.own(own))
        q = self.query(h) @ self.key.weight * self.scale  # the query in token space
        logits = (tokens @ q.unsqueeze(-1)).squeeze(-1)
        if self.flag_column is not None or visible is not None:
            if visible is None:
                visible = tokens[..., self.flag_column] > 0
            # The mask as a float: a compiled update then saves no bool tensor for the backward
            # (Inductor writes bools slowly); hidden tokens get -1e9, as masked_fill gave them.
            seen = visible.to(logits.dtype)
            weights = torch.softmax(logits + (seen - 1.0) * 1e9, -1) * seen
        else:
            weights = torch.softmax(logits, -1)
        pooled = (weights.unsqueeze(-2) @ tokens).squeeze(-2)  # [..., entity_dim]
        read = pooled @ self.value.weight.T + weights.sum(-1, keepdim=True) * self.value.bias
        return self.out(torch.cat([h, read], -1))


class MLPEncoder(nn.Module):
    """Two-layer MLP on the flat input."""

    def __init__(self, in_dim: int, hidden: int):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(in_dim, hidden), ReLU(), nn.Linear(hidden, hidden), ReLU()
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


def make_encoder(
    kind: str,
    *,
    own_dim: int,
    n_entities: int,
    entity_dim: int,
    hidden: int,
    flag_column: int | None = None,
) -> nn.Module:
    """``kind``: ``"attention"`` (its tokens' visibility flag in ``flag_column``) or ``"mlp"``;
    input width ``own_dim + n_entities*entity_dim``."""
    if kind == "attention":
        return EntityAttentionEncoder(own_dim, n_entities, entity_dim, hidden, flag_column)
    if kind == "mlp":
        return MLPEncoder(own_dim + n_entities * entity_dim, hidden)
    raise ValueError(f"encoder must be 'attention' or 'mlp', got {kind!r}")
