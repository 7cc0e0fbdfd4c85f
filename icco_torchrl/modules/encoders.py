"""Observation encoders shared by the local agents, the coordinator and the posterior.

Entity attention (COPA's choice) reads a set of entity tokens with a visibility mask, so it
does not care about entity order and can later handle other team sizes. The MLP encoder
reads the flat vector: smaller and faster, but tied to the layout it was trained on.
"""
from __future__ import annotations

import math

import torch
from torch import nn


class EntityAttentionEncoder(nn.Module):
    """One "self" token attends over entity tokens; returns ``[..., hidden]``.

    Input ``x = [own (own_dim + extra), tokens (n_entities * entity_dim)]``. A token whose last
    feature (the visibility flag) is 0 is masked out; with nothing visible the attention
    read-out is zero.
    """

    def __init__(self, own_dim: int, n_entities: int, entity_dim: int, hidden: int):
        super().__init__()
        self.own_dim, self.n_entities, self.entity_dim = own_dim, n_entities, entity_dim
        self.own = nn.Linear(own_dim, hidden)
        self.key = nn.Linear(entity_dim, hidden)
        self.value = nn.Linear(entity_dim, hidden)
        self.query = nn.Linear(hidden, hidden)
        self.out = nn.Sequential(nn.Linear(2 * hidden, hidden), nn.ReLU())
        self.scale = 1.0 / math.sqrt(hidden)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        own, tokens = x[..., : self.own_dim], x[..., self.own_dim:]
        tokens = tokens.unflatten(-1, (self.n_entities, self.entity_dim))
        h = torch.relu(self.own(own))
        logits = (self.key(tokens) @ self.query(h).unsqueeze(-1)).squeeze(-1) * self.scale
        visible = tokens[..., -1] > 0
        weights = torch.softmax(logits.masked_fill(~visible, -1e9), -1) * visible
        read = (weights.unsqueeze(-1) * self.value(tokens)).sum(-2)
        return self.out(torch.cat([h, read], -1))


class MLPEncoder(nn.Module):
    """Two-layer MLP on the flat input."""

    def __init__(self, in_dim: int, hidden: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


def make_encoder(kind: str, *, own_dim: int, n_entities: int, entity_dim: int, hidden: int) -> nn.Module:
    """``kind`` is ``"attention"`` or ``"mlp"``; the input is ``own_dim + n_entities*entity_dim`` wide."""
    if kind == "attention":
        return EntityAttentionEncoder(own_dim, n_entities, entity_dim, hidden)
    if kind == "mlp":
        return MLPEncoder(own_dim + n_entities * entity_dim, hidden)
    raise ValueError(f"encoder must be 'attention' or 'mlp', got {kind!r}")
