"""The ICCO resource-collection task as a batched, pure-torch TorchRL environment.

Robots collect resources and bring them home while an invader walks toward home; a
human instruction is given as K waypoints per robot. Everything is vectorised over
``[num_envs, n_agents, ...]``: there is no Python loop over envs or agents in ``_step``.

Keys (``B = num_envs``, ``N = n_agents``, ``K = n_waypoints``)::

    ("agents", "observation")  [B, N, obs_dim]   own state, own waypoints, visible entities
    ("agents", "waypoints")    [B, N, K, 2]      instruction vectors (input and output)
    ("agents", "action")       [B, N]            0 no-op, 1 -x, 2 +x, 3 -y, 4 +y
    ("agents", "reward")       [B, N, 1]         each robot's own reward   (in "next")
    "state"                    [B, state_dim]    global state incl. everyone's waypoints
    "step_count"               [B, 1]            steps since reset (drives z and waypoint refresh)
    "reward"                   [B, 1]            team reward = sum of the robots' rewards
    "done" / "terminated" / "truncated"  [B, 1]  truncated at ``max_steps``, never terminated
    ("events", name)           [B]               this step's pick/collect/defense/invasion counts
                                                 and the summed instruction reward ``inst_reward``

Observation layout (per robot; see :class:`ObsLayout`): ``own`` = [x, y, vx, vy, carry,
waypoints relative to the robot (K*2)], then ``n_entities`` tokens of ``entity_dim`` features
[dx, dy, dvx, dvy, one-hot type (agent, resource, invader, home), flag, visible]; tokens
outside ``vision_radius`` are all zeros. The global state is ``N + R + I`` tokens of
``state_token_dim`` features [x, y, vx, vy, one-hot type (agent, resource, invader), flag,
defended, absolute waypoints (K*2, agents only)].
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

N_ACTIONS = 5
# Unit force per action: no-op, -x, +x, -y, +y (COPA's order).
_ACTION_DIRS = ((0.0, 0.0), (-1.0, 0.0), (1.0, 0.0), (0.0, -1.0), (0.0, 1.0))
_EVENTS = ("pick", "collect", "defense", "invasion")


@dataclass(frozen=True)
class ObsLayout:
    """Where things sit in the flat per-robot observation and in the global state."""

    n_agents: int
    n_waypoints: int
    own_dim: int          # [x, y, vx, vy, carry] + relative waypoints
    n_entities: int       # other robots + resources + invaders + home
    entity_dim: int
    state_tokens: int     # robots + resources + invaders
    state_token_dim: int

    @property
    def obs_dim(self) -> int:
        return self.own_dim + self.n_entities * self.entity_dim

    @property
    def state_dim(self) -> int:
        return self.state_tokens * self.state_token_dim


def _positive(name: str, value, integer: bool = False) -> None:
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    if not ok or isinstance(value, bool) or not value > 0 or not math.isfinite(value):
        kind = "a positive integer" if integer else "a positive finite number"
        raise ValueError(f"{name} must be {kind}, got {value!r}")


class ResourceCollectionEnv(EnvBase):
    """Batched resource collection with language-instruction waypoints (ICCO, Sec. IV).

    Args:
        num_envs: number of independent envs stepped together (the batch size).
        device: torch device of every tensor the env holds and emits.
        seed: seed of the env's own random generator (``set_seed`` re-seeds it).
        n_agents: robots per env (paper: 3).
        n_resources: resources on the field at all times; a picked one respawns at once (6).
        n_invaders: invaders (1). Each walks straight to home and respawns after removal.
        field_size: side of the square field in metres, centred on home at (0, 0) (6.5).
        vision_radius: robots see entities within this distance, inclusive (0.65).
        max_steps: episode length; ``truncated`` is set on the step that reaches it (145).
        inst_reward_scale: weight of the instruction reward ``r_inst`` (1.3).
        inst_dist_coef: weight of ``e_dist = -distance to nearest waypoint`` inside r_inst (0.1).
            The paper's text would reward being far away; we read it as a penalty.
        n_waypoints: waypoints K per robot (4).
        waypoint_interval: steps between random-walk refreshes of the waypoints (4).
        waypoint_sigma: std (m) of each random-walk increment; about one robot step (0.19).
        waypoint_mode: ``"random_walk"`` (training default: the env regenerates waypoints) or
            ``"external"`` (the env keeps whatever the caller wrote; see :meth:`write_waypoints`).
        pick_reward / collect_reward / defense_reward / invasion_penalty: event rewards
            (5, 1, 4, 4). The invasion penalty is shared equally by the robots so that the
            team reward (their sum) gets exactly ``-invasion_penalty`` per invasion.
        home_radius / resource_radius / agent_radius / invader_radius: contact radii in metres
            (COPA's geometry scaled by ~3.8: 0.3, 0.19, 0.15, 0.11). Two bodies touch when the
            distance between centres is below the sum of their radii.
        dt / damping / accel / max_speed: point-mass dynamics ``v <- damping*v + dt*accel*u``,
            speed capped at ``max_speed``, ``p <- p + dt*v`` (0.1, 0.75, 5.0, 1.9: ~0.19 m per
            step at full speed).
        invader_speed: metres per step toward home (0.19).
        invader_respawn_max: an invader respawns U{1..this} steps after removal (10).
        resource_min_radius: resources spawn between this distance from home and the field
            edge (1.5).
        validate: check actions and supplied waypoints at every step (costs a device sync).
    """

    batch_locked = True

    def __init__(
        self,
        num_envs: int = 1,
        device: str | torch.device = "cpu",
        seed: int | None = None,
        *,
        n_agents: int = 3,
        n_resources: int = 6,
        n_invaders: int = 1,
        field_size: float = 6.5,
        vision_radius: float = 0.65,
        max_steps: int = 145,
        inst_reward_scale: float = 1.3,
        inst_dist_coef: float = 0.1,
        n_waypoints: int = 4,
        waypoint_interval: int = 4,
        waypoint_sigma: float = 0.19,
        waypoint_mode: str = "random_walk",
        pick_reward: float = 5.0,
        collect_reward: float = 1.0,
        defense_reward: float = 4.0,
        invasion_penalty: float = 4.0,
        home_radius: float = 0.3,
        resource_radius: float = 0.19,
        agent_radius: float = 0.15,
        invader_radius: float = 0.11,
        dt: float = 0.1,
        damping: float = 0.75,
        accel: float = 5.0,
        max_speed: float = 1.9,
        invader_speed: float = 0.19,
        invader_respawn_max: int = 10,
        resource_min_radius: float = 1.5,
        validate: bool = True,
    ):
        for name, value in dict(num_envs=num_envs, n_agents=n_agents, n_resources=n_resources,
                                n_invaders=n_invaders, max_steps=max_steps, n_waypoints=n_waypoints,
                                waypoint_interval=waypoint_interval,
                                invader_respawn_max=invader_respawn_max).items():
            _positive(name, value, integer=True)
        for name, value in dict(field_size=field_size, vision_radius=vision_radius, dt=dt,
                                accel=accel, max_speed=max_speed, home_radius=home_radius,
                                resource_radius=resource_radius, agent_radius=agent_radius,
                                invader_radius=invader_radius, invader_speed=invader_speed).items():
            _positive(name, value)
        if n_waypoints < 2:
            raise ValueError(f"n_waypoints must be >= 2 (e_cossim needs two), got {n_waypoints}")
        if waypoint_sigma < 0 or not 0 <= damping < 1 or inst_reward_scale < 0:
            raise ValueError("waypoint_sigma, inst_reward_scale must be >= 0 and damping in [0, 1)")
        if not 0 < resource_min_radius < field_size / 2:
            raise ValueError(f"resource_min_radius must be in (0, field_size/2), got {resource_min_radius}")
        if waypoint_mode not in ("random_walk", "external"):
            raise ValueError(f"waypoint_mode must be 'random_walk' or 'external', got {waypoint_mode!r}")
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.num_envs, self.n_agents, self.n_resources, self.n_invaders = num_envs, n_agents, n_resources, n_invaders
        self.field_size, self.half = float(field_size), float(field_size) / 2
        self.vision_radius, self.max_steps = float(vision_radius), max_steps
        self.inst_reward_scale, self.inst_dist_coef = float(inst_reward_scale), float(inst_dist_coef)
        self.n_waypoints, self.waypoint_interval = n_waypoints, waypoint_interval
        self.waypoint_sigma, self.waypoint_mode = float(waypoint_sigma), waypoint_mode
        self.event_rewards = dict(pick=pick_reward, collect=collect_reward, defense=defense_reward,
                                  invasion=-invasion_penalty)
        self.home_radius, self.resource_radius = home_radius, resource_radius
        self.agent_radius, self.invader_radius = agent_radius, invader_radius
        self.dt, self.damping, self.accel, self.max_speed = dt, damping, accel, max_speed
        self.invader_speed, self.invader_respawn_max = invader_speed, invader_respawn_max
        self.resource_min_radius, self.validate = resource_min_radius, validate

        N, R, I, K = n_agents, n_resources, n_invaders, n_waypoints
        self.layout = ObsLayout(n_agents=N, n_waypoints=K, own_dim=5 + 2 * K,
                                n_entities=(N - 1) + R + I + 1, entity_dim=10,
                                state_tokens=N + R + I, state_token_dim=9 + 2 * K)
        dev = self.device
        self._action_dirs = torch.tensor(_ACTION_DIRS, device=dev)
        # Entity table seen by robots: robots, resources, invaders, home (self removed per robot).
        n_all = N + R + I + 1
        types = torch.cat([torch.zeros(N), torch.ones(R), torch.full((I,), 2.0), torch.full((1,), 3.0)]).long()
        self._entity_type = torch.nn.functional.one_hot(types, 4).float().to(dev)           # [E_all, 4]
        others = torch.arange(n_all).expand(N, n_all)
        keep = others != torch.arange(N)[:, None]
        self._others_idx = others[keep].view(N, n_all - 1).to(dev)                            # [N, E]
        state_types = torch.nn.functional.one_hot(types[: N + R + I], 3).float().to(dev)
        self._state_type = state_types                                                         # [N+R+I, 3]
        self._rng = torch.Generator(device=dev)
        self._rng.manual_seed(int(seed) if seed is not None else int(torch.empty((), dtype=torch.int64).random_().item()))
        self._make_specs()
        self._alloc_state()

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        B, N, K, L = self.num_envs, self.n_agents, self.n_waypoints, self.layout
        dev = self.device
        events = Composite(
            {name: Unbounded((B,), dtype=torch.int64, device=dev) for name in _EVENTS},
            inst_reward=Unbounded((B,), device=dev), shape=(B,), device=dev)
        self.observation_spec = Composite(
            agents=Composite(
                observation=Unbounded((B, N, L.obs_dim), device=dev),
                waypoints=Bounded(-self.half, self.half, (B, N, K, 2), device=dev),
                shape=(B, N), device=dev),
            state=Unbounded((B, L.state_dim), device=dev),
            step_count=Bounded(0, self.max_steps, (B, 1), dtype=torch.int64, device=dev),
            events=events,
            shape=(B,), device=dev)
        self.action_spec = Composite(
            agents=Composite(action=Categorical(N_ACTIONS, (B, N), dtype=torch.int64, device=dev),
                             shape=(B, N), device=dev),
            shape=(B,), device=dev)
        self.reward_spec = Composite(
            reward=Unbounded((B, 1), device=dev),
            agents=Composite(reward=Unbounded((B, N, 1), device=dev), shape=(B, N), device=dev),
            shape=(B,), device=dev)
        flag = lambda: Categorical(2, (B, 1), dtype=torch.bool, device=dev)  # noqa: E731
        self.done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), shape=(B,), device=dev)

    def _alloc_state(self) -> None:
        B, N, R, I, K, dev = self.num_envs, self.n_agents, self.n_resources, self.n_invaders, self.n_waypoints, self.device
        self.pos = torch.zeros(B, N, 2, device=dev)
        self.vel = torch.zeros(B, N, 2, device=dev)
        self.carry = torch.zeros(B, N, dtype=torch.bool, device=dev)
        self.defended = torch.zeros(B, N, dtype=torch.bool, device=dev)
        self.res_pos = torch.zeros(B, R, 2, device=dev)
        self.inv_pos = torch.zeros(B, I, 2, device=dev)
        self.inv_vel = torch.zeros(B, I, 2, device=dev)
        self.inv_active = torch.zeros(B, I, dtype=torch.bool, device=dev)
        self.inv_timer = torch.zeros(B, I, dtype=torch.int64, device=dev)
        self.waypoints = torch.zeros(B, N, K, 2, device=dev)
        self.t = torch.zeros(B, dtype=torch.int64, device=dev)

    def _set_seed(self, seed: int | None):
        self._rng.manual_seed(int(seed) if seed is not None else 0)

    # ------------------------------------------------------------------ sampling
    def _rand(self, *shape) -> torch.Tensor:
        return torch.rand(*shape, generator=self._rng, device=self.device)

    def _randn(self, *shape) -> torch.Tensor:
        return torch.randn(*shape, generator=self._rng, device=self.device)

    def _respawn_timer(self, *shape) -> torch.Tensor:
        return torch.randint(1, self.invader_respawn_max + 1, shape, generator=self._rng, device=self.device)

    def _edge_points(self, *shape) -> torch.Tensor:
        """Uniform points on the field's boundary (where invaders appear)."""
        side = torch.randint(0, 4, shape, generator=self._rng, device=self.device)
        along = (self._rand(*shape) * 2 - 1) * self.half
        fixed = torch.where(side % 2 == 0, -self.half, self.half) + 0 * along
        return torch.where((side < 2)[..., None], torch.stack([fixed, along], -1), torch.stack([along, fixed], -1))

    def _resource_candidates(self, *shape, n_candidates: int = 8) -> torch.Tensor:
        """Candidate spawn points on the annulus [resource_min_radius, field edge] around home."""
        r = self.resource_min_radius + self._rand(*shape, n_candidates) * (self.half - self.resource_min_radius)
        angle = self._rand(*shape, n_candidates) * (2 * math.pi)
        return torch.stack([r * torch.cos(angle), r * torch.sin(angle)], -1)               # [..., C, 2]

    def _spawn_resources(self, res_pos: torch.Tensor, respawn: torch.Tensor) -> torch.Tensor:
        """New positions for the slots in ``respawn`` [B, R], avoiding the other resources.

        Each slot draws a few candidates and keeps the first that overlaps no resource that
        stays; with 6 resources on ~30 m^2 a clash among the candidates is very rare.
        """
        cand = self._resource_candidates(*respawn.shape)                                     # [B, R, C, 2]
        d = (cand.unsqueeze(-2) - res_pos[:, None, None]).norm(dim=-1)                       # [B, R, C, R]
        blocking = (~respawn)[:, None, None, :] & (d < 2 * self.resource_radius)
        free = ~blocking.any(-1)                                                             # [B, R, C]
        first = free.to(torch.uint8).argmax(-1)                                              # first free or 0
        chosen = cand.gather(2, first[..., None, None].expand(-1, -1, 1, 2)).squeeze(2)
        return torch.where(respawn[..., None], chosen, res_pos)

    def _random_walk(self, start: torch.Tensor) -> torch.Tensor:
        """K waypoints ``p + cumsum(eps)``, eps ~ N(0, sigma^2 I), clipped to the field."""
        steps = self._randn(*start.shape[:-1], self.n_waypoints, 2) * self.waypoint_sigma
        return (start.unsqueeze(-2) + steps.cumsum(-2)).clamp(-self.half, self.half)

    # ------------------------------------------------------------------ reset
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        B, N, R, I = self.num_envs, self.n_agents, self.n_resources, self.n_invaders
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(B)
        lim = self.half - self.agent_radius
        pos = (self._rand(B, N, 2) * 2 - 1) * lim
        res_pos = torch.full((B, R, 2), 10 * self.field_size, device=self.device)
        for j in range(R):  # sequential so initial resources do not overlap (reset only)
            only_j = torch.zeros(B, R, dtype=torch.bool, device=self.device)
            only_j[:, j] = True
            res_pos = self._spawn_resources(res_pos, only_j)
        fresh = dict(
            pos=pos, vel=torch.zeros_like(pos), carry=torch.zeros(B, N, dtype=torch.bool, device=self.device),
            defended=torch.zeros(B, N, dtype=torch.bool, device=self.device), res_pos=res_pos,
            inv_pos=self._edge_points(B, I), inv_vel=torch.zeros(B, I, 2, device=self.device),
            inv_active=torch.zeros(B, I, dtype=torch.bool, device=self.device),
            inv_timer=self._respawn_timer(B, I), t=torch.zeros(B, dtype=torch.int64, device=self.device),
        )
        fresh["waypoints"] = self._random_walk(pos) if self.waypoint_mode == "random_walk" else pos.unsqueeze(-2).expand(B, N, self.n_waypoints, 2).clone()
        for name, value in fresh.items():
            current = getattr(self, name)
            if mask is None:
                setattr(self, name, value)
            else:
                m = mask.view(B, *([1] * (value.dim() - 1)))
                setattr(self, name, torch.where(m, value, current))
        out = self._observe()
        zeros = torch.zeros(B, dtype=torch.int64, device=self.device)
        out.set("events", TensorDict({**{k: zeros for k in _EVENTS}, "inst_reward": torch.zeros(B, device=self.device)}, [B]))
        false = torch.zeros(B, 1, dtype=torch.bool, device=self.device)
        out.update({"done": false, "terminated": false, "truncated": false})
        return out

    # ------------------------------------------------------------------ step
    def _read_waypoints(self, tensordict: TensorDictBase) -> None:
        wp = tensordict.get(("agents", "waypoints"), None)
        if wp is None:
            return
        self.waypoints = self._check_waypoints(wp)

    def _check_waypoints(self, wp: torch.Tensor) -> torch.Tensor:
        expected = (self.num_envs, self.n_agents, self.n_waypoints, 2)
        if tuple(wp.shape) != expected:
            raise ValueError(f"('agents', 'waypoints') must have shape {list(expected)}, got {list(wp.shape)}")
        wp = wp.to(self.device, torch.float32)
        if self.validate and not torch.isfinite(wp).all():
            raise ValueError("('agents', 'waypoints') contains non-finite values")
        return wp.clamp(-self.half, self.half)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(("agents", "action"))
        if action.shape != (self.num_envs, self.n_agents):  # one-hot or trailing dim: take the index
            action = action.argmax(-1) if action.shape[-1] == N_ACTIONS and action.dim() == 3 else action.reshape(self.num_envs, self.n_agents)
        if self.validate and ((action < 0) | (action >= N_ACTIONS)).any():
            raise ValueError(f"('agents', 'action') must be in [0, {N_ACTIONS - 1}], got {action.tolist()}")
        self._read_waypoints(tensordict)
        B, N = self.num_envs, self.n_agents
        dev = self.device

        # Robots: damped point masses with a speed cap, kept inside the field.
        vel = self.damping * self.vel + (self.dt * self.accel) * self._action_dirs[action]
        speed = vel.norm(dim=-1, keepdim=True)
        vel = vel * (self.max_speed / speed.clamp_min(self.max_speed))
        lim = self.half - self.agent_radius
        raw = self.pos + self.dt * vel
        new_pos = raw.clamp(-lim, lim)
        vel = torch.where(new_pos != raw, torch.zeros_like(vel), vel)
        disp = new_pos - self.pos
        r_inst = self._instruction_reward(self.pos, new_pos, disp)                            # [B, N]
        self.pos, self.vel = new_pos, vel

        # Invaders walk straight home.
        to_home = -self.inv_pos
        dist_home = to_home.norm(dim=-1, keepdim=True)
        move = to_home * (self.invader_speed / dist_home.clamp_min(self.invader_speed))
        self.inv_vel = torch.where(self.inv_active[..., None], move, torch.zeros_like(move))
        self.inv_pos = self.inv_pos + self.inv_vel

        # Events; one per robot per step, defense > pick > collect, ties to the lower index.
        d_inv = torch.cdist(self.pos, self.inv_pos)                                          # [B, N, I]
        hit = _assign((d_inv < self.agent_radius + self.invader_radius) & self.inv_active[:, None, :])
        defense = hit.any(-1)                                                                 # [B, N]
        removed = hit.any(1)                                                                  # [B, I]
        invaded = self.inv_active & ~removed & (self.inv_pos.norm(dim=-1) < self.home_radius + self.invader_radius)
        gone = removed | invaded
        timer = torch.where(gone, self._respawn_timer(B, self.n_invaders), self.inv_timer - (~self.inv_active).long())
        respawn = ~self.inv_active & ~gone & (timer <= 0)
        self.inv_pos = torch.where(respawn[..., None], self._edge_points(B, self.n_invaders), self.inv_pos)
        self.inv_active = (self.inv_active & ~gone) | respawn
        self.inv_timer = timer

        was_carrying = self.carry
        d_res = torch.cdist(self.pos, self.res_pos)                                          # [B, N, R]
        took = _assign((d_res < self.agent_radius + self.resource_radius) & ~(was_carrying | defense)[..., None])
        pick = took.any(-1)
        collect = was_carrying & ~defense & (self.pos.norm(dim=-1) < self.home_radius + self.agent_radius)
        self.carry = (was_carrying & ~collect) | pick
        picked = took.any(1)                                                                  # [B, R]
        rows = picked.any(1).nonzero().squeeze(-1)  # respawn only where something was picked
        if rows.numel():
            self.res_pos = self.res_pos.index_put((rows,), self._spawn_resources(self.res_pos[rows], picked[rows]))
        self.defended = defense

        n_invasion = invaded.sum(-1)                                                          # [B]
        w = self.event_rewards
        agent_reward = (w["pick"] * pick + w["collect"] * collect + w["defense"] * defense).float() \
            + (w["invasion"] / N) * n_invasion[:, None].float() + r_inst
        self.t = self.t + 1
        if self.waypoint_mode == "random_walk":
            refresh = self.t % self.waypoint_interval == 0
            if bool(refresh.any()):
                self.waypoints = torch.where(refresh[:, None, None, None], self._random_walk(self.pos), self.waypoints)

        out = self._observe()
        out.set(("agents", "reward"), agent_reward.unsqueeze(-1))
        out.set("reward", agent_reward.sum(-1, keepdim=True))
        out.set("events", TensorDict(dict(pick=pick.sum(-1), collect=collect.sum(-1), defense=defense.sum(-1),
                                          invasion=n_invasion, inst_reward=r_inst.sum(-1)), [B]))
        truncated = (self.t >= self.max_steps).unsqueeze(-1)
        out.update({"done": truncated, "terminated": torch.zeros_like(truncated), "truncated": truncated})
        return out

    def _instruction_reward(self, old_pos: torch.Tensor, new_pos: torch.Tensor, disp: torch.Tensor) -> torch.Tensor:
        """``r_inst = scale * (e_cossim + coef * e_dist)`` per robot.

        e_cossim: cosine between this step's displacement and the vector from the waypoint
        nearest to the robot (before the move) to the second-nearest one; 0 when either is
        zero. e_dist: minus the distance from the new position to its nearest waypoint.
        """
        wp = self.waypoints
        d_old = (wp - old_pos.unsqueeze(-2)).norm(dim=-1)                                     # [B, N, K]
        nearest2 = d_old.topk(2, dim=-1, largest=False).indices                               # [B, N, 2]
        pair = wp.gather(2, nearest2[..., None].expand(-1, -1, -1, 2))                        # [B, N, 2, 2]
        path = pair[:, :, 1] - pair[:, :, 0]
        cos = (disp * path).sum(-1) / (disp.norm(dim=-1) * path.norm(dim=-1)).clamp_min(1e-8)
        e_dist = -(wp - new_pos.unsqueeze(-2)).norm(dim=-1).min(-1).values
        return self.inst_reward_scale * (cos + self.inst_dist_coef * e_dist)

    # ------------------------------------------------------------------ observations
    def _observe(self) -> TensorDictBase:
        B, N, R, I, L = self.num_envs, self.n_agents, self.n_resources, self.n_invaders, self.layout
        dev = self.device
        # One table of every entity: [x, y, vx, vy, flag, exists] (robots, resources, invaders, home).
        table = torch.zeros(B, N + R + I + 1, 6, device=dev)
        table[:, :N, 0:2], table[:, :N, 2:4], table[:, :N, 4] = self.pos, self.vel, self.carry.float()
        table[:, N:N + R, 0:2] = self.res_pos
        table[:, N + R:N + R + I, 0:2], table[:, N + R:N + R + I, 2:4] = self.inv_pos, self.inv_vel
        table[:, N + R:N + R + I, 4] = self.inv_active.float()
        table[:, :, 5] = 1.0
        table[:, N + R:N + R + I, 5] = self.inv_active.float()

        obs = torch.empty(B, N, L.obs_dim, device=dev)
        obs[..., 0:2], obs[..., 2:4], obs[..., 4] = self.pos, self.vel, self.carry.float()
        obs[..., 5:L.own_dim] = (self.waypoints - self.pos.unsqueeze(2)).flatten(2)
        # What each robot sees: entities within vision_radius, relative to itself (else zeros).
        seen = table[:, self._others_idx]                                                    # [B, N, E, 6]
        ent = obs[..., L.own_dim:].view(B, N, L.n_entities, L.entity_dim)
        torch.sub(seen[..., 0:4], obs[..., 0:4].unsqueeze(2), out=ent[..., 0:4])
        ent[..., 4:8] = self._entity_type[self._others_idx]
        ent[..., 8] = seen[..., 4]
        visible = (ent[..., 0:2].square().sum(-1) <= self.vision_radius ** 2) & (seen[..., 5] > 0)
        ent[..., 9] = 1.0
        ent.mul_(visible.unsqueeze(-1))

        # Global state: robots (with their absolute waypoints), resources, invaders.
        n_tok = L.state_tokens
        tok = torch.zeros(B, n_tok, L.state_token_dim, device=dev)
        tok[..., 0:4] = table[:, :n_tok, 0:4] * table[:, :n_tok, 5:6]
        tok[..., 4:7] = self._state_type
        tok[..., 7] = table[:, :n_tok, 4]
        tok[:, :N, 8] = self.defended.float()
        tok[:, :N, 9:] = self.waypoints.flatten(2)
        return TensorDict({
            "agents": TensorDict({"observation": obs, "waypoints": self.waypoints.clone()}, [B, N]),
            "state": tok.flatten(1),
            "step_count": self.t.unsqueeze(-1),
        }, [B], device=dev)

    # ------------------------------------------------------------------ instructions
    def write_waypoints(self, tensordict: TensorDictBase, waypoints: torch.Tensor) -> TensorDictBase:
        """Give the robots new instruction waypoints ``[num_envs, n_agents, K, 2]`` now.

        Clips them to the field, stores them in the env and rewrites the observation and the
        state in ``tensordict`` (the current root td returned by reset/step_mdp), so the policy
        acts on them at this very step. With ``waypoint_mode="external"`` they are kept until
        the next call; in random-walk mode the env overwrites them at its next refresh.
        """
        self.waypoints = self._check_waypoints(torch.as_tensor(waypoints, device=self.device))
        obs = self._observe()
        tensordict.set(("agents", "observation"), obs.get(("agents", "observation")))
        tensordict.set(("agents", "waypoints"), obs.get(("agents", "waypoints")))
        tensordict.set("state", obs.get("state"))
        return tensordict


def _assign(contact: torch.Tensor) -> torch.Tensor:
    """Resolve contacts ``[B, N, M]`` into at most one item per robot and one robot per item.

    Each robot claims the lowest-index item it touches; a claimed item goes to the lowest-index
    claimant (the loser gets nothing this step).
    """
    first = contact.to(torch.uint8).argmax(-1)
    claim = torch.nn.functional.one_hot(first, contact.shape[-1]).bool() & contact.any(-1, keepdim=True)
    return claim & (claim.long().cumsum(1) == 1)
