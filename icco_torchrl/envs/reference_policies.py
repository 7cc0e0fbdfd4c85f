"""Scripted reference policies: the yardsticks every trained method is reported beside.

Each drives a :class:`~icco_torchrl.envs.ResourceCollectionEnv` (or a ``TransformedEnv``
over one) through its public state, batched over envs in pure torch:

* ``random``: uniform random actions (its own seeded generator).
* ``follower``: greedy on the instruction reward: each robot takes the action whose predicted
  ``r_inst`` (the env's own kernel, one step ahead) is largest. Ignores the task.
* ``pursuit``: a perfect path follower: each robot steers to the waypoint after its nearest one
  (the next point of its route; the last one once it is at the end), at full speed. The
  ``follower`` can stall where this one cannot: ``r_inst``'s cosine does not see speed, so on a
  diagonal path coasting to a halt along the path's direction scores more than any of the axis
  moves (experiments/language/serving/README.md). Ignores the task.
* ``heuristic``: full-information task policy: for each active invader the robot that can
  intercept it soonest goes to the interception point (the invader walks straight home, so its
  future positions are known); robots carrying a resource go home; the others take the nearest
  resource no lower-index robot has claimed. Ignores the instruction. It sees everything, so it
  is an upper reference for the task, not a bound.
* ``blend`` (radius ``r``): each robot acts as the heuristic when its heuristic target is within
  ``r`` metres and follows the waypoints otherwise. ``r = 0`` is the follower, ``r = inf`` the
  heuristic; ``r = vision_radius`` is roughly "do the task you can see".
* ``blend(defend=R, collect=R, deliver=R)``: the blend with a radius per role (:data:`ROLES`):
  ``defend``, the robot the heuristic sends to intercept the invader; ``collect``, the robots it
  sends to a resource; ``deliver``, the carriers it sends home. A role left out follows (radius 0);
  ``blend(R)`` and the bare ``blend`` (radius ``eval.blend_radius``) give every role one radius.
  ``follow=pursuit`` (:data:`FOLLOWS`) makes the robots outside their radius pursue their route
  instead of following greedily: ``blend(defend=1.75, follow=pursuit)`` is the team a person
  asks for, every robot at its slot but the one that stops an invader near it.
* ``best_scripted``: the role blend :data:`BEST_SCRIPTED`, the best point of the scripted frontier
  at the calibrated reward (``experiments/calibration/best_scripted.py``). Every report states a
  learned team's reward as a share of it.

Names parse in one place (:func:`parse_reference`) and fail in one line naming the bad field:

    >>> parse_reference("blend(defend=1.75)").radii
    RoleRadii(defend=1.75, collect=0.0, deliver=0.0)
    >>> parse_reference("blend(defend=1.75, follow=pursuit)").follow
    'pursuit'
    >>> reference_label("blend(defend=1.75, collect=1)")
    'blend (defend=1.75, collect=1, deliver=0 m)'
    >>> reference_label("blend(defend=1.75, follow=pursuit)")
    'blend (defend=1.75, collect=0, deliver=0 m; follow=pursuit)'
    >>> reference_key(reference_label("blend(defend=1.75, follow=pursuit)"))
    'blend(defend=1.75, collect=0, deliver=0, follow=pursuit)'
    >>> parse_reference("blend(defend=-1)")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ValueError: reference 'blend(defend=-1)': radius 'defend' must be a number >= 0 ...

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
import re
from collections.abc import Mapping
from typing import NamedTuple

import torch
from tensordict import TensorDictBase

from icco_torchrl.envs._kernels import batch_last, motion
from icco_torchrl.envs.resource_collection import N_ACTIONS, ResourceCollectionEnv

REFERENCE_POLICIES = ("random", "follower", "heuristic", "blend", "best_scripted", "pursuit")
# The rows every evaluation reports beside the checkpoints (``eval.references``): ``pursuit``
# ignores the task and earns little reward; it is the arrival yardstick (assets/go_right.py).
EVAL_REFERENCES = REFERENCE_POLICIES[:-1]
ROLES = ("defend", "collect", "deliver")  # a role blend's radii, in this order
# What a blend's robots do outside their role's radius: follow greedily on r_inst, or pursue.
FOLLOWS = ("follower", "pursuit")
DEFEND, COLLECT, DELIVER = range(len(ROLES))
ACTION_KEY = ("agents", "action")


class RoleRadii(NamedTuple):
    """A blend's radius (m) per role: within it the robot does its heuristic task, else it
    follows. ``0`` never works, ``inf`` always does."""

    defend: float = 0.0
    collect: float = 0.0
    deliver: float = 0.0


# The blend radius that wins at the calibrated reward (experiments/calibration/README.md).
BEST_BLEND_RADIUS = 1.75
# The best role blend at the calibrated reward: the scripted frontier's best point, searched on
# episodes no evaluation plays (experiments/calibration/results/best_scripted.json, README.md).
BEST_SCRIPTED = RoleRadii(defend=math.inf, collect=1.0, deliver=2.0)
BEST_SCRIPTED_LABEL = "best scripted"


class Reference(NamedTuple):
    """A parsed reference name (:func:`parse_reference`): ``kind`` (one of
    :data:`REFERENCE_POLICIES` but ``best_scripted``), a blend's ``radii`` (None for the bare
    ``blend`` and the other kinds) and what its robots do outside them (:data:`FOLLOWS`)."""

    kind: str
    radii: RoleRadii | None = None
    follow: str = "follower"


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


def route_target(env: ResourceCollectionEnv) -> torch.Tensor:
    """Each robot's next route point ``[B, N, 2]``: the waypoint after its nearest one (the last
    one once it is at the end)."""
    wp = env.waypoints  # [B, N, K, 2]
    nearest = (wp - env.pos.unsqueeze(-2)).norm(dim=-1).argmin(-1, keepdim=True)  # [B, N, 1]
    ahead = (nearest + 1).clamp_max(wp.shape[-2] - 1)
    return wp.gather(-2, ahead.unsqueeze(-1).expand(*ahead.shape, 2)).squeeze(-2)


class PursuitPolicy(ReferencePolicy):
    name = "pursuit"

    def act(self) -> torch.Tensor:
        return steer(lookahead(self.env)[0], route_target(self.env))


class HeuristicPolicy(ReferencePolicy):
    """Full-information task heuristic (see the module docstring)."""

    name = "heuristic"

    def targets(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Each robot's task target ``[B, N, 2]`` and its distance ``[B, N]``."""
        return self.plan()[:2]

    def plan(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Each robot's task target ``[B, N, 2]``, its distance ``[B, N]`` and its role ``[B, N]``
        (an index into :data:`ROLES`: the interceptor defends, other carriers deliver, the rest
        collect)."""
        e = self.env
        pos, carry, present = e.pos, e.carry, e.present  # [B, N, 2], [B, N], [B, N]
        B, N = carry.shape
        target = torch.zeros(B, N, 2, device=e.device)  # carriers: home (the origin)
        busy = carry | ~present  # absent robots take no part (their actions are ignored)
        role = torch.where(carry, DELIVER, COLLECT)
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
            role = role.masked_fill(sel, DEFEND)
            busy = busy | sel
        self._claim_resources(pos, target, busy)
        return target, (target - pos).norm(dim=-1), role

    def _claim_resources(self, pos: torch.Tensor, target: torch.Tensor, busy: torch.Tensor) -> None:
        """Send each free robot (not ``busy [B, N]``, at ``pos [B, N, 2]``) to the nearest
        resource not claimed by a lower-index robot, in ``target [B, N, 2]``."""
        e = self.env
        B, N = busy.shape
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

    def act(self) -> torch.Tensor:
        return steer(lookahead(self.env)[0], self.targets()[0])


class BlendPolicy(HeuristicPolicy):
    """The heuristic for a robot whose task target is within its role's radius; the follower
    otherwise. ``radius``: one number (every role), a ``{role: radius}`` mapping or
    :class:`RoleRadii` (roles left out follow), or a tensor ``[num_envs, 3]`` of radii per env in
    :data:`ROLES` order (a grid of blends in one batch). ``follow`` (:data:`FOLLOWS`): what a
    robot outside its radius does, greedy on r_inst (``follower``) or on its route (``pursuit``)."""

    name = "blend"

    def __init__(self, env, radius, follow: str = "follower"):
        super().__init__(env)
        if follow not in FOLLOWS:
            raise ValueError(f"blend follow must be one of {', '.join(FOLLOWS)}, got {follow!r}")
        self.follow = follow
        B = self.env.num_envs
        if isinstance(radius, torch.Tensor):
            radii = radius.to(self.env.device, torch.float32)
            if radii.shape not in ((len(ROLES),), (B, len(ROLES))) or not (radii >= 0).all():
                raise ValueError(
                    f"blend radii tensor must be [{len(ROLES)}] or [num_envs={B}, {len(ROLES)}] "
                    f"of numbers >= 0 (metres), got shape {tuple(radii.shape)}"
                )
            self.radius = None
        else:
            self.radius = role_radii(radius)
            radii = torch.tensor(self.radius, device=self.env.device)
        self.radii = radii.expand(B, len(ROLES))  # [B, 3]

    def act(self) -> torch.Tensor:
        new_pos, r_inst = lookahead(self.env)
        target, dist, role = self.plan()
        task = steer(new_pos, target)
        if self.follow == "pursuit":
            follow = steer(new_pos, route_target(self.env))
        else:
            follow = r_inst.argmax(-1)
        return torch.where(dist <= self.radii.gather(1, role), task, follow)

    def __repr__(self) -> str:
        radius = self.radius if self.radius is not None else "per env"
        follow = "" if self.follow == "follower" else f", follow={self.follow!r}"
        return f"BlendPolicy(radius={radius}{follow})"


def _radius(value, field: str) -> float:
    """``value`` as a radius (a number >= 0, ``inf`` allowed), or a one-line error naming
    ``field``."""
    try:
        number = float(value) if isinstance(value, str) else value
        ok = not isinstance(number, bool) and number >= 0  # NaN fails the comparison
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{field} must be a number >= 0 (metres), got {value!r}")
    return float(number)


def role_radii(radius) -> RoleRadii:
    """One radius for every role, or ``{role: radius}`` (roles left out: 0, they follow)."""
    if isinstance(radius, RoleRadii):
        radius = radius._asdict()
    if not isinstance(radius, Mapping):
        return RoleRadii(*[_radius(radius, "blend radius")] * len(ROLES))
    unknown = [role for role in radius if role not in ROLES]
    if unknown:
        raise ValueError(f"blend role {unknown[0]!r} is unknown; roles are {', '.join(ROLES)}")
    return RoleRadii(**{r: _radius(v, f"blend radius {r!r}") for r, v in radius.items()})


_CALL = re.compile(r"blend\s*\((.*)\)", re.S)


def parse_reference(name: str) -> Reference:
    """The :class:`Reference` a name stands for: ``kind`` is one of :data:`REFERENCE_POLICIES`
    but ``best_scripted`` (a blend), ``radii`` the blend's (None for the bare ``blend``, whose
    radius the caller gives, and for the others). See the module docstring for the syntax."""
    if name == "best_scripted":
        return Reference("blend", BEST_SCRIPTED)
    if name in REFERENCE_POLICIES:
        return Reference(name)
    call = _CALL.fullmatch(name.strip()) if isinstance(name, str) else None
    if call is None:
        raise ValueError(
            f"unknown reference policy {name!r}; choose from {REFERENCE_POLICIES} or "
            "blend(defend=R, collect=R, deliver=R)"
        )
    args = [a.strip() for a in call.group(1).split(",")]
    follow = "follower"
    if args and args[-1].replace(" ", "").startswith("follow="):
        follow = args.pop().partition("=")[2].strip()
        if follow not in FOLLOWS:
            raise ValueError(
                f"reference {name!r}: follow must be one of {', '.join(FOLLOWS)}, got {follow!r}"
            )
    if args in ([""], []):
        raise ValueError(f"reference {name!r} gives no radius: blend(R) or blend(role=R, ...)")
    if len(args) == 1 and "=" not in args[0]:  # blend(R): every role
        return Reference(
            "blend", role_radii(_radius(args[0], f"reference {name!r}: radius")), follow
        )
    radii = {}
    for arg in args:
        role, eq, value = (part.strip() for part in arg.partition("="))
        if not eq:
            raise ValueError(f"reference {name!r}: {arg!r} is not role=radius")
        if role not in ROLES:
            raise ValueError(
                f"reference {name!r}: unknown role {role!r}; roles are {', '.join(ROLES)}"
            )
        if role in radii:
            raise ValueError(f"reference {name!r}: role {role!r} is given twice")
        radii[role] = _radius(value, f"reference {name!r}: radius {role!r}")
    return Reference("blend", RoleRadii(**radii), follow)


def _radii_text(radii: RoleRadii) -> str:
    if len(set(radii)) == 1:
        return f"r={radii[0]:g} m"
    return ", ".join(f"{role}={r:g}" for role, r in radii._asdict().items()) + " m"


def reference_label(name: str, radius: float = BEST_BLEND_RADIUS) -> str:
    """The row label of a reference policy in tables and figures (``radius``: the bare blend's)."""
    kind, radii, follow = parse_reference(name)
    if kind != "blend":
        return name
    text = _radii_text(radii if radii is not None else role_radii(radius))
    if name == "best_scripted":
        return f"{BEST_SCRIPTED_LABEL} ({text})"
    return f"blend ({text}{'' if follow == 'follower' else f'; follow={follow}'})"


def reference_key(label: str) -> str | None:
    """The results.json key of a reference's row label (:func:`reference_label`): its name, or
    for a role blend its canonical name; None for a label no reference writes."""
    if label in REFERENCE_POLICIES:
        return label
    if label.startswith(BEST_SCRIPTED_LABEL + " ("):
        return "best_scripted"
    head, sep, follow = label.rpartition("; follow=")
    if sep and label.startswith("blend (") and follow[:-1] in FOLLOWS and follow.endswith(")"):
        radii = head[len("blend (") :].removesuffix(" m").removeprefix("r=")
        return f"blend({radii}, follow={follow[:-1]})"
    if label.startswith("blend (r="):
        return "blend"
    if label.startswith("blend (") and label.endswith(" m)"):
        return f"blend({label[len('blend (') : -len(' m)')]})"
    return None


def make_reference_policy(
    name: str, env, *, radius: float | None = None, seed: int = 0
) -> ReferencePolicy:
    """A reference policy by name (:func:`parse_reference`); ``radius`` is the bare ``blend``'s."""
    kind, radii, follow = parse_reference(name)
    if kind == "random":
        return RandomPolicy(env, seed=seed)
    if kind == "follower":
        return FollowerPolicy(env)
    if kind == "pursuit":
        return PursuitPolicy(env)
    if kind == "heuristic":
        return HeuristicPolicy(env)
    if radii is None and radius is None:
        raise ValueError("the blend reference policy needs radius=... (metres)")
    return BlendPolicy(env, radii if radii is not None else radius, follow)
