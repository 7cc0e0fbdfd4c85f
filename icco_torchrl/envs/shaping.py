"""Potential-based reward shaping for the training env: ``F = gamma * Phi(s') - Phi(s)``.

Shaping of this form cannot change which policies are optimal (Ng, Harada and Russell 1999) nor
the Nash equilibria of a stochastic game (Devlin and Kudenko 2011): over an episode it adds
``gamma^T Phi(s_T) - Phi(s_0)`` to the discounted return, whatever the robots do in between.
It gives collecting a dense signal without boosting the delivery reward.

``Phi`` is read from the global state (robots, resources and invaders as tokens, home at the
origin), one potential per robot, summed over the named potentials and scaled by ``weight``:

- ``collect``: minus the distance a robot has left in its delivery cycle: a carrier's distance
  home; a free robot's shortest trip through a resource and home. Continuous at a pick; it drops
  by one cycle's length at a delivery (the delivery reward pays for it).
- ``defend``: minus a free robot's distance to the nearest active invader (0 without one).

The team reward gets ``sum_i F_i``, each robot's own reward its ``F_i``.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

from icco_torchrl.envs.layout import ObsLayout

POTENTIALS = ("collect", "defend")
# State token columns (ObsLayout): position, and the flag that is a robot's carry flag and an
# invader's active flag.
_X, _FLAG = ObsLayout.POSITION, ObsLayout.FLAG


def missing_for(name: str, *, n_resources: int, n_invaders: int) -> str | None:
    """What the env's state lacks for potential ``name`` (None when it has everything)."""
    if name == "collect" and n_resources < 1:
        return "resources (n_resources >= 1)"
    if name == "defend" and n_invaders < 1:
        return "invaders (n_invaders >= 1)"
    return None


class StatePotential:
    """``Phi(state) [..., N]`` per robot from the flat global state ``[..., state_dim]``."""

    def __init__(self, layout: ObsLayout, n_resources: int, potentials, weight: float):
        unknown = [p for p in potentials if p not in POTENTIALS]
        if unknown:
            raise ValueError(f"unknown shaping potentials {unknown}; choose from {POTENTIALS}")
        n_invaders = layout.state_tokens - layout.n_agents - n_resources
        for name in potentials:
            lack = missing_for(name, n_resources=n_resources, n_invaders=n_invaders)
            if lack:
                raise ValueError(f"shaping potential {name!r} needs {lack} in the env's state")
        self.layout = layout
        self.N, self.R, self.D = layout.n_agents, n_resources, layout.state_token_dim
        self.potentials, self.weight = tuple(potentials), float(weight)

    def __call__(self, state: torch.Tensor) -> torch.Tensor:
        tokens = state.unflatten(-1, (-1, self.D))  # [..., tokens, D]
        robots, rest = tokens[..., : self.N, :], tokens[..., self.N :, :]
        resources, invaders = rest[..., : self.R, :], rest[..., self.R :, :]
        pos, carry = robots[..., _X], robots[..., _FLAG] > 0.5  # [..., N, 2], [..., N]
        present = self.layout.robot_mask(state)  # an absent robot's token is all zeros: no Phi
        phi = torch.zeros_like(pos[..., 0])
        if "collect" in self.potentials:
            res = resources[..., _X]  # [..., R, 2]
            trip = torch.cdist(pos, res) + res.norm(dim=-1).unsqueeze(-2)  # robot -> r -> home
            phi = phi - torch.where(carry, pos.norm(dim=-1), trip.min(-1).values)
        if "defend" in self.potentials:
            active = invaders[..., _FLAG] > 0.5  # [..., I]
            dist = torch.cdist(pos, invaders[..., _X]).masked_fill(~active.unsqueeze(-2), torch.inf)
            nearest = dist.min(-1).values
            phi = phi - torch.where(~carry & nearest.isfinite(), nearest, torch.zeros_like(nearest))
        return self.weight * torch.where(present, phi, torch.zeros_like(phi))


class PotentialShaping(Transform):
    """Adds ``F_i = gamma * Phi_i(s') - Phi_i(s)`` to each robot's reward and their sum to the
    team reward, for the training env only (an evaluation env never carries it).

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from icco_torchrl.envs import ResourceCollectionEnv
        >>> base = ResourceCollectionEnv(num_envs=2, seed=0)
        >>> env = TransformedEnv(base, PotentialShaping.for_env(base, ["collect"], 0.3, 0.99))
        >>> env.rollout(3)["next", "reward"].shape
        torch.Size([2, 3, 1])
    """

    def __init__(self, potential: StatePotential, gamma: float, state_key="state"):
        super().__init__(in_keys=[state_key], out_keys=[])
        self.potential, self.gamma, self.state_key = potential, float(gamma), state_key

    @classmethod
    def for_env(cls, env, potentials, weight: float, gamma: float) -> PotentialShaping:
        """The shaping for a :class:`~icco_torchrl.envs.ResourceCollectionEnv` ``env``."""
        return cls(StatePotential(env.layout, env.n_resources, potentials, weight), gamma)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        # Both states in one pass: the env step pays the potential's ops once, not twice.
        states = (tensordict.get(self.state_key), next_tensordict.get(self.state_key))
        before, after = self.potential(torch.stack(states))
        shaping = self.gamma * after - before  # [B, N]
        next_tensordict.set("reward", next_tensordict.get("reward") + shaping.sum(-1, keepdim=True))
        agent_reward = ("agents", "reward")
        if agent_reward in next_tensordict.keys(True):
            next_tensordict.set(
                agent_reward, next_tensordict.get(agent_reward) + shaping.unsqueeze(-1)
            )
        return next_tensordict

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return tensordict_reset
