"""The ICCO resource-collection task as a batched, pure-torch TorchRL environment.

Robots collect resources and bring them home while an invader walks toward home; a
human instruction is given as K waypoints per robot. Everything is vectorised over
``[num_envs, n_agents, ...]``: there is no Python loop over envs or agents in ``_step``.

Keys (``B = num_envs``, ``N = n_agents``, ``K = n_waypoints``)::

    ("agents", "observation")  [B, N, obs_dim]   own state, own waypoints, visible entities
    ("agents", "waypoints")    [B, N, K, 2]      instruction vectors (input and output)
    ("agents", "action")       [B, N]            0 no-op, 1 -x, 2 +x, 3 -y, 4 +y
    ("agents", "reward")       [B, N, 1]         each robot's own reward   (in "next")
    ("agents", "present")      [B, N, 1]  bool   which robots are in the team (see team_sizes)
    "state"                    [B, state_dim]    global state incl. everyone's waypoints
    "step_count"               [B, 1]            steps since reset (drives z and waypoint refresh)
    "reward"                   [B, 1]            team reward = sum of the robots' rewards
    "done" / "terminated" / "truncated"  [B, 1]  truncated at ``max_steps``, never terminated
    ("events", name)           [B]               this step's pick/collect/defense/invasion counts
                                                 and the summed instruction reward ``inst_reward``

Observation layout (per robot; see :class:`ObsLayout`): ``own`` = [x, y, vx, vy, carry,
waypoints relative to the robot (K*2)], then ``n_entities`` tokens of ``entity_dim`` features
[dx, dy, dvx, dvy, one-hot type (agent, resource, invader, home), flag, visible] (the
``ObsLayout.ENTITY_*`` columns); tokens outside ``vision_radius`` are all zeros. The global
state is ``N + R + I`` tokens of ``state_token_dim`` features [x, y, vx, vy, one-hot type
(agent, resource, invader), flag, defended, absolute waypoints (K*2, agents only)], each column
named by :class:`ObsLayout`.

Team sizes. ``n_agents`` is the most robots an env holds; ``present`` ``[B, N]`` says which are
in its team. With ``team_sizes`` each env draws its team size k at reset, uniformly from that
list, and robots ``0..k-1`` are present; :meth:`remove_robot` and :meth:`add_robot` change a team
mid-episode. An absent robot is masked out of everything: its own observation row is all zeros,
it is invisible to the others (its entity token is zero, visible flag 0, as for a robot out of
range), its **state token is all zeros, its type flags included**, so a network reads the
robot mask from the state with :meth:`ObsLayout.robot_mask` (a contract); its action and waypoints
are ignored (it does not move), it picks, delivers and defends nothing, its reward is 0 and the
event counters and the team reward leave it out (the invasion penalty is shared by the present
robots). Its ``pos`` is where it was left and means nothing.

Performance notes. On CPU an elementwise op whose innermost dimension is tiny (the ``2`` of
``[B, N, 2]``) or broadcast runs 5-20x slower per element than one over a long contiguous
row. So the env keeps its state *batch-last* (robot positions are ``[N, 2, B]``) and does its
arithmetic on rows of length ``B``; the public attributes (``env.pos`` ``[B, N, 2]``, ...) are
views of that storage in the documented layout and may be written in place. Entity tokens are
mostly zeros (vision is short), so only the visible ones are computed and scattered into a
zeroed observation. Waypoints stay ``[B, N, K, 2]`` (their input/output layout) with a
batch-last copy that is refreshed only when they change. The step's arithmetic is in
:mod:`._kernels`. Random numbers are drawn only for what actually respawns (invader timers and
edge points, picked resources, refreshed waypoints, reset envs), so a run is reproducible
under a seed but its stream differs from versions that drew for every env at every step.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import numbers

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from icco_torchrl.envs._kernels import (
    Params,
    any_,
    batch_first,
    batch_last,
    dynamics,
    pair_sq_dist,
    sq_norm,
)
from icco_torchrl.envs.layout import ObsLayout
from icco_torchrl.envs.params import (
    ResourceCollectionParams,
    keyword_args_doc,
    positive,
)

N_ACTIONS = 5
# Unit force per action: no-op, -x, +x, -y, +y (COPA's order).
_ACTION_DIRS = ((0.0, 0.0), (-1.0, 0.0), (1.0, 0.0), (0.0, -1.0), (0.0, 1.0))
EVENTS = ("pick", "collect", "defense", "invasion")  # the counted events, under ("events", name)
EVENT_KEYS = (*EVENTS, "inst_reward")  # every ("events", ...) entry of a step
_FAR = 1e9  # where inactive invaders are "seen" from: beyond any vision radius


def check_team_sizes(team_sizes, n_agents: int) -> tuple[int, ...] | None:
    """``team_sizes`` as a tuple (None stays None), or a one-line ValueError naming the problem
    (the one check of team sizes: ``train.team_sizes`` goes through it too)."""
    if team_sizes is None:
        return None
    if isinstance(team_sizes, (str, bytes)) or not hasattr(team_sizes, "__iter__"):
        raise ValueError(f"team_sizes must be a list of team sizes or None, got {team_sizes!r}")
    sizes = tuple(team_sizes)
    if not sizes:
        raise ValueError("team_sizes must not be empty (None: every env holds n_agents robots)")
    for k in sizes:
        if not isinstance(k, int) or isinstance(k, bool) or not 1 <= k <= n_agents:
            raise ValueError(
                f"team_sizes entries must be integers in 1..n_agents={n_agents}, got {k!r}"
            )
    return sizes


def _is_index(value) -> bool:
    """An integer (Python or numpy), not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _state_property(name: str, doc: str) -> property:
    """Public ``[B, ...]`` view of the batch-last state tensor ``name`` (writable in place)."""

    def get(self):
        return getattr(self, name).movedim(-1, 0)

    def set(self, value):
        self._put(**{name: batch_last(torch.as_tensor(value, device=self.device))})

    return property(get, set, doc=doc)


class ResourceCollectionEnv(EnvBase):
    """Batched resource collection with language-instruction waypoints (ICCO, Sec. IV).

    Args:
        num_envs: number of independent envs stepped together (the batch size).
        device: torch device of every tensor the env holds and emits.
        seed: seed of the env's own random generator (``set_seed`` re-seeds it).
        team_sizes: team sizes to draw from at each reset, uniformly over the list (a size
            listed twice is drawn twice as often), each in ``1..n_agents``; robots ``0..k-1``
            are present. None (default): every env holds all ``n_agents`` robots and no random
            number is drawn for it, so the env is the fixed-team env, bit for bit.
        **params: the task's parameters, the fields of
            :class:`~icco_torchrl.envs.params.ResourceCollectionParams` (the Keyword Args below,
            generated from it): checked there, then read-only as ``env.params`` and as attributes
            (``env.dt``...).

    Absent robots (``present`` False; contract, see the module docstring): zero observation row,
    invisible in the others' observations, **all-zero state token, type flags included**, so
    networks read the robot mask with :meth:`ObsLayout.robot_mask`; action and waypoints
    ignored (it does not move); no pick, delivery, defense or instruction reward, reward 0, left
    out of the event counts and the team reward. :meth:`remove_robot` and :meth:`add_robot` change
    a team mid-episode.
    """

    batch_locked = True

    def __init__(
        self,
        num_envs: int = 1,
        device: str | torch.device = "cpu",
        seed: int | None = None,
        *,
        team_sizes: tuple[int, ...] | list[int] | None = None,
        **params,
    ):
        positive("num_envs", num_envs, integer=True)
        p = ResourceCollectionParams(**params)  # the checks, each error naming its field
        self.team_sizes = check_team_sizes(team_sizes, p.n_agents)
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.params, self.num_envs = p, num_envs
        self.half = p.field_size / 2
        self.event_rewards = dict(
            pick=p.pick_reward,
            collect=p.collect_reward,
            defense=p.defense_reward,
            invasion=-p.invasion_penalty,
        )
        self._kernel_params = p.kernel_params()  # the step's constants, derived once

        N, R, I, K = p.n_agents, p.n_resources, p.n_invaders, p.n_waypoints
        self.layout = ObsLayout.for_env(N, R, I, K)
        dev = self.device
        self._action_dirs = torch.tensor(_ACTION_DIRS, device=dev)
        # Entity table seen by robots: robots, resources, invaders, home.
        types = torch.cat(
            [torch.zeros(N), torch.ones(R), torch.full((I,), 2.0), torch.full((1,), 3.0)]
        ).long()
        self._entity_type = torch.nn.functional.one_hot(types, 4).float().to(dev)  # [E_all, 4]
        template, cols = self._state_layout()
        self._state_template, self._state_cols = template.to(dev), cols.to(dev)
        L = self.layout
        self._own_cols = (
            (torch.arange(N)[:, None] * L.obs_dim + torch.arange(L.own_dim)).view(-1).to(dev)
        )
        self._agents_batch = torch.Size([num_envs, N])
        if self.team_sizes is not None:
            self._team_size_table = torch.tensor(self.team_sizes, device=dev)
        self._rng = torch.Generator(device=dev)
        self._rng.manual_seed(
            int(seed)
            if seed is not None
            else int(torch.empty((), dtype=torch.int64).random_().item())
        )
        self._make_specs()
        self._alloc_state()

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        B, N, K, L = self.num_envs, self.n_agents, self.n_waypoints, self.layout
        dev = self.device
        events = Composite(
            {name: Unbounded((B,), dtype=torch.int64, device=dev) for name in EVENTS},
            inst_reward=Unbounded((B,), device=dev),
            shape=(B,),
            device=dev,
        )
        self.observation_spec = Composite(
            agents=Composite(
                observation=Unbounded((B, N, L.obs_dim), device=dev),
                waypoints=Bounded(-self.half, self.half, (B, N, K, 2), device=dev),
                present=Categorical(2, (B, N, 1), dtype=torch.bool, device=dev),
                shape=(B, N),
                device=dev,
            ),
            state=Unbounded((B, L.state_dim), device=dev),
            step_count=Bounded(0, self.max_steps, (B, 1), dtype=torch.int64, device=dev),
            events=events,
            shape=(B,),
            device=dev,
        )
        self.action_spec = Composite(
            agents=Composite(
                action=Categorical(N_ACTIONS, (B, N), dtype=torch.int64, device=dev),
                shape=(B, N),
                device=dev,
            ),
            shape=(B,),
            device=dev,
        )
        self.reward_spec = Composite(
            reward=Unbounded((B, 1), device=dev),
            agents=Composite(reward=Unbounded((B, N, 1), device=dev), shape=(B, N), device=dev),
            shape=(B,),
            device=dev,
        )
        flag = lambda: Categorical(2, (B, 1), dtype=torch.bool, device=dev)  # noqa: E731
        self.done_spec = Composite(
            done=flag(), terminated=flag(), truncated=flag(), shape=(B,), device=dev
        )

    # ------------------------------------------------------------------ state
    # Batch-last storage (see the module docstring); the public names are [B, ...] views.
    pos = _state_property("_pos", "Robot positions [B, N, 2].")
    vel = _state_property("_vel", "Robot velocities [B, N, 2].")
    carry = _state_property("_carry", "Whether each robot carries a resource [B, N].")
    defended = _state_property("_defended", "Whether each robot hit an invader this step [B, N].")
    res_pos = _state_property("_res", "Resource positions [B, R, 2].")
    inv_pos = _state_property("_inv", "Invader positions [B, I, 2].")
    inv_vel = _state_property("_inv_vel", "Invader velocities [B, I, 2].")
    inv_active = _state_property("_inv_on", "Whether each invader is on the field [B, I].")
    inv_timer = _state_property("_inv_timer", "Steps until an inactive invader respawns [B, I].")

    @property
    def waypoints(self) -> torch.Tensor:
        """Current instruction waypoints [B, N, K, 2] (writable in place)."""
        return self._wp

    @waypoints.setter
    def waypoints(self, value: torch.Tensor) -> None:
        self._put(_wp=torch.as_tensor(value, device=self.device))

    @property
    def present(self) -> torch.Tensor:
        """Which robots are in each env's team, bool ``[B, N]`` on the env's device (a copy:
        change a team with :meth:`add_robot` and :meth:`remove_robot`)."""
        return self._present.t().clone()

    def _set_present(self, present: torch.Tensor, all_present: bool | None = None) -> None:
        """Store the batch-last team mask [N, B], its emitted form [B, N, 1] and whether every
        robot of every env is present (the step takes the full-team path then)."""
        if all_present is None:
            all_present = bool(present.all())
        self._put(
            _present=present,
            _present_bf=batch_first(present).unsqueeze(-1),
            _all_present=all_present,
        )

    def _put(self, **state: torch.Tensor) -> None:
        # Plain instance attributes: nn.Module.__setattr__ costs ~10 us a call, paid per step.
        self.__dict__.update(state)

    def _alloc_state(self) -> None:
        B, N, R, I, K, dev = (
            self.num_envs,
            self.n_agents,
            self.n_resources,
            self.n_invaders,
            self.n_waypoints,
            self.device,
        )
        self._put(
            _pos=torch.zeros(N, 2, B, device=dev),
            _vel=torch.zeros(N, 2, B, device=dev),
            _carry=torch.zeros(N, B, dtype=torch.bool, device=dev),
            _defended=torch.zeros(N, B, dtype=torch.bool, device=dev),
            _res=torch.zeros(R, 2, B, device=dev),
            _inv=torch.zeros(I, 2, B, device=dev),
            _inv_vel=torch.zeros(I, 2, B, device=dev),
            _inv_on=torch.zeros(I, B, dtype=torch.bool, device=dev),
            _inv_timer=torch.zeros(I, B, dtype=torch.int64, device=dev),
            _wp=torch.zeros(B, N, K, 2, device=dev),
            _wp_cache=(None, None, None),
            _wp_emitted=(None, None),
            _on_path=torch.zeros(
                N, 1, B, dtype=torch.bool, device=dev
            ),  # robots whose walk is a path
            _on_route=torch.zeros(N, 1, B, dtype=torch.bool, device=dev),  # ... a route to a slot
            _slot=torch.zeros(N, 2, B, device=dev),  # the slot of a robot on a route
            t=torch.zeros(B, dtype=torch.int64, device=dev),
        )
        self._set_present(torch.ones(N, B, dtype=torch.bool, device=dev), all_present=True)
        # Scratch entity table for _write_visible_entities: one-hot types and "visible" are fixed.
        L = self.layout
        table = torch.zeros(N + R + I + 1, L.entity_dim, B, device=dev)
        table[:, L.ENTITY_TYPE] = self._entity_type.unsqueeze(-1)
        table[:, L.ENTITY_VISIBLE] = 1.0
        self._put(_entity_table=table)

    def _waypoints_bl(self) -> torch.Tensor:
        """Batch-last copy ``[N, K, 2, B]`` of :attr:`waypoints`, redone only when they changed."""
        wp = self._wp
        cached_for, version, cache = self._wp_cache
        if cached_for is not wp or version != wp._version:
            cache = batch_last(wp)
            self._put(_wp_cache=(wp, wp._version, cache))
        return cache

    def _set_seed(self, seed: int | None):
        self._rng.manual_seed(
            int(seed)
            if seed is not None
            else int(torch.empty((), dtype=torch.int64).random_().item())
        )

    # ------------------------------------------------------------------ sampling
    # Random numbers are drawn only for what (re)spawns, so a quiet step draws none. The draws
    # are a deterministic function of the seed and the trajectory.
    def _rand(self, *shape) -> torch.Tensor:
        return torch.rand(*shape, generator=self._rng, device=self.device)

    def _randn(self, *shape) -> torch.Tensor:
        return torch.randn(*shape, generator=self._rng, device=self.device)

    def _respawn_timer(self, n: int) -> torch.Tensor:
        """``n`` waits U{1..invader_respawn_max} before an invader comes back."""
        return torch.randint(
            1, self.invader_respawn_max + 1, (n,), generator=self._rng, device=self.device
        )

    def _invader_points(self, n: int) -> torch.Tensor:
        """``n`` spawn points of invaders [n, 2]: see ``spawn`` in the class docstring."""
        if self.spawn == "copa":
            return self._edge_points(n)
        # Uniform in the field outside the disc of radius invader_min_radius: rejection
        # sampling, vectorised (a few rounds; each keeps the points that fell outside).
        out = torch.empty(n, 2, device=self.device)
        todo = torch.arange(n, device=self.device)
        while todo.numel():
            cand = (self._rand(todo.numel(), 2) * 2 - 1) * self.half
            ok = cand.square().sum(-1) >= self.invader_min_radius**2
            out[todo[ok]] = cand[ok]
            todo = todo[~ok]
        return out

    def _edge_points(self, n: int) -> torch.Tensor:
        """``n`` uniform points on the field's boundary (where invaders appear), [n, 2]."""
        side = torch.randint(0, 4, (n,), generator=self._rng, device=self.device)
        along = (self._rand(n) * 2 - 1) * self.half
        fixed = torch.where(side % 2 == 0, -self.half, self.half)
        vertical = side < 2  # sides 0, 1: x fixed; sides 2, 3: y fixed
        return torch.stack(
            [torch.where(vertical, fixed, along), torch.where(vertical, along, fixed)], -1
        )

    def _resource_candidates(self, n: int, n_candidates: int = 8) -> torch.Tensor:
        """``n`` sets of candidate spawn points [n, C, 2]: uniform in the field outside home
        (``spawn="uniform"``) or on the annulus [resource_min_radius, edge] (``"copa"``)."""
        if self.spawn == "uniform":
            lim = self.half - self.resource_radius
            cand = (self._rand(n, n_candidates, 2) * 2 - 1) * lim
            # A candidate on home is moved out radially to its rim (probability ~0.6 %).
            clear = self.home_radius + self.resource_radius
            norm = cand.norm(dim=-1, keepdim=True)
            return torch.where(norm < clear, cand / norm.clamp_min(1e-6) * clear, cand)
        r = self.resource_min_radius + self._rand(n, n_candidates) * (
            self.half - self.resource_min_radius
        )
        angle = self._rand(n, n_candidates) * (2 * math.pi)
        return torch.stack([r * torch.cos(angle), r * torch.sin(angle)], -1)

    def _spawn_resources(self, res_pos: torch.Tensor, respawn: torch.Tensor) -> torch.Tensor:
        """New positions ``[M, R, 2]`` for the slots in ``respawn`` [M, R], avoiding every other
        resource.

        Each slot draws a few candidates and keeps the first that overlaps no resource already
        in place. Slots respawning in the same env are placed in rounds (the k-th of each env in
        round k), so they avoid each other too; a round is vectorised over envs and there are as
        many rounds as the most simultaneous respawns in one env (usually one).
        """
        if not bool(respawn.any()):
            return res_pos
        rank = respawn.long().cumsum(-1) - 1  # k-th respawn of its env
        pending = respawn
        for k in range(int(rank.masked_fill(~respawn, 0).max()) + 1):
            now = pending & (rank == k)
            env, slot = now.nonzero(as_tuple=True)
            cand = self._resource_candidates(env.numel())  # [P, C, 2]
            d2 = (cand.unsqueeze(2) - res_pos[env].unsqueeze(1)).square().sum(-1)  # [P, C, R]
            blocking = (~pending[env]).unsqueeze(1) & (d2 < (2 * self.resource_radius) ** 2)
            first = (~any_(blocking, -1)).to(torch.uint8).argmax(-1)  # first free or 0
            chosen = cand[torch.arange(env.numel(), device=self.device), first]  # [P, 2]
            res_pos = res_pos.index_put((env, slot), chosen)
            pending = pending & ~now
        return res_pos

    def _random_walk(self, start: torch.Tensor) -> torch.Tensor:
        """K waypoints ``p + cumsum(eps)``, eps ~ N(0, sigma^2 I), clipped to the field.

        ``start`` is batch-last ``[N, 2, M]``; returns ``[M, N, K, 2]``.
        """
        M = start.shape[-1]
        steps = batch_last(self._randn(M, self.n_agents, self.n_waypoints, 2)) * self.waypoint_sigma
        return batch_first((start.unsqueeze(1) + steps.cumsum(1)).clamp(-self.half, self.half))

    # ------------------------------------------------------------------ reset
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        B, N, R, I = self.num_envs, self.n_agents, self.n_resources, self.n_invaders
        dev = self.device
        ids = None  # the envs to reset (None: all); only they draw random numbers
        if tensordict is not None and "_reset" in tensordict.keys():
            ids = tensordict.get("_reset").reshape(B).nonzero().squeeze(-1)
        M = B if ids is None else ids.numel()
        lim = self.half - self.agent_radius
        pos = (self._rand(M, N, 2) * 2 - 1) * lim
        res_pos = self._spawn_resources(
            torch.zeros(M, R, 2, device=dev), torch.ones(M, R, dtype=torch.bool, device=dev)
        )
        pos_bl = batch_last(pos)
        fresh = dict(  # batch-last, in the order the random numbers are drawn
            _pos=pos_bl,
            _vel=torch.zeros_like(pos_bl),
            _carry=torch.zeros(N, M, dtype=torch.bool, device=dev),
            _defended=torch.zeros(N, M, dtype=torch.bool, device=dev),
            _res=batch_last(res_pos),
            _inv=batch_last(self._invader_points(M * I).view(M, I, 2)),
            _inv_vel=torch.zeros(I, 2, M, device=dev),
            # uniform: the invader is on the field from the first step; copa: it appears later.
            _inv_on=torch.full((I, M), self.spawn == "uniform", dtype=torch.bool, device=dev),
            _inv_timer=self._respawn_timer(M * I).view(M, I).t().contiguous(),
        )
        if self.waypoint_mode == "random_walk":
            start = pos_bl
            if (
                self.waypoint_path_prob > 0
            ):  # drawn last and only then: the paper's episodes stay the same
                fresh["_on_path"] = batch_last(self._rand(M, N, 1) < self.waypoint_path_prob)
                start = torch.where(
                    fresh["_on_path"], batch_last((self._rand(M, N, 2) * 2 - 1) * self.half), pos_bl
                )
            wp = self._random_walk(start)
            if self.waypoint_route_prob > 0:  # drawn after the paths', and only then
                fresh["_on_route"] = batch_last(self._rand(M, N, 1) < self.waypoint_route_prob)
                fresh["_slot"] = batch_last((self._rand(M, N, 2) * 2 - 1) * lim)
                wp = self._serve_routes(wp, pos_bl, fresh["_slot"], fresh["_on_route"])
        else:
            wp = pos.unsqueeze(-2).expand(M, N, self.n_waypoints, 2).clone()
        present = None  # the team: drawn last and only with team_sizes (a full team draws nothing)
        if self.team_sizes is not None:
            pick = torch.randint(
                0, len(self.team_sizes), (M,), generator=self._rng, device=self.device
            )
            present = torch.arange(N, device=dev).unsqueeze(1) < self._team_size_table[pick]
        t = torch.zeros(M, dtype=torch.int64, device=dev)
        if ids is None:
            self._put(**fresh, _wp=wp, t=t)
        else:  # batch-last state: envs on the last dim; waypoints and t: on the first
            self._put(
                **{
                    name: getattr(self, name).index_copy(-1, ids, value)
                    for name, value in fresh.items()
                },
                _wp=self._wp.index_copy(0, ids, wp),
                t=self.t.index_copy(0, ids, t),
            )
        if present is not None:
            self._set_present(
                present if ids is None else self._present.index_copy(-1, ids, present)
            )
        elif ids is None:
            self._set_present(torch.ones(N, B, dtype=torch.bool, device=dev), all_present=True)
        elif not self._all_present:  # a full team again in the reset envs
            self._set_present(
                self._present.index_copy(-1, ids, torch.ones_like(self._present[:, ids]))
            )
        zeros = torch.zeros(B, dtype=torch.int64, device=dev)
        false = torch.zeros(B, 1, dtype=torch.bool, device=dev)
        return self._output(
            events={**{k: zeros for k in EVENTS}, "inst_reward": torch.zeros(B, device=dev)},
            done=false,
            terminated=false,
            truncated=false,
        )

    # ------------------------------------------------------------------ step
    def _read_action(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The action as ``[B, N]`` indices, checked when ``validate``."""
        action = tensordict.get(("agents", "action"))
        if action.shape != (
            self.num_envs,
            self.n_agents,
        ):  # one-hot or trailing dim: take the index
            action = (
                action.argmax(-1)
                if action.shape[-1] == N_ACTIONS and action.dim() == 3
                else action.reshape(self.num_envs, self.n_agents)
            )
        if self.validate:
            lo, hi = torch.aminmax(action)
            if lo < 0 or hi >= N_ACTIONS:
                raise ValueError(
                    f"('agents', 'action') must be in [0, {N_ACTIONS - 1}], got {action.tolist()}"
                )
        return action

    def _read_waypoints(self, tensordict: TensorDictBase) -> None:
        wp = tensordict.get(("agents", "waypoints"), None)
        if wp is None:
            return
        emitted, version = self._wp_emitted
        if wp is emitted and wp._version == version:
            return  # the very tensor this env emitted, untouched: already checked and stored
        self._put(_wp=self._check_waypoints(wp))

    def _check_waypoints(self, wp: torch.Tensor) -> torch.Tensor:
        expected = (self.num_envs, self.n_agents, self.n_waypoints, 2)
        if tuple(wp.shape) != expected:
            raise ValueError(
                f"('agents', 'waypoints') must have shape {list(expected)}, got {list(wp.shape)}"
            )
        wp = wp.to(self.device, torch.float32)
        if self.validate and not torch.isfinite(wp).view(torch.uint8).all():
            raise ValueError("('agents', 'waypoints') contains non-finite values")
        return wp.clamp(-self.half, self.half)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = self._read_action(tensordict)
        self._read_waypoints(tensordict)
        d = dynamics(
            self._pos,
            self._vel,
            self._carry,
            self._res,
            self._inv,
            self._inv_on,
            self._inv_timer,
            self._waypoints_bl(),
            action,
            (self.dt * self.accel) * self._action_dirs,
            self._params(),
            None if self._all_present else self._present,
        )
        # Respawns draw from the env's generator, so they happen here, only where needed.
        timer, inv, on = d.timer, d.inv, d.inv_on
        n_gone = int(d.gone.sum())
        if n_gone:
            timer.masked_scatter_(d.gone, self._respawn_timer(n_gone))
        which, env = d.respawn.nonzero(as_tuple=True)
        if env.numel():
            inv[which, :, env] = self._invader_points(env.numel())
            on = on | d.respawn
        self._put(
            _pos=d.pos,
            _vel=d.vel,
            _carry=d.carry,
            _defended=d.defense,
            _res=self._respawn_picked(d.picked),
            _inv=inv,
            _inv_vel=d.inv_vel,
            _inv_on=on,
            _inv_timer=timer,
            t=self.t + 1,
        )
        if self.waypoint_mode == "random_walk":
            self._refresh_waypoints((self.t % self.waypoint_interval == 0).nonzero().squeeze(-1))

        truncated = (self.t >= self.max_steps).unsqueeze(-1)
        return self._output(
            agent_reward=d.agent_reward,
            reward=d.agent_reward.sum(0).unsqueeze(-1),
            events=dict(zip(EVENTS, d.counts), inst_reward=d.r_inst.sum(0)),
            done=truncated,
            terminated=torch.zeros_like(truncated),
            truncated=truncated,
        )

    def _params(self) -> Params:
        """The constants of :func:`dynamics` (:meth:`ResourceCollectionParams.kernel_params`,
        derived once from :attr:`params`)."""
        return self._kernel_params

    def _refresh_waypoints(self, ids: torch.Tensor) -> None:
        """New random-walk waypoints for the envs ``ids``: from the robots' positions, or for a
        robot on a path (``waypoint_path_prob``), from its walk's last waypoint."""
        start = self._pos
        if self.waypoint_path_prob > 0:
            start = torch.where(self._on_path, batch_last(self._wp[:, :, -1]), start)
        if ids.numel() == self.num_envs:
            wp = self._random_walk(start)
            if self.waypoint_route_prob > 0:
                wp = self._serve_routes(wp, self._pos, self._slot, self._on_route)
            self._put(_wp=wp)
        elif ids.numel():
            wp = self._random_walk(start[..., ids])
            if self.waypoint_route_prob > 0:
                pick = lambda x: x[..., ids]  # noqa: E731
                wp = self._serve_routes(wp, pick(self._pos), pick(self._slot), pick(self._on_route))
            self._put(_wp=self._wp.index_copy(0, ids, wp))

    def _serve_routes(self, walk, pos, slot, on_route) -> torch.Tensor:
        """``walk`` ``[M, N, K, 2]`` with the robots ``on_route`` ``[N, 1, M]`` given their route
        served instead (``waypoint_route_prob``): K waypoints from ``pos`` ``[N, 2, M]`` straight
        to ``slot``, ``waypoint_route_step`` metres apart, stopping on the slot. This is
        :func:`~icco_torchrl.envs.routes.serve_routes` for a straight route, batch-last."""
        gap = slot - pos
        dist = sq_norm(gap).sqrt_()  # [N, M]
        k = torch.arange(1, self.n_waypoints + 1, device=pos.device, dtype=pos.dtype)
        along = torch.minimum((k * self.waypoint_route_step).view(1, -1, 1), dist.unsqueeze(1))
        unit = gap / dist.clamp_min(1e-12).unsqueeze(1)  # [N, 2, M]
        route = batch_first(pos.unsqueeze(1) + along.unsqueeze(2) * unit.unsqueeze(1))
        return torch.where(batch_first(on_route).unsqueeze(-1), route, walk)

    def _respawn_picked(self, picked: torch.Tensor) -> torch.Tensor:
        """Resource positions after respawning the ``picked`` [R, B] ones (envs with a pick)."""
        res = self._res
        rows = any_(picked, 0).nonzero().squeeze(-1)
        if not rows.numel():
            return res
        new = self._spawn_resources(
            res[:, :, rows].permute(2, 0, 1), picked[:, rows].t()
        )  # [M, R, 2]
        return res.index_copy(2, rows, new.permute(1, 2, 0))

    # ------------------------------------------------------------------ observations
    def _output(
        self,
        agent_reward: torch.Tensor | None = None,
        events: dict | None = None,
        **root,
    ) -> TensorDictBase:
        """The TensorDict ``_reset``/``_step`` return: observation, state and ``root`` entries."""
        obs, state = self._observe()
        wp = self._wp.clone()  # the emitted copy; _read_waypoints recognises it next step
        self._put(_wp_emitted=(wp, wp._version))
        agents = {"observation": obs, "waypoints": wp, "present": self._present_bf.clone()}
        if agent_reward is not None:
            agents["reward"] = batch_first(agent_reward).unsqueeze(-1)
        return self._td(
            {
                "agents": self._td(agents, self._agents_batch),
                "state": state,
                "step_count": self.t.unsqueeze(-1),
                "events": self._td(events, self.batch_size),
                **root,
            },
            self.batch_size,
        )

    def _td(self, source: dict, batch_size: torch.Size) -> TensorDictBase:
        # Skips the per-entry checks of TensorDict(...) (~50 us a step): every entry is built
        # here on self.device with the batch dims of its spec.
        return TensorDict._new_unsafe(source, batch_size=batch_size, device=self.device)

    def _observe(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-robot observations [B, N, obs_dim] and the global state [B, state_dim].

        Both are built batch-first from batch-last rows with ``index_copy_`` along dim 1: it
        reads each source row contiguously: 1.3-2x faster than a transpose + strided copy or gather.
        """
        B, N, L = self.num_envs, self.n_agents, self.layout
        pos, vel, carry = self._pos, self._vel, self._carry.float()
        wp = self._waypoints_bl()
        # Own features [N, own_dim, B] into the zeroed observation; then the visible entities.
        own = torch.cat([pos, vel, carry.unsqueeze(1), (wp - pos.unsqueeze(1)).flatten(1, 2)], 1)
        if not self._all_present:  # an absent robot observes nothing
            own = own * self._present.unsqueeze(1)
        obs = torch.zeros(B, N * L.obs_dim, device=self.device)
        obs.index_copy_(1, self._own_cols, own.reshape(N * L.own_dim, B).t())
        obs = obs.view(B, N, L.obs_dim)
        self._write_visible_entities(obs[..., L.own_dim :].view(B, N, L.n_entities, L.entity_dim))

        # Global state: the constant entries (types, zeros) from a template, then every varying
        # entry from one batch-last table of them, each row to its column.
        on = self._inv_on.float()
        src = torch.cat(
            [
                pos.flatten(0, 1),
                vel.flatten(0, 1),
                carry,
                self._defended.float(),
                wp.flatten(0, 2),
                self._res.flatten(0, 1),
                (self._inv * on.unsqueeze(1)).flatten(0, 1),
                (self._inv_vel * on.unsqueeze(1)).flatten(0, 1),
                on,
            ],
            0,
        )  # [S, B]
        state = self._state_template.expand(B, -1).clone()
        state.index_copy_(1, self._state_cols, src.t())
        if not self._all_present:  # an absent robot's token is all zeros, its type flag included
            robots = state.view(B, L.state_tokens, L.state_token_dim)[:, :N]
            robots.mul_(self._present_bf)
        return obs, state

    def _write_visible_entities(self, ent: torch.Tensor) -> None:
        """Fill the tokens [B, N, E, entity_dim] of the entities each robot sees (the rest stay
        zero), column by column as :class:`ObsLayout` names them."""
        N, R, I, L = self.n_agents, self.n_resources, self.n_invaders, self.layout
        POS, VEL, FLAG = L.ENTITY_POSITION, L.ENTITY_VELOCITY, L.ENTITY_FLAG
        MOTION = slice(POS.start, VEL.stop)  # adjacent columns: position, velocity
        on = self._inv_on
        # Every entity as a full token, batch-last [E_all, entity_dim, B]; only the moving parts
        # are rewritten (types, the visible flag and zeros stay). Inactive invaders are put far
        # away.
        table, inv = self._entity_table, slice(N + R, N + R + I)
        table[:N, POS], table[:N, VEL], table[:N, FLAG] = self._pos, self._vel, self._carry
        table[N : N + R, POS] = self._res
        table[inv, POS] = torch.where(on.unsqueeze(1), self._inv, _FAR)
        table[inv, VEL], table[inv, FLAG] = self._inv_vel, on
        visible = pair_sq_dist(self._pos, table[:, POS]) <= self.vision_radius**2  # [N, E_all, B]
        visible[:, :N].diagonal(0, 0, 1).fill_(False)  # a robot is not its own entity
        if not self._all_present:  # absent robots see nothing and nobody sees them
            visible &= self._present.unsqueeze(1)
            visible[:, :N] &= self._present.unsqueeze(0)
        flat = (
            visible.reshape(-1).nonzero().squeeze(1)
        )  # 1-D nonzero: ~2x faster than on [N, E_all, B]
        if not flat.numel():
            return
        E_all, B = visible.shape[1:]
        n, rest = flat.div(E_all * B, rounding_mode="floor"), flat % (E_all * B)
        j, b = rest.div(B, rounding_mode="floor"), rest % B
        tokens = table[j, :, b]  # [V, entity_dim]
        tokens[:, MOTION] -= table[n, MOTION, b]  # relative to the observing robot
        slot = j - (j > n).long()  # entity j's place in robot n's list (itself removed)
        ent.index_put_((b, n, slot), tokens)

    def _state_layout(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The state's constant template [state_dim] and, for each row of the table built by
        :meth:`_observe`, the state column it goes to [S]."""
        N, R, I, L = self.n_agents, self.n_resources, self.n_invaders, self.layout
        D = L.state_token_dim
        robot, res, inv = (lambda n: n * D), (lambda r: (N + r) * D), (lambda i: (N + R + i) * D)
        pos, vel, wp = (range(c.start, c.stop) for c in (L.POSITION, L.VELOCITY, L.waypoints))
        # Token features (ObsLayout): position, velocity, type, flag, defended, waypoints (2K).
        cols = [robot(n) + c for n in range(N) for c in pos] + [
            robot(n) + c for n in range(N) for c in vel
        ]
        cols += [robot(n) + L.FLAG for n in range(N)] + [
            robot(n) + L.DEFENDED for n in range(N)
        ]  # carry, defended
        cols += [robot(n) + c for n in range(N) for c in wp]  # waypoints
        cols += [res(r) + c for r in range(R) for c in pos]
        cols += [inv(i) + c for i in range(I) for c in pos] + [
            inv(i) + c for i in range(I) for c in vel
        ]
        cols += [inv(i) + L.FLAG for i in range(I)]  # active
        template = torch.zeros(L.state_tokens, D)
        template[:, L.TYPE] = self._entity_type[: L.state_tokens, :3].cpu()
        assert sorted(set(cols)) == sorted(cols) and not template.view(-1)[cols].any()
        return template.view(-1), torch.tensor(cols)

    # ------------------------------------------------------------------ instructions
    def write_waypoints(
        self, tensordict: TensorDictBase, waypoints: torch.Tensor
    ) -> TensorDictBase:
        """Give the robots new instruction waypoints ``[num_envs, n_agents, K, 2]`` now.

        Clips them to the field, stores them in the env and rewrites the observation and the
        state in ``tensordict`` (the current root td returned by reset/step_mdp), so the policy
        acts on them at this very step. With ``waypoint_mode="external"`` they are kept until
        the next call; in random-walk mode the env overwrites them at its next refresh.
        """
        self._put(_wp=self._check_waypoints(torch.as_tensor(waypoints, device=self.device)))
        obs, state = self._observe()
        wp = self._wp.clone()
        self._put(_wp_emitted=(wp, wp._version))
        tensordict.set(("agents", "observation"), obs)
        tensordict.set(("agents", "waypoints"), wp)
        tensordict.set("state", state)
        return tensordict

    # ------------------------------------------------------------------ team changes
    def remove_robot(
        self, env_index: int, robot: int, *, tensordict: TensorDictBase | None = None
    ) -> None:
        """Take ``robot`` out of env ``env_index``'s team now; the episode goes on without it.

        It stops (zero velocity), drops what it carries and from the next step on is masked out
        of everything (see the class docstring). An env keeps at least one robot. With
        ``tensordict`` (the current root td) its observation, state and ``present`` are rewritten,
        as :meth:`write_waypoints` does. Not for the hot path (a few small ops and a sync).
        """
        e = self._team_env_index(env_index)
        r = self._robot_index(robot)
        present = self._present.clone()
        if not bool(present[r, e]):
            raise ValueError(f"robot {r} is not in env {e}'s team (present: {self._team(e)})")
        if int(present[:, e].sum()) == 1:
            raise ValueError(f"robot {r} is the last robot of env {e}; an env keeps at least one")
        present[r, e] = False
        self._put(**self._robot_reset(r, e, self._pos[r, :, e]))
        self._set_present(present)
        self._rewrite(tensordict)

    def add_robot(
        self,
        env_index: int,
        robot: int | None = None,
        *,
        tensordict: TensorDictBase | None = None,
    ) -> int:
        """Bring a robot into env ``env_index``'s team now and return its index.

        ``robot`` None takes the lowest absent index. It appears at rest at a random point of the
        field clear of the other robots, the resources, the invaders and home (at home's edge if
        64 tries find none), with fresh waypoints (a random walk from it, or its position
        repeated with ``waypoint_mode="external"``). Draws from the env's generator. With
        ``tensordict`` (the current root td) its observation, state and ``present`` are
        rewritten, as :meth:`write_waypoints` does. Not for the hot path.
        """
        e = self._team_env_index(env_index)
        present = self._present.clone()
        if robot is None:
            absent = (~present[:, e]).nonzero().squeeze(-1)
            if not absent.numel():
                raise ValueError(
                    f"env {e} is full: all n_agents={self.n_agents} robots are present"
                )
            r = int(absent[0])
        else:
            r = self._robot_index(robot)
            if bool(present[r, e]):
                raise ValueError(
                    f"robot {r} is already in env {e}'s team (present: {self._team(e)})"
                )
        present[r, e] = True
        self._put(**self._robot_reset(r, e, self._free_point(e, present[:, e])))
        wp = self._wp.clone()
        if self.waypoint_mode == "random_walk":
            steps = self._randn(self.n_waypoints, 2) * self.waypoint_sigma
            wp[e, r] = (self._pos[r, :, e] + steps.cumsum(0)).clamp(-self.half, self.half)
        else:
            wp[e, r] = self._pos[r, :, e]
        self._put(_wp=wp)
        self._set_present(present)
        self._rewrite(tensordict)
        return r

    def _team_env_index(self, env_index) -> int:
        if not _is_index(env_index) or not 0 <= env_index < self.num_envs:
            raise ValueError(
                f"env_index must be an integer in 0..{self.num_envs - 1}, got {env_index!r}"
            )
        return int(env_index)

    def _robot_index(self, robot) -> int:
        if not _is_index(robot) or not 0 <= robot < self.n_agents:
            raise ValueError(f"robot must be an integer in 0..{self.n_agents - 1}, got {robot!r}")
        return int(robot)

    def _team(self, e: int) -> list[int]:
        return self._present[:, e].nonzero().squeeze(-1).tolist()

    def _robot_reset(self, r: int, e: int, point: torch.Tensor) -> dict:
        """Robot ``r`` of env ``e`` at ``point`` [2], at rest, carrying nothing, on no path."""
        state = {
            name: getattr(self, name).clone() for name in ("_pos", "_vel", "_carry", "_defended")
        }
        state["_pos"][r, :, e] = point
        state["_vel"][r, :, e] = 0.0
        state["_carry"][r, e] = False
        state["_defended"][r, e] = False
        on_path, on_route = self._on_path.clone(), self._on_route.clone()
        on_path[r, :, e] = False
        on_route[r, :, e] = False
        return dict(state, _on_path=on_path, _on_route=on_route)

    def _free_point(self, e: int, team: torch.Tensor, tries: int = 64) -> torch.Tensor:
        """A uniform point [2] of env ``e``'s field touching no robot of ``team`` [N], resource,
        active invader or home; home's edge (+x side first, then around) when none of ``tries``
        is."""
        lim = self.half - self.agent_radius
        cand = (self._rand(tries, 2) * 2 - 1) * lim
        edge = self.home_radius + self.agent_radius + 1e-3
        angle = torch.linspace(0, 2 * math.pi, tries + 1, device=self.device)[:-1]
        ring = edge * torch.stack([angle.cos(), angle.sin()], -1)
        cand = torch.cat([cand, ring])  # [2 * tries, 2]; the ring only if no uniform one fits
        robots = self._pos[:, :, e][team]
        inv = self._inv[:, :, e][self._inv_on[:, e]]
        clear = torch.ones(cand.shape[0], dtype=torch.bool, device=self.device)
        for others, gap in (
            (robots, 2 * self.agent_radius),
            (self._res[:, :, e], self.agent_radius + self.resource_radius),
            (inv, self.agent_radius + self.invader_radius),
            (torch.zeros(1, 2, device=self.device), self.home_radius + self.agent_radius),
        ):
            if others.numel():
                clear &= torch.cdist(cand, others).amin(-1) >= gap
        return cand[int(clear.to(torch.uint8).argmax())] if bool(clear.any()) else ring[0]

    def _rewrite(self, tensordict: TensorDictBase | None) -> None:
        """Rewrite the observation, state, waypoints and team mask of the root ``tensordict``."""
        if tensordict is None:
            return
        obs, state = self._observe()
        wp = self._wp.clone()
        self._put(_wp_emitted=(wp, wp._version))
        tensordict.set(("agents", "observation"), obs)
        tensordict.set(("agents", "waypoints"), wp)
        tensordict.set(("agents", "present"), self._present_bf.clone())
        tensordict.set("state", state)


# ---------------------------------------------------------------- the parameters, from the table
def _read_only(name: str, doc: str) -> property:
    return property(lambda self: getattr(self.params, name), doc=doc)


def _signature() -> inspect.Signature:
    """``__init__``'s signature with the table's fields as keyword-only arguments (what
    ``inspect.signature`` and ``help`` show)."""
    fixed = inspect.signature(ResourceCollectionEnv.__init__).parameters.values()
    fields = [
        inspect.Parameter(
            f.name, inspect.Parameter.KEYWORD_ONLY, default=f.default, annotation=f.type
        )
        for f in dataclasses.fields(ResourceCollectionParams)
    ]
    head = [a for a in fixed if a.kind is not a.VAR_KEYWORD and a.name != "team_sizes"]
    (team_sizes,) = [a for a in fixed if a.name == "team_sizes"]
    return inspect.Signature([*head, *fields, team_sizes])


for _f in dataclasses.fields(ResourceCollectionParams):
    setattr(ResourceCollectionEnv, _f.name, _read_only(_f.name, _f.metadata["doc"]))
ResourceCollectionEnv.__init__.__signature__ = _signature()
if ResourceCollectionEnv.__doc__:  # (None under python -OO)
    ResourceCollectionEnv.__doc__ += "\n    Keyword Args:\n" + keyword_args_doc() + "\n"
