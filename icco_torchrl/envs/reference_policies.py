"""Scripted reference policies: the yardsticks every trained method is reported beside.

All four drive a :class:`~icco_torchrl.envs.ResourceCollectionEnv` (or a ``TransformedEnv``
over one) through its public state, batched over envs in pure torch:

* ``random``: uniform random actions (its own seeded generator).
* ``follower``: greedy on the instruction reward: each robot takes the action whose predicted
  ``r_inst`` (the env's own kernel, one step ahead) is largest. Ignores the task.
* ``heuristic``: full-information task policy: for each active invader the robot that can
  intercept it soonest goes to the interception point (the invader walks straight home, so its
  future positions are known); robots carrying a resource go home; the others take the nearest
  resource no lower-index robot has claimed. Ignores the instruction. It sees everything, so it
  is an upper reference for the task, not a bound.
* ``blend`` (radius ``r``): each robot acts as the heuristic when its heuristic target is within
  ``r`` metres and follows the waypoints otherwise. ``r = 0`` is the follower, ``r = inf`` the
  heuristic; ``r = vision_radius`` is roughly "do the task you can see".

A policy is a callable ``td -> td`` writing ``("agents", "action")``, like a trained policy,
so it plugs into ``env.rollout``, :func:`~icco_torchrl.evaluation.protocols.run_schedule`
and the trainer's evaluation. It reads the env's state at call time, so call it on the td the
env just returned (as rollouts do). Moves are chosen by a one-step lookahead through the env's
own dynamics kernel; the few loops below run over a fixed small count (robots, lookahead
steps), never over envs. Robots absent from a team (``env.present``) get actions too, which the
env ignores; the heuristic neither sends one to an invader nor lets one claim a resource.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase

from icco_torchrl.envs._kernels import batch_last, motion
from icco_torchrl.envs.resource_collection import N_ACTIONS, ResourceCollectionEnv

REFERENCE_POLICIES = ("random", "follower", "heuristic", "blend")
# The blend radius that wins at the calibrated reward (experiments/calibration/README.md).
BEST_BLEND_RADIUS = 1.75
ACTION_KEY = ("agents", "action")


def raw_env(env) -> ResourceCollectionEnv:
    """The :class:`ResourceCollectionEnv` under ``env``, or a one-line error naming what it is."""
    base = getattr(env, "base_env", env)
    if not isinstance(base, ResourceCollectionEnv):
        raise TypeError(
            f"reference policies drive a ResourceCollectionEnv (5 move actions, its state layout); "
            f"got {type(base).__name__}"
        )
    spec = base.full_action_spec[ACTION_KEY]
    n = getattr(spec, "n", None) or getattr(getattr(spec, "space", None), "n", None)
    if n != N_ACTIONS:
        raise TypeError(
            f"reference policies need the {N_ACTIONS} actions no-op/-x/+x/-y/+y; this env has {n}"
        )
    return base


class ReferencePolicy:
    """Base: ``policy(td)`` writes ``("agents", "action")`` [B, N] for the env's current state."""

    name = "reference"

    def __init__(self, env):
        self.env = raw_env(env)

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td.set(ACTION_KEY, self.act())
        return td

    def act(self) -> torch.Tensor:
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class RandomPolicy(ReferencePolicy):
    name = "random"

    def __init__(self, env, seed: int = 0):
        super().__init__(env)
        self.generator = torch.Generator(device=self.env.device)
        self.generator.manual_seed(seed)

    def act(self) -> torch.Tensor:
        e = self.env
        return torch.randint(
            0, N_ACTIONS, (e.num_envs, e.n_agents), generator=self.generator, device=e.device
        )


def lookahead(env: ResourceCollectionEnv) -> tuple[torch.Tensor, torch.Tensor]:
    """Every action of every robot one step ahead, from the env's own :func:`motion` kernel with the
    actions folded into the batch: positions ``[A, N, 2, B]`` (batch-last) and the unit-scale
    instruction reward ``[B, N, A]`` of each action."""
    A, N, B = N_ACTIONS, env.n_agents, env.num_envs
    fold = lambda x: x.unsqueeze(-1).expand(*x.shape, A).flatten(-2)  # noqa: E731  (env b, action a -> b*A + a)
    action = torch.arange(A, device=env.device).repeat(B).unsqueeze(-1).expand(B * A, N)
    params = env._params()._replace(
        inst_scale=1.0
    )  # the argmax must not vanish when the env's scale is 0
    new_pos, _, r_inst, _, _ = motion(
        fold(env._pos),
        fold(env._vel),
        fold(env._inv),
        fold(env._inv_on),
        fold(env._waypoints_bl()),
        action,
        (env.dt * env.accel) * env._action_dirs,
        params,
    )
    return new_pos.view(N, 2, B, A).permute(3, 0, 1, 2), r_inst.view(N, B, A).transpose(0, 1)


def steer(new_pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The action whose predicted position is nearest ``target`` [B, N, 2]: ``[B, N]``."""
    d = (new_pos - batch_last(target).unsqueeze(0)).square().sum(2)  # [A, N, B]
    return d.argmin(0).t()


class FollowerPolicy(ReferencePolicy):
    name = "follower"

    def act(self) -> torch.Tensor:
        return lookahead(self.env)[1].argmax(-1)


class HeuristicPolicy(ReferencePolicy):
    """Full-information task heuristic (see the module docstring)."""

    name = "heuristic"

    def targets(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Each robot's task target ``[B, N, 2]`` and its distance ``[B, N]``."""
        e = self.env
        pos, carry, present = e.pos, e.carry, e.present  # [B, N, 2], [B, N], [B, N]
        B, N = carry.shape
        target = torch.zeros(B, N, 2, device=e.device)  # carriers: home (the origin)
        busy = carry | ~present  # absent robots take no part (their actions are ignored)
        # Invaders: interception point of the robot that gets there first.
        step = e.max_speed * e.dt  # metres per robot step
        touch = e.agent_radius + e.invader_radius
        horizon = math.ceil(e.field_size * math.sqrt(2) / e.invader_speed) + 1
        k = torch.arange(horizon, device=e.device, dtype=pos.dtype)  # [H]
        inv, on = e.inv_pos, e.inv_active  # [B, I, 2], [B, I]
        dist_home = inv.norm(dim=-1, keepdim=True)  # [B, I, 1]
        walk = (k * e.invader_speed).clamp(max=dist_home)  # [B, I, H]
        future = inv.unsqueeze(2) * (1 - walk / dist_home.clamp_min(1e-6)).unsqueeze(
            -1
        )  # [B, I, H, 2]
        reach = (pos[:, :, None, None] - future[:, None]).norm(dim=-1) - touch  # [B, N, I, H]
        feasible = reach <= k * step
        feasible[..., -1] = True  # else: wait at the last point (home's rim)
        when = feasible.to(torch.uint8).argmax(-1)  # [B, N, I] first feasible
        when = when.masked_fill(~present.unsqueeze(-1), horizon)  # never an absent interceptor
        for i in range(inv.shape[1]):  # a fixed small count (1 invader by default)
            robot = when[:, :, i].argmin(
                -1
            )  # the soonest interceptor, carriers included       # [B]
            active = on[:, i]
            point = future[
                torch.arange(B, device=e.device),
                i,
                when[torch.arange(B, device=e.device), robot, i],
            ]
            sel = torch.nn.functional.one_hot(robot, N).bool() & active.unsqueeze(-1)  # [B, N]
            target = torch.where(sel.unsqueeze(-1), point.unsqueeze(1), target)
            busy = busy | sel
        # Free robots: nearest resource not claimed by a lower-index robot.
        d_res = torch.cdist(pos, e.res_pos)  # [B, N, R]
        claimed = torch.zeros_like(d_res[:, 0], dtype=torch.bool)  # [B, R]
        for n in range(N):  # robots claim in index order
            d = d_res[:, n].masked_fill(claimed, float("inf"))
            j = d.argmin(-1)
            free = ~busy[:, n]
            target[:, n] = torch.where(
                free.unsqueeze(-1), e.res_pos[torch.arange(B, device=e.device), j], target[:, n]
            )
            claimed = claimed | (
                torch.nn.functional.one_hot(j, claimed.shape[1]).bool() & free.unsqueeze(-1)
            )
        return target, (target - pos).norm(dim=-1)

    def act(self) -> torch.Tensor:
        return steer(lookahead(self.env)[0], self.targets()[0])


class BlendPolicy(HeuristicPolicy):
    """The heuristic for robots whose task target is within ``radius``; the follower otherwise."""

    name = "blend"

    def __init__(self, env, radius: float):
        super().__init__(env)
        if not (isinstance(radius, (int, float)) and not isinstance(radius, bool) and radius >= 0):
            raise ValueError(f"blend radius must be a number >= 0 (metres), got {radius!r}")
        self.radius = float(radius)

    def act(self) -> torch.Tensor:
        new_pos, r_inst = lookahead(self.env)
        target, dist = self.targets()
        task = steer(new_pos, target)
        follow = r_inst.argmax(-1)
        return torch.where(dist <= self.radius, task, follow)

    def __repr__(self) -> str:
        return f"BlendPolicy(radius={self.radius})"


def reference_label(name: str, radius: float = BEST_BLEND_RADIUS) -> str:
    """The row label of a reference policy in tables and figures."""
    return f"blend (r={radius:g} m)" if name == "blend" else name


def make_reference_policy(
    name: str, env, *, radius: float | None = None, seed: int = 0
) -> ReferencePolicy:
    """A reference policy by name (``random``, ``follower``, ``heuristic``, ``blend``)."""
    if name == "random":
        return RandomPolicy(env, seed=seed)
    if name == "follower":
        return FollowerPolicy(env)
    if name == "heuristic":
        return HeuristicPolicy(env)
    if name == "blend":
        if radius is None:
            raise ValueError("the blend reference policy needs radius=... (metres)")
        return BlendPolicy(env, radius)
    raise ValueError(f"unknown reference policy {name!r}; choose from {REFERENCE_POLICIES}")
