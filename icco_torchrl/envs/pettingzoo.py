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

    Teams: ``possible_agents`` are all ``n_agents`` robots and ``agents`` the present ones (with
    ``team_sizes``, drawn at each reset; :meth:`remove_robot` and :meth:`add_robot` change them
    between steps). Observations, rewards, terminations, truncations, infos and the expected
    actions cover exactly ``agents``; absent robots' state tokens are zeros.

    Actions are integers ``0..4`` (Python or numpy integers); anything else is a ``ValueError``.
    The observation and state ``Box`` bounds are computed from the env parameters (see
    :func:`space_bounds`) and hold for every valid setting. One difference from the batched
    env's observation: the token of an *inactive* invader (between its removal and respawn)
    is all zeros, as for any entity out of sight. The batched env hides such invaders by
    placing them 1e9 m away, which a robot with a vision radius that large would "see".
    """

    metadata = {
        "render_modes": ["rgb_array"],
        "name": "resource_collection_v0",
        "is_parallelizable": True,
    }

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
        (obs_low, obs_high), (state_low, state_high) = space_bounds(self._env)
        self.observation_spaces = {
            a: spaces.Box(obs_low, obs_high, dtype=np.float32) for a in self.possible_agents
        }
        self.action_spaces = {a: spaces.Discrete(N_ACTIONS) for a in self.possible_agents}
        self.state_space = spaces.Box(state_low, state_high, dtype=np.float32)
        L = self._env.layout
        # Columns of the invaders' tokens in an observation: after the other robots and resources.
        first = L.own_dim + (L.n_agents - 1 + self._env.n_resources) * L.entity_dim
        self._invader_cols = [
            slice(first + i * L.entity_dim, first + (i + 1) * L.entity_dim)
            for i in range(self._env.n_invaders)
        ]
        self._td = None
        self._steps = 0

    def observation_space(self, agent: str) -> spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Discrete:
        return self.action_spaces[agent]

    def reset(self, seed: int | None = None, options: dict | None = None):
        """Start an episode; ``seed`` re-seeds the env exactly as
        ``ResourceCollectionEnv(seed=seed)``."""
        if seed is not None:
            self._env.set_seed(seed)
        self._td = self._env.reset()
        self._steps = 0
        self.agents = self._team()
        return self._observations(self._td), {a: {} for a in self.agents}

    def step(self, actions: dict):
        if self._td is None:
            raise RuntimeError("step() called before reset(); call reset() first")
        if not self.agents:
            raise RuntimeError("step() called on a finished episode; call reset() first")
        if set(actions) != set(self.agents):
            raise ValueError(
                f"actions must have exactly one entry per live agent {self.agents}, "
                f"got {sorted(actions)}"
            )
        action = torch.tensor(  # an absent robot's action is ignored by the env: a no-op
            [[_action_index(a, actions[a]) if a in actions else 0 for a in self.possible_agents]],
            dtype=torch.int64,
        )
        self._td.set(("agents", "action"), action)
        nxt = self._env.step(self._td).get("next")
        self._td = nxt.exclude("reward", ("agents", "reward"))
        self._steps += 1

        rewards = dict(zip(self.possible_agents, nxt.get(("agents", "reward"))[0, :, 0].tolist()))
        events = {k: v.item() for k, v in nxt.get("events")[0].items()}
        truncated = self._steps >= self.max_cycles
        agents = self.agents
        obs = self._observations(nxt)
        out = (
            obs,
            {a: float(rewards[a]) for a in agents},
            {a: False for a in agents},
            {a: truncated for a in agents},
            {a: {"events": dict(events)} for a in agents},
        )
        if truncated:
            self.agents = []
        return out

    def remove_robot(self, agent: str) -> None:
        """Take ``agent`` (``"agent_<i>"``) out of the team between steps; it leaves ``agents``."""
        self._env.remove_robot(0, self._robot(agent), tensordict=self._td)
        self.agents = self._team()

    def add_robot(self, agent: str | None = None) -> str:
        """Bring ``agent`` (None: the lowest absent one) into the team between steps; its name."""
        robot = None if agent is None else self._robot(agent)
        added = self._env.add_robot(0, robot, tensordict=self._td)
        self.agents = self._team()
        return self.possible_agents[added]

    def _robot(self, agent: str) -> int:
        if self._td is None or not self.agents:
            raise RuntimeError("a team changes during an episode; call reset() first")
        if agent not in self.possible_agents:
            raise ValueError(f"unknown agent {agent!r}; possible agents: {self.possible_agents}")
        return self.possible_agents.index(agent)

    def _team(self) -> list[str]:
        present = self._env.present[0].tolist()
        return [a for a, here in zip(self.possible_agents, present) if here]

    def state(self) -> np.ndarray:
        """Global state (everyone's positions, flags and waypoints), as the coordinator sees it."""
        if self._td is None:
            raise RuntimeError("state() called before reset()")
        return self._td.get("state")[0].numpy().astype(np.float32, copy=True)

    def render(self):
        if self.render_mode is None:
            gymnasium.logger.warn(
                "render() called with render_mode=None; pass render_mode='rgb_array'"
            )
            return None
        from icco_torchrl.envs.render import render_frame

        return render_frame(self._env, index=0, size=self.render_size)

    def close(self) -> None:
        """Nothing to release: the env holds only tensors."""

    def _observations(self, td) -> dict[str, np.ndarray]:
        obs = td.get(("agents", "observation"))[0].numpy().astype(np.float32, copy=True)
        for cols, active in zip(self._invader_cols, self._env.inv_active[0].tolist()):
            if not active:  # out of play: no 1e9 placeholder distances (see the class docstring)
                obs[:, cols] = 0.0
        return {a: obs[self.possible_agents.index(a)] for a in self.agents}


def _action_index(agent: str, value) -> int:
    """``value`` as an action index; floats, strings, bools and out-of-range integers refused."""
    index = value
    if isinstance(index, (np.ndarray, torch.Tensor)) and index.ndim == 0:
        index = index.item()  # a 0-d array or tensor, e.g. np.asarray(space.sample()) or q.argmax()
    if (
        isinstance(index, (int, np.integer))
        and not isinstance(index, (bool, np.bool_))
        and 0 <= index < N_ACTIONS
    ):
        return int(index)
    raise ValueError(
        f"action for {agent} must be an integer in 0..{N_ACTIONS - 1} "
        f"(int or numpy integer), got {value!r}"
    )


def _pad(bound: float) -> float:
    # float32 rounding (speed caps, clamps, squared-distance tests) can exceed a bound by an ulp
    # or so; a small relative margin keeps the values inside.
    return bound * (1 + 1e-4) + 1e-6


def _sym(bound: float, n: int = 1) -> list[tuple[float, float]]:
    """``n`` features in ``[-bound, bound]`` (padded)."""
    return [(-_pad(bound), _pad(bound))] * n


def _flags(n: int) -> list[tuple[float, float]]:
    """``n`` flags or one-hot entries, in ``[0, 1]``."""
    return [(0.0, 1.0)] * n


def space_bounds(
    env: ResourceCollectionEnv,
) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """``(low, high)`` of every observation feature and of every state feature, from ``env``'s
    parameters.

    Robots stay within ``|x|, |y| <= |field_size/2 - agent_radius|`` (the wall); invaders and
    waypoints within the field; resources within the field or on home's rim (a candidate spawn
    on home is pushed out to ``home_radius + resource_radius``). Speeds are capped at
    ``max_speed`` (robots) and ``invader_speed / dt`` (invaders, metres per step over dt).
    A relative position is at most the vision radius, or twice the largest coordinate.
    """
    half = env.field_size / 2
    robot = abs(half - env.agent_radius)
    extent = max(
        half, robot, abs(half - env.resource_radius), env.home_radius + env.resource_radius
    )
    invader_v = env.invader_speed / env.dt
    K = env.n_waypoints
    own = _sym(robot, 2) + _sym(env.max_speed, 2) + _flags(1) + _sym(robot + extent, 2 * K)
    token = (
        _sym(min(env.vision_radius, 2 * extent), 2)
        + _sym(env.max_speed + max(env.max_speed, invader_v), 2)
        + _flags(6)
    )  # one-hot type (4), flag, visible
    state_token = (
        _sym(extent, 2)
        + _sym(max(env.max_speed, invader_v), 2)
        + _flags(5)  # type (3), flag, defended
        + _sym(extent, 2 * K)
    )
    obs = np.array(own + token * env.layout.n_entities, np.float32)
    state = np.array(state_token * env.layout.state_tokens, np.float32)
    return (obs[:, 0], obs[:, 1]), (state[:, 0], state[:, 1])
