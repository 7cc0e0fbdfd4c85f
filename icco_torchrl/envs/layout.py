"""The observation layout contract between the resource-collection env and the networks that read
it.

The env writes per-robot observations and a global state in this layout; the entity-attention
and relative-state encoders of :mod:`icco_torchrl.modules` read it. It is a plain record of sizes
(no env code), so networks can be built for any env that describes itself this way, and a flat
observation needs no layout at all (see ``make_agent(obs_dim=...)``).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ObsLayout:
    """Where things sit in the flat per-robot observation and in the global state."""

    n_agents: int
    n_waypoints: int
    own_dim: int  # [x, y, vx, vy, carry] + relative waypoints
    n_entities: int  # other robots + resources + invaders + home
    entity_dim: int
    state_tokens: int  # robots + resources + invaders
    state_token_dim: int

    @property
    def obs_dim(self) -> int:
        return self.own_dim + self.n_entities * self.entity_dim

    @property
    def state_dim(self) -> int:
        return self.state_tokens * self.state_token_dim
