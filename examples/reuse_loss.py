"""Reusing ``ICCOLoss`` on another TorchRL multi-agent env with its own key names.

The env here, "rendezvous", has nothing to do with resource collection: N robots on a plane
must meet. Its per-robot group is ``"robots"`` (not ``"agents"``), the observation is
``("robots", "obs")``, the action ``("robots", "move")``, the global state ``"world"`` and the
team reward ``"team_reward"``. ICCO's modules are built with the flat MLP encoders from the
sizes in this env's specs (observation and state width, action count; no layout), and the loss
is told the key names with ``set_keys``; nothing in the ``icco_torchrl`` package is edited.

Run::

    python examples/reuse_loss.py --total-frames 40000 --seed 0
"""

from __future__ import annotations

import argparse
import json
import math
import time

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import (
    Bounded,
    Categorical,
    Composite,
    LazyTensorStorage,
    RandomSampler,
    TensorDictReplayBuffer,
    Unbounded,
)
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from icco_torchrl.modules import make_agent, make_coordinator, make_mixer, make_posterior
from icco_torchrl.modules.policy import exploration_module, make_policy, make_primer
from icco_torchrl.objectives import ICCOLoss, make_target_updater, total_loss
from icco_torchrl.training.segments import SegmentCutter

GROUP = "robots"
# Where this env keeps what ICCOLoss reads (its defaults are the resource-collection names).
LOSS_KEYS = dict(
    observation=(GROUP, "obs"),
    action=(GROUP, "move"),
    state="world",
    reward="team_reward",
    prev_action=(GROUP, "prev_action"),
    rnn_hidden=(GROUP, "rnn_hidden"),
    z=(GROUP, "z"),
    z_noise=(GROUP, "z_noise"),
    action_value=(GROUP, "action_value"),
    local_value=(GROUP, "chosen_action_value"),
)
# 0 stay, 1 -x, 2 +x, 3 -y, 4 +y
MOVES = ((0.0, 0.0), (-1.0, 0.0), (1.0, 0.0), (0.0, -1.0), (0.0, 1.0))


class RendezvousEnv(EnvBase):
    """Batched pure-torch rendezvous: robots start at random points of [-1, 1]^2 and should meet.

    Keys (``B = num_envs``, ``N = n_agents``)::

        ("robots", "obs")   [B, N, 2N]  own position, then the others' positions relative to it
        ("robots", "move")  [B, N]      0 stay, 1 -x, 2 +x, 3 -y, 4 +y (``step_size`` each)
        "world"             [B, 2N]     every robot's position (the global state)
        "step_count"        [B, 1]      steps since reset
        "team_reward"       [B, 1]      minus the mean pairwise distance after the move (in "next")
        "done" / "terminated" / "truncated"  [B, 1]  truncated after ``max_steps``, never terminated
    """

    batch_locked = True

    def __init__(
        self,
        num_envs: int = 8,
        n_agents: int = 3,
        max_steps: int = 20,
        step_size: float = 0.1,
        device: str | torch.device = "cpu",
        seed: int | None = None,
    ):
        if n_agents < 2 or num_envs < 1 or max_steps < 1 or not step_size > 0:
            raise ValueError("need n_agents >= 2, num_envs >= 1, max_steps >= 1 and step_size > 0")
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        B, N = num_envs, n_agents
        self.num_envs, self.n_agents, self.max_steps, self.step_size = (
            B,
            N,
            max_steps,
            float(step_size),
        )
        self.obs_dim = self.state_dim = 2 * N
        dev = self.device
        self.observation_spec = Composite(
            {
                GROUP: Composite(
                    obs=Unbounded((B, N, self.obs_dim), device=dev), shape=(B, N), device=dev
                )
            },
            world=Unbounded((B, self.state_dim), device=dev),
            step_count=Bounded(0, max_steps, (B, 1), dtype=torch.int64, device=dev),
            shape=(B,),
            device=dev,
        )
        self.action_spec = Composite(
            {
                GROUP: Composite(
                    move=Categorical(len(MOVES), (B, N), dtype=torch.int64, device=dev),
                    shape=(B, N),
                    device=dev,
                )
            },
            shape=(B,),
            device=dev,
        )
        self.reward_spec = Composite(
            team_reward=Unbounded((B, 1), device=dev), shape=(B,), device=dev
        )
        flag = lambda: Categorical(2, (B, 1), dtype=torch.bool, device=dev)  # noqa: E731
        self.done_spec = Composite(
            done=flag(), terminated=flag(), truncated=flag(), shape=(B,), device=dev
        )
        self._moves = torch.tensor(MOVES, device=dev) * self.step_size
        others = torch.arange(N).expand(N, N)
        self._others = others[others != torch.arange(N)[:, None]].view(N, N - 1).to(dev)
        self._pairs = torch.triu_indices(N, N, 1, device=dev)
        self._rng = torch.Generator(device=dev)
        self._rng.manual_seed(0 if seed is None else int(seed))
        self.pos = torch.zeros(B, N, 2, device=dev)
        self.t = torch.zeros(B, dtype=torch.int64, device=dev)

    def _set_seed(self, seed: int | None):
        self._rng.manual_seed(0 if seed is None else int(seed))

    def _observe(self) -> TensorDictBase:
        B, N = self.num_envs, self.n_agents
        rel = self.pos[:, self._others] - self.pos.unsqueeze(2)  # [B, N, N-1, 2]
        obs = torch.cat([self.pos, rel.flatten(2)], -1)
        return TensorDict(
            {
                GROUP: TensorDict({"obs": obs}, [B, N]),
                "world": self.pos.flatten(1),
                "step_count": self.t.unsqueeze(-1),
            },
            [B],
            device=self.device,
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        B, N = self.num_envs, self.n_agents
        fresh = torch.rand(B, N, 2, generator=self._rng, device=self.device) * 2 - 1
        if tensordict is not None and "_reset" in tensordict.keys():
            reset = tensordict.get("_reset").reshape(B)
        else:
            reset = torch.ones(B, dtype=torch.bool, device=self.device)
        self.pos = torch.where(reset[:, None, None], fresh, self.pos)
        self.t = torch.where(reset, torch.zeros_like(self.t), self.t)
        out = self._observe()
        false = torch.zeros(B, 1, dtype=torch.bool, device=self.device)
        out.update({"done": false, "terminated": false.clone(), "truncated": false.clone()})
        return out

    def mean_pairwise_distance(self) -> torch.Tensor:
        i, j = self._pairs
        return (self.pos[:, i] - self.pos[:, j]).norm(dim=-1).mean(-1)  # [B]

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        move = tensordict.get((GROUP, "move")).reshape(self.num_envs, self.n_agents).long()
        self.pos = (self.pos + self._moves[move]).clamp(-1.5, 1.5)
        self.t = self.t + 1
        out = self._observe()
        truncated = (self.t >= self.max_steps).unsqueeze(-1)
        out.update(
            {
                "team_reward": -self.mean_pairwise_distance().unsqueeze(-1),
                "done": truncated,
                "terminated": torch.zeros_like(truncated),
                "truncated": truncated,
            }
        )
        return out


def make_env(
    num_envs: int, n_agents: int, hidden: int, z_dim: int, seed: int, max_steps: int = 20
) -> TransformedEnv:
    """The env plus the primer carrying the policy's GRU state, previous move and z ("robots")."""
    base = RendezvousEnv(num_envs=num_envs, n_agents=n_agents, max_steps=max_steps, seed=seed)
    return TransformedEnv(
        base, make_primer(n_agents, hidden, z_dim, group=GROUP, n_actions=len(MOVES))
    )


def build(
    *,
    num_envs: int = 8,
    n_agents: int = 3,
    hidden: int = 32,
    z_dim: int = 8,
    period: int = 4,
    seed: int = 0,
    gamma: float = 0.95,
    ce_coef: float = 1e-3,
    entropy_coef: float = 1e-4,
) -> dict:
    """Env, ICCO modules, policy and the loss (with this env's key names)."""
    torch.manual_seed(seed)
    env = make_env(num_envs, n_agents, hidden, z_dim, seed)
    # Sizes from the specs: per-robot observation width, state width, action count.
    obs_dim = env.observation_spec[GROUP, "obs"].shape[-1]
    state_dim = env.observation_spec["world"].shape[-1]
    n_actions = env.full_action_spec[GROUP, "move"].space.n
    agent = make_agent(
        obs_dim=obs_dim,
        n_actions=n_actions,
        hidden=hidden,
        z_dim=z_dim,
        obs_key=(GROUP, "obs"),
        state_key="world",
        action_key=(GROUP, "move"),
    )
    coordinator = make_coordinator(
        n_agents=n_agents,
        state_dim=state_dim,
        z_dim=z_dim,
        hidden=hidden,
        period=period,
        init_logvar=0.0,
        state_key="world",
        group=GROUP,
    )
    mixer = make_mixer(
        state_dim,
        n_agents,
        kind="qmix",
        local_value_key=(GROUP, "chosen_action_value"),
        state_key="world",
    )
    # The posterior has no keys of its own: ICCOLoss passes it what it read through its (renamed)
    # keys.
    posterior = make_posterior(
        n_actions=n_actions,
        n_agents=n_agents,
        obs_dim=obs_dim,
        state_dim=state_dim,
        z_dim=z_dim,
        hidden=hidden,
        combine="product",
    )
    policy = make_policy(
        agent, env.full_action_spec_unbatched, coordinator, group=GROUP, action_name="move"
    )
    loss = ICCOLoss(
        agent,
        mixer,
        coordinator,
        posterior,
        gamma=gamma,
        ce_coef=ce_coef,
        entropy_coef=entropy_coef,
    )
    loss.set_keys(**LOSS_KEYS)
    return dict(
        env=env,
        agent=agent,
        coordinator=coordinator,
        mixer=mixer,
        posterior=posterior,
        policy=policy,
        loss=loss,
        cutter=SegmentCutter(length=period),
    )


@torch.no_grad()
def evaluate(
    policy, *, n_agents: int, hidden: int, z_dim: int, seed: int, episodes: int = 16
) -> float:
    """Mean episode return of the greedy policy (coordinator mean, no epsilon) on fixed starts."""
    env = make_env(episodes, n_agents, hidden, z_dim, seed=10_000 + seed)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        ro = env.rollout(env.base_env.max_steps, policy, break_when_any_done=False)
    return float(ro["next", "team_reward"].sum(1).mean())


def main(
    total_frames: int = 40_000,
    seed: int = 0,
    *,
    num_envs: int = 8,
    steps_per_batch: int = 20,
    updates_per_batch: int = 4,
    batch_segments: int = 32,
    buffer_segments: int = 5_000,
    lr: float = 1e-3,
    target_interval: int = 50,
    hidden: int = 32,
    z_dim: int = 8,
    n_agents: int = 3,
    eval_episodes: int = 16,
    verbose: bool = False,
) -> dict:
    """Train ICCO on rendezvous: losses, greedy returns before/after and what the loss read."""
    start = time.perf_counter()
    parts = build(num_envs=num_envs, n_agents=n_agents, hidden=hidden, z_dim=z_dim, seed=seed)
    env, policy, loss, cutter = parts["env"], parts["policy"], parts["loss"], parts["cutter"]
    explore = exploration_module(policy)
    optim = torch.optim.Adam(loss.parameters(), lr=lr)
    updater = make_target_updater(loss, "hard", interval=target_interval)
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(buffer_segments),
        sampler=RandomSampler(),
        batch_size=batch_segments,
    )
    ev = dict(n_agents=n_agents, hidden=hidden, z_dim=z_dim, seed=seed, episodes=eval_episodes)
    eval_before = evaluate(policy, **ev)

    frames_per_batch = num_envs * steps_per_batch
    collector = Collector(
        env,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=total_frames,
        auto_register_policy_transforms=False,
    )
    history, frames, updates, sample_keys = [], 0, 0, None
    for batch in collector:
        frames += batch.numel()
        explore.eps.fill_(max(0.05, 1.0 - 0.95 * frames / (0.6 * total_frames)))  # linear 1 -> 0.05
        buffer.extend(cutter(batch))
        if len(buffer) < batch_segments:
            continue
        for _ in range(updates_per_batch):
            sample = buffer.sample()
            sample_keys = sample_keys or sorted(map(str, sample.keys(True, True)))
            losses = loss(sample)
            optim.zero_grad(set_to_none=True)
            total_loss(losses).backward()
            torch.nn.utils.clip_grad_norm_(loss.parameters(), 10.0)
            optim.step()
            updater.step()
            updates += 1
        history.append({k: v.item() for k, v in losses.items()})
        if verbose and len(history) % 25 == 0:
            print(
                f"frames {frames:>7d}  loss_td {history[-1]['loss_td']:.4f}  eps "
                f"{float(explore.eps):.2f}"
            )
    collector.shutdown()

    eval_after = evaluate(policy, **ev)
    return {
        "frames": frames,
        "updates": updates,
        "first_loss_td": history[0]["loss_td"] if history else math.nan,
        "last_loss_td": history[-1]["loss_td"] if history else math.nan,
        "first_loss_ce": history[0]["loss_ce"] if history else math.nan,
        "last_loss_ce": history[-1]["loss_ce"] if history else math.nan,
        "history": history,
        "eval_return_before": eval_before,
        "eval_return_after": eval_after,
        "sample_keys": sample_keys or [],
        "seconds": time.perf_counter() - start,
    }


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--total-frames", type=int, default=40_000, help="env transitions to collect"
    )
    parser.add_argument("--seed", type=int, default=0, help="torch and env seed")
    parser.add_argument("--num-envs", type=int, default=8, help="envs stepped together")
    parser.add_argument(
        "--updates-per-batch", type=int, default=4, help="gradient steps per collector batch"
    )
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    result = main(
        args.total_frames,
        args.seed,
        num_envs=args.num_envs,
        updates_per_batch=args.updates_per_batch,
        lr=args.lr,
        verbose=True,
    )
    result.pop("history")
    result.pop("sample_keys")
    print(json.dumps(result, indent=2))
