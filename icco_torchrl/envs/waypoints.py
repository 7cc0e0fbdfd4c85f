"""Waypoint sources: where the robots' waypoints come from when the env does not draw its own.

The policy is trained on random-walk waypoints and can be driven at evaluation by any
instruction: the training distribution, a reference walk kept inside a quadrant (paper Fig. 4),
fixed waypoints, or (in :mod:`icco_torchrl.instructions`) a language instruction planned by an
LLM. Each is an :class:`InstructionSource`; an evaluation loop calls ``reset`` when the
instruction starts and ``source(env, td, step)`` before every policy step, and writes whatever
comes back with ``env.base_env.write_waypoints(td, W)`` (the env runs with
``waypoint_mode="external"``). The quadrant geometry (:data:`QUADRANT_SIGNS`) lives here, with
the env, for the sources, the metrics and the figures.

Shapes: ``B = num_envs``, ``N = n_agents``, ``K = n_waypoints``; waypoints are ``[B, N, K, 2]``
in metres on the env's device.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:  # annotations only
    from tensordict import TensorDictBase

    from icco_torchrl.envs.resource_collection import ResourceCollectionEnv

# How a plan reaches the robots (``eval.plan``): "served" (the default: a training-like walk from
# each robot along its route at every refresh, icco_torchrl/instructions/serving.py) or "fixed"
# (the planner's waypoints written once and kept: the interface the team never trained on, kept
# only so that the comparison on experiments/language/serving can be rerun).
PLAN_INTERFACES = ("served", "fixed")
# Standard maths numbering, counter-clockwise from (+, +): the sign of x and y in each quadrant.
QUADRANT_SIGNS = {1: (1.0, 1.0), 2: (-1.0, 1.0), 3: (-1.0, -1.0), 4: (1.0, -1.0)}


def base_env(env) -> ResourceCollectionEnv:
    """The raw task env under any TorchRL transforms (sources read its state tensors)."""
    return getattr(env, "base_env", env)


def refresh_mask(env: ResourceCollectionEnv, step: int, interval: int) -> torch.Tensor:
    """Envs whose waypoints are due: at the instruction's first step, then whenever the
    env's own step count is a multiple of ``interval``.

    Following the env's clock (not the segment's) keeps the refreshes where training put them,
    on the steps where the coordinator redraws z.
    """
    due = env.t % interval == 0
    return due | (step == 0)


class InstructionSource(ABC):
    """Gives the robots new waypoints, or ``None`` to keep the current ones.

    ``quadrant`` is set by sources that confine the robots to a quadrant (metrics use it).
    """

    quadrant: int | None = None
    instruction: str | None = None  # the words a person gave, for sources that carry them

    @property
    def slots(self) -> torch.Tensor | None:
        """``[B, N, 2]``: where each robot is meant to end up, for sources that say (plans)."""
        return None

    def reset(self, env, td: TensorDictBase) -> None:  # noqa: B027 (an optional hook)
        """The instruction starts now (episode or segment start); ``env`` is in its start state."""

    @abstractmethod
    def __call__(self, env, td: TensorDictBase, step: int) -> torch.Tensor | None:
        """Waypoints ``[B, N, K, 2]`` for the coming step ``step`` (0 = the instruction's first)."""


class _NoisySource(InstructionSource):
    """A source drawing Gaussian increments from its own CPU generator.

    Drawing on the CPU and moving the result makes the walks identical on every device, and
    an own generator leaves the env's random stream (spawns, respawns) untouched.
    """

    def __init__(self, sigma: float | None, interval: int | None, seed: int):
        if sigma is not None and not sigma >= 0:
            raise ValueError(f"sigma must be >= 0, got {sigma!r}")
        if interval is not None and (not isinstance(interval, int) or interval < 1):
            raise ValueError(f"interval must be a positive integer, got {interval!r}")
        self.sigma, self.interval = sigma, interval
        self._gen = torch.Generator().manual_seed(int(seed))

    def settings(self, env: ResourceCollectionEnv) -> tuple[float, int]:
        """``(sigma, interval)``: the given ones, else the env's training values."""
        sigma = env.waypoint_sigma if self.sigma is None else float(self.sigma)
        return sigma, env.waypoint_interval if self.interval is None else self.interval

    def _noise(self, env: ResourceCollectionEnv, sigma: float) -> torch.Tensor:
        shape = (env.num_envs, env.n_agents, env.n_waypoints, 2)
        return (torch.randn(shape, generator=self._gen) * sigma).to(env.device)

    def _due(self, env, step: int):
        """``(raw env, sigma, due mask [B])`` when some env refreshes at this step, else None."""
        env = base_env(env)
        sigma, interval = self.settings(env)
        due = refresh_mask(env, step, interval)
        return (env, sigma, due) if bool(due.any()) else None


class RandomWalkSource(_NoisySource):
    """The training distribution: every ``interval`` steps, K waypoints ``p + cumsum(eps)``,
    ``eps ~ N(0, sigma^2 I)``, from each robot's position, clipped to the field.

    ``sigma`` and ``interval`` default to the env's own (0.19 m, 4 steps), so a policy sees
    exactly what it was trained on.
    """

    def __init__(self, sigma: float | None = None, interval: int | None = None, seed: int = 0):
        super().__init__(sigma, interval, seed)

    def __call__(self, env, td, step):
        if (refresh := self._due(env, step)) is None:
            return None
        env, sigma, due = refresh
        walk = (env.pos.unsqueeze(-2) + self._noise(env, sigma).cumsum(-2)).clamp(
            -env.half, env.half
        )
        return torch.where(due[:, None, None, None], walk, env.waypoints)


class QuadrantSource(_NoisySource):
    """A smooth reference inside one quadrant (paper Sec. V-B): the four-quadrant protocol.

    Every ``interval`` steps each robot gets a K-step zero-mean Gaussian walk that starts from
    its position projected into the quadrant (shrunk by ``margin`` on every side), each step's
    increment clipped to ``max_step`` per axis (default 3 sigma) and each point clamped back into
    the shrunk quadrant. Clamping is 1-Lipschitz, so consecutive waypoints stay within
    ``max_step`` per axis and every waypoint lies strictly inside the quadrant; a robot outside
    it is pulled in by waypoints on the quadrant's near edge.

    Quadrants use the maths convention: 1 = (x>0, y>0), 2 = (x<0, y>0), 3 = (x<0, y<0),
    4 = (x>0, y<0).
    """

    def __init__(
        self,
        quadrant: int,
        sigma: float | None = None,
        interval: int | None = None,
        margin: float = 0.25,
        max_step: float | None = None,
        seed: int = 0,
    ):
        if quadrant not in QUADRANT_SIGNS:
            raise ValueError(f"quadrant must be 1, 2, 3 or 4, got {quadrant!r}")
        if not margin > 0:
            raise ValueError(
                f"margin must be > 0 so that waypoints stay strictly inside, got {margin!r}"
            )
        if max_step is not None and not max_step > 0:
            raise ValueError(f"max_step must be > 0, got {max_step!r}")
        super().__init__(sigma, interval, seed)
        self.quadrant, self.margin, self.max_step = quadrant, float(margin), max_step

    def bounds(self, env: ResourceCollectionEnv) -> tuple[torch.Tensor, torch.Tensor]:
        """Lower and upper corners ``[2]`` of the shrunk quadrant every waypoint lies in."""
        if not self.margin < env.half / 2:
            raise ValueError(
                f"margin {self.margin} leaves no room in a {env.field_size} m field's quadrant"
            )
        signs = torch.tensor(QUADRANT_SIGNS[self.quadrant], device=env.device)
        near, far = self.margin, env.half - self.margin
        low = torch.where(signs > 0, torch.full_like(signs, near), torch.full_like(signs, -far))
        return low, low + (far - near)

    def __call__(self, env, td, step):
        if (refresh := self._due(env, step)) is None:
            return None
        env, sigma, due = refresh
        low, high = self.bounds(env)
        limit = 3 * sigma if self.max_step is None else float(self.max_step)
        noise = self._noise(env, sigma).clamp(-limit, limit)
        point = env.pos.clamp(low, high)
        points = []
        for k in range(env.n_waypoints):  # K is small; envs and robots stay vectorised
            point = (point + noise[:, :, k]).clamp(low, high)
            points.append(point)
        return torch.where(due[:, None, None, None], torch.stack(points, -2), env.waypoints)


class FixedSource(InstructionSource):
    """Caller-given waypoints (``[N, K, 2]`` for every env, or ``[B, N, K, 2]``), written once
    when the instruction starts and then kept."""

    def __init__(self, waypoints):
        self.waypoints = torch.as_tensor(np.asarray(waypoints), dtype=torch.float32)
        if self.waypoints.dim() not in (3, 4) or self.waypoints.shape[-1] != 2:
            raise ValueError(
                f"waypoints must be [N, K, 2] or [B, N, K, 2], got {list(self.waypoints.shape)}"
            )

    def __call__(self, env, td, step):
        if step != 0:
            return None
        env = base_env(env)
        shape = (env.num_envs, env.n_agents, env.n_waypoints, 2)
        try:
            return self.waypoints.to(env.device).expand(shape)
        except RuntimeError:
            raise ValueError(
                f"fixed waypoints {list(self.waypoints.shape)} do not fit the env's {list(shape)}"
            ) from None
