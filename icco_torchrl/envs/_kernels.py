"""Pure tensor kernels of :class:`~icco_torchrl.envs.ResourceCollectionEnv`.

All tensors are *batch-last*: the env index is the last dimension (robot positions are
``[N, 2, B]``, x and y on dim -2), so every elementwise op runs over contiguous rows of
length ``B``. On CPU that is 5-20x faster per element than the ``[B, N, 2]`` layout, whose
innermost loop has 2 elements.

:func:`dynamics` is one env step without its random draws: no data-dependent shapes and no
random numbers (respawns are drawn afterwards by the env, only where needed).

``torch.compile`` was tried on these (torch 2.13, CPU inductor, one thread) and not kept: the
float math (:func:`motion`) gets ~4x faster, but kernels that produce bool/uint8 masks or
reduce over a middle dimension come out 5-10x slower than eager, so a compiled step was
1.0-1.2x the eager one, for ~7 s of compilation per ``num_envs``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch


# ---------------------------------------------------------------- layout and small helpers
def batch_last(x: torch.Tensor) -> torch.Tensor:
    """``[B, *rest]`` -> contiguous ``[*rest, B]`` (one 2-D transpose, the fast copy kernel)."""
    return x.reshape(x.shape[0], -1).t().contiguous().view(*x.shape[1:], x.shape[0])


def batch_first(x: torch.Tensor) -> torch.Tensor:
    """``[*rest, B]`` -> contiguous ``[B, *rest]``."""
    return x.reshape(-1, x.shape[-1]).t().contiguous().view(x.shape[-1], *x.shape[:-1])


def any_(mask: torch.Tensor, dim: int) -> torch.Tensor:
    """``mask.any(dim)``; a max over uint8 is ~10x faster than the bool reduction on CPU."""
    return mask.view(torch.uint8).amax(dim).view(torch.bool)


def sq_norm(p: torch.Tensor) -> torch.Tensor:
    """Squared length of vectors with x, y on dim -2."""
    x, y = p.select(-2, 0), p.select(-2, 1)
    return (x * x).add_(y * y)


def sq_dist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared distances between points with x, y on dim -2, broadcasting ``a`` against ``b``."""
    dx = a.select(-2, 0) - b.select(-2, 0)
    dy = a.select(-2, 1) - b.select(-2, 1)
    return dx.mul_(dx).add_(dy.mul_(dy))


def pair_sq_dist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared distances ``[Na, Nb, B]`` between points ``a`` [Na, 2, B] and ``b`` [Nb, 2, B]."""
    return sq_dist(b.unsqueeze(0), a.unsqueeze(1))


def first(mask: torch.Tensor, dim: int) -> torch.Tensor:
    """Keep only the first True along ``dim`` (a cumsum or argmax there is several times slower)."""
    size = mask.shape[dim]
    small = size < 255
    rank = torch.arange(
        size, 0, -1, dtype=torch.uint8 if small else torch.int32, device=mask.device
    )
    rank = rank.view([size] + [1] * (mask.dim() - dim - 1))
    score = (
        mask.view(torch.uint8) if small else mask.int()
    ) * rank  # size - index where True, else 0
    return mask & (score == score.amax(dim, keepdim=True))


def assign(contact: torch.Tensor) -> torch.Tensor:
    """Resolve contacts ``[N, M, B]`` into at most one item per robot and one robot per item.

    Each robot claims the lowest-index item it touches; a claimed item goes to the lowest-index
    claimant (the loser gets nothing this step).
    """
    return first(first(contact, 1), 0)


# ---------------------------------------------------------------- one step
class Params(NamedTuple):
    """The constants :func:`dynamics` needs (squared radii: contacts compare squared distances)."""

    damping: float
    max_speed: float
    dt: float
    wall: float  # robots' centres stay within [-wall, wall]
    invader_speed: float
    touch_invader2: float  # (agent_radius + invader_radius) ** 2
    touch_resource2: float  # (agent_radius + resource_radius) ** 2
    invader_home2: float  # (home_radius + invader_radius) ** 2
    robot_home2: float  # (home_radius + agent_radius) ** 2
    inst_scale: float
    inst_dist_coef: float
    inst_hold: float  # 0: off; else 1 / (max_speed * dt): a route's end rewards holding still
    pick: float
    collect: float
    defense: float
    invasion_share: float  # -invasion_penalty / n_agents (every robot present)
    invasion: float  # -invasion_penalty (shared by the present robots of a partial team)


class Dynamics(NamedTuple):
    """Everything one step decides before its random respawns (batch-last)."""

    pos: torch.Tensor  # [N, 2, B]
    vel: torch.Tensor  # [N, 2, B]
    carry: torch.Tensor  # [N, B]
    defense: torch.Tensor  # [N, B]
    inv: torch.Tensor  # [I, 2, B] moved; respawning invaders still to be placed
    inv_vel: torch.Tensor  # [I, 2, B]
    inv_on: torch.Tensor  # [I, B] active and not removed this step (respawns still to add)
    gone: torch.Tensor  # [I, B] removed this step: needs a new respawn timer
    respawn: torch.Tensor  # [I, B] inactive invaders whose timer ran out: need an edge point
    timer: torch.Tensor  # [I, B] respawn timers (entries of `gone` still to draw)
    picked: torch.Tensor  # [R, B] resources picked this step: need a new position
    agent_reward: torch.Tensor  # [N, B]
    r_inst: torch.Tensor  # [N, B]
    counts: torch.Tensor  # [4, B] picks, collects, defenses, invasions


def dynamics(
    pos, vel, carry, res, inv, inv_on, timer, wp, action, action_force, p: Params, present=None
) -> Dynamics:
    """One step of robots, invaders and events (see the env's docstring for the rules).

    ``wp`` [N, K, 2, B] are the waypoints, ``action`` [B, N] indices into ``action_force`` [5, 2].
    ``present`` [N, B] (None: every robot) masks the absent robots out of everything: they do
    not move (their action is ignored, their velocity is zero), touch nothing, earn nothing, and
    the invasion penalty is shared by the present robots only. None runs the full-team ops alone,
    so a full team's numbers are those of a build without team sizes, bit for bit.
    """
    if present is not None:
        action = action.masked_fill(~present.t(), 0)
    new_pos, new_vel, r_inst, inv, inv_vel = motion(
        pos, vel, inv, inv_on, wp, action, action_force, p
    )
    if present is not None:
        new_pos = torch.where(present.unsqueeze(1), new_pos, pos)
        new_vel = new_vel.masked_fill(~present.unsqueeze(1), 0.0)
        r_inst = r_inst.masked_fill(~present, 0.0)
        live = present.unsqueeze(1)  # [N, 1, B]: only present robots touch anything

    # Events; one per robot per step, defense > pick > collect, ties to the lower index.
    touch = (pair_sq_dist(new_pos, inv) < p.touch_invader2) & inv_on
    hit = assign(touch if present is None else touch & live)  # [N, I, B]
    defense = any_(hit, 1)
    removed = any_(hit, 0)
    invaded = inv_on & ~removed & (sq_norm(inv) < p.invader_home2)
    gone = removed | invaded
    timer = timer - (~inv_on).long()
    respawn = ~inv_on & ~gone & (timer <= 0)
    touch = (pair_sq_dist(new_pos, res) < p.touch_resource2) & ~(carry | defense).unsqueeze(1)
    took = assign(touch if present is None else touch & live)  # [N, R, B]
    pick = any_(took, 1)
    collect = carry & ~defense & (sq_norm(new_pos) < p.robot_home2)
    if present is not None:
        collect = collect & present

    n_invasion = invaded.sum(0)
    if present is None:
        share = p.invasion_share * n_invasion.float()
    else:  # per env: the penalty split among its present robots, nothing for the absent ones
        share = (p.invasion * n_invasion.float() / present.sum(0).clamp_min(1)) * present
    agent_reward = (
        (p.pick * pick + p.collect * collect + p.defense * defense).float() + share + r_inst
    )
    counts = torch.cat([torch.stack([pick, collect, defense]).sum(1), n_invasion.unsqueeze(0)])
    return Dynamics(
        pos=new_pos,
        vel=new_vel,
        carry=(carry & ~collect) | pick,
        defense=defense,
        inv=inv,
        inv_vel=inv_vel,
        inv_on=inv_on & ~gone,
        gone=gone,
        respawn=respawn,
        timer=timer,
        picked=any_(took, 0),
        agent_reward=agent_reward,
        r_inst=r_inst,
        counts=counts,
    )


def motion(pos, vel, inv, inv_on, wp, action, action_force, p: Params):
    """Robots and invaders move; the instruction reward of the robots' moves. Float math only."""
    N, B = pos.shape[0], pos.shape[-1]
    # Robots: damped point masses with a speed cap, kept inside the field.
    force = action_force.index_select(0, action.reshape(-1)).view(B, 2 * N).t().view(N, 2, B)
    new_vel = vel * p.damping + force
    speed = sq_norm(new_vel).sqrt_().unsqueeze(1)
    new_vel = new_vel * (p.max_speed / speed.clamp_min_(p.max_speed))
    raw = pos + p.dt * new_vel
    new_pos = raw.clamp(-p.wall, p.wall)
    new_vel = new_vel.masked_fill_(new_pos != raw, 0.0)  # a wall stops that axis
    r_inst = instruction_reward(wp, pos, new_pos, p.inst_scale, p.inst_dist_coef, p.inst_hold)
    # Invaders walk straight home.
    dist_home = sq_norm(inv).sqrt_().unsqueeze(1)
    move = -inv * (p.invader_speed / dist_home.clamp_min_(p.invader_speed))
    move = torch.where(inv_on.unsqueeze(1), move, 0.0)
    return new_pos, new_vel, r_inst, inv + move, move / p.dt  # velocity in m/s, like the robots'


def instruction_reward(
    wp, old_pos, new_pos, scale: float, dist_coef: float, hold: float = 0.0
) -> torch.Tensor:
    """``r_inst = scale * (e_dir + dist_coef * e_dist)`` per robot, [N, B].

    The path direction is the vector from the waypoint nearest to the robot (before the move) to
    the second-nearest one. e_dir is the cosine between this step's displacement and it
    (the paper's e_cossim); 0 when either vector is zero. With ``hold``
    (``1 / (max_speed * dt)``), a zero path direction (the two nearest waypoints coincide: a served
    route's end, its slot) scores ``1 - hold * |displacement|`` (at least 0) instead: holding the
    slot earns what following earned, where otherwise arriving would end the reward. e_dist:
    minus the distance from the new position to its nearest waypoint.
    """
    d_old = sq_dist(wp, old_pos.unsqueeze(1))  # [N, K, B]
    nearest = first(d_old == d_old.amin(1, keepdim=True), 1)  # one-hot over K
    d_old.masked_fill_(nearest, float("inf"))
    second = first(d_old == d_old.amin(1, keepdim=True), 1)
    # wp[second] - wp[nearest] as a masked sum (exact: the other terms add zeros); ~2x faster
    # than min(dim).indices + gather over a middle dimension.
    path = (wp * (second.to(wp.dtype) - nearest.to(wp.dtype)).unsqueeze(2)).sum(1)  # [N, 2, B]
    disp = new_pos - old_pos
    along = (disp * path).sum(1)
    length = sq_norm(path).sqrt_()
    e_dir = along.div_(sq_norm(disp).sqrt_().mul_(length).clamp_min_(1e-8))
    if hold:
        still = sq_norm(disp).sqrt_().mul_(-hold).add_(1.0).clamp_min_(0.0)
        e_dir = torch.where(length == 0, still, e_dir)
    e_dist = sq_dist(wp, new_pos.unsqueeze(1)).amin(1).sqrt_().neg_()
    return scale * (e_dir + dist_coef * e_dist)
