"""Greedy evaluation episodes: the policy acts deterministically (argmax Q, coordinator mean)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from icco_torchrl.envs.resource_collection import EVENT_KEYS


def greedy_rollout(
    env: EnvBase, policy, steps: int, tensordict: TensorDictBase | None = None
) -> TensorDictBase:
    """``[num_envs, steps]`` rollout under deterministic exploration, without gradients."""
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        return env.rollout(
            steps,
            policy,
            break_when_any_done=False,
            auto_reset=tensordict is None,
            tensordict=tensordict,
        )


def episode_metrics(rollout: TensorDictBase) -> dict[str, torch.Tensor]:
    """Per-env totals over the rollout's time dim: team ``reward`` and each event count."""
    nxt = rollout.get("next")
    out = {"reward": nxt.get("reward").sum((-2, -1)).float()}
    for key in EVENT_KEYS:
        out[key] = nxt.get(("events", key)).sum(-1).float()
    out["task_reward"] = out["reward"] - out["inst_reward"]
    sent = rollout.get(("agents", "z_sent"), None)
    if sent is not None:  # a coordinator's policy: the share of robot-steps a z reached a robot
        present = rollout.get(("agents", "present"), None)
        weight = torch.ones_like(sent, dtype=torch.float) if present is None else present.float()
        out["broadcast_rate"] = (sent.float() * weight).sum((1, 2, 3)) / weight.sum(
            (1, 2, 3)
        ).clamp_min(1.0)
    return out


def evaluate(
    env: EnvBase, policy, *, steps: int | None = None, seed: int | None = None
) -> dict[str, float]:
    """Mean and std over the env batch of one greedy episode's totals (``reward``, ``reward_std``,
    ``task_reward``, ...). With ``seed`` the env is re-seeded first, so every call (a trained
    policy at each evaluation, the reference policies) faces the same initial configurations.

    ``policy=None`` rolls out uniformly random actions from the spec.
    """
    if steps is None:
        steps = getattr(env, "base_env", env).max_steps
    if seed is not None:
        env.set_seed(seed)
    metrics = episode_metrics(greedy_rollout(env, policy, steps))
    return summarize(metrics)


def summarize(metrics: dict[str, torch.Tensor]) -> dict[str, float]:
    """``{key: mean, key_std: std}`` over trials."""
    out = {}
    for key, value in metrics.items():
        out[key] = value.float().mean().item()
        out[f"{key}_std"] = value.float().std(unbiased=False).item()
    return out
