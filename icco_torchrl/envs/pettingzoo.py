"""PettingZoo ``ParallelEnv`` view of one resource-collection env.

Users of other MARL libraries get the task through the standard PettingZoo API (numpy in
and out, one dict entry per robot) while the dynamics stay those of
:class:`~icco_torchrl.envs.resource_collection.ResourceCollectionEnv` with ``num_envs=1``:
there is one implementation of the task, so the two views cannot drift apart.
"""
from __future__ import annotations

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv

from icco_torchrl.envs.resource_collection import N_ACTIONS, ResourceCollectionEnv


class ResourceCollectionParallelEnv(ParallelEnv):
    """One resource-collection env as a PettingZoo ``ParallelEnv`` (robots ``agent_0..``).

    Args:
        render_mode: ``"rgb_array"`` (``render()`` returns an ``[H, W, 3]`` uint8 frame) or None.
        render_size: side of rendered frames in pixels.
        **env_kwargs: forwarded to :class:`ResourceCollectionEnv` (``seed``, ``n_agents``,
            ``max_steps``, ...); ``num_envs`` is fixed to 1 and the device to CPU, since
            every step crosses to numpy anyway.

    ``max_cycles`` is PettingZoo's name for the episode length: it starts at the env's
    ``max_steps`` and may be reassigned (``parallel_api_test`` does); the view truncates when
    its own step counter reaches it. Observations and rewards are unaffected by it.

    ``infos[agent]["events"]`` holds the team's event counts of the step (pick, collect,
    defense, invasion) and the summed instruction reward, identical for every robot.
    """

    metadata = {"render_modes": ["rgb_array"], "name": "resource_collection_v0", "is_parallelizable": True}

    def __init__(self, render_mode: str | None = None, render_size: int = 480, **env_kwargs):
        modes = self.metadata["render_modes"]
        if render_mode not in (None, *modes):
            raise ValueError(f"render_mode must be None or one of {modes}, got {render_mode!r}")
        for fixed in ("num_envs", "device"):
            if fixed in env_kwargs:
                raise ValueError(f"{fixed} is fixed by the PettingZoo view (one env on CPU)")
        self.render_mode, self.render_size = render_mode, render_size
        self._env = ResourceCollectionEnv(num_envs=1, device="cpu", **env_kwargs)
        self.max_cycles = self._env.max_steps
        self.possible_agents = [f"agent_{i}" for i in range(self._env.n_agents)]
        self.agents: list[str] = []
        # Every observation feature is a position or a difference of positions inside the
        # field, a (relative) velocity, or a flag, hence this loose but valid bound.
        bound = float(self._env.field_size + 2 * self._env.max_speed + 1)
        obs_dim, state_dim = self._env.layout.obs_dim, self._env.layout.state_dim
        self.observation_spaces = {a: spaces.Box(-bound, bound, (obs_dim,), np.float32)
                                   for a in self.possible_agents}
        self.action_spaces = {a: spaces.Discrete(N_ACTIONS) for a in self.possible_agents}
        self.state_space = spaces.Box(-bound, bound, (state_dim,), np.float32)
        self._td = None
        self._steps = 0

    def observation_space(self, agent: str) -> spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Discrete:
        return self.action_spaces[agent]

    def reset(self, seed: int | None = None, options: dict | None = None):
        """Start an episode; ``seed`` re-seeds the env exactly as ``ResourceCollectionEnv(seed=seed)``."""
        if seed is not None:
            self._env.set_seed(seed)
        self._td = self._env.reset()
        self._steps = 0
        self.agents = list(self.possible_agents)
        return self._observations(self._td), {a: {} for a in self.agents}

    def step(self, actions: dict):
        if not self.agents:
            raise RuntimeError("step() called on a finished episode; call reset() first")
        if set(actions) != set(self.agents):
            raise ValueError(f"actions must have exactly one entry per live agent {self.agents}, "
                             f"got {sorted(actions)}")
        action = torch.tensor([[int(actions[a]) for a in self.possible_agents]], dtype=torch.int64)
        self._td.set(("agents", "action"), action)
        nxt = self._env.step(self._td).get("next")
        self._td = nxt.exclude("reward", ("agents", "reward"))
        self._steps += 1

        rewards = nxt.get(("agents", "reward"))[0, :, 0].tolist()
        events = {k: v.item() for k, v in nxt.get("events")[0].items()}
        truncated = self._steps >= self.max_cycles
        agents = self.agents
        obs = self._observations(nxt)
        out = (
            obs,
            {a: float(rewards[i]) for i, a in enumerate(agents)},
            {a: False for a in agents},
            {a: truncated for a in agents},
            {a: {"events": dict(events)} for a in agents},
        )
        if truncated:
            self.agents = []
        return out

    def state(self) -> np.ndarray:
        """Global state (everyone's positions, flags and waypoints), as the coordinator sees it."""
        if self._td is None:
            raise RuntimeError("state() called before reset()")
        return self._td.get("state")[0].numpy().astype(np.float32, copy=True)

    def render(self):
        if self.render_mode is None:
            gymnasium.logger.warn("render() called with render_mode=None; pass render_mode='rgb_array'")
            return None
        from icco_torchrl.envs.render import render_frame

        return render_frame(self._env, index=0, size=self.render_size)

    def close(self) -> None:
        """Nothing to release: the env holds only tensors."""

    def _observations(self, td) -> dict[str, np.ndarray]:
        obs = td.get(("agents", "observation"))[0].numpy()
        return {a: obs[i].astype(np.float32, copy=True) for i, a in enumerate(self.possible_agents)}
