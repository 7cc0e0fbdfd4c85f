"""Per-robot reward channels (``method.reward_channels=per_robot``): the env's own-reward split,
the agent's two value channels, the loss's split of the team reward, bad input and a CLI run."""

from __future__ import annotations

import pytest
import torch
from conftest import run_cli
from torchrl.envs.utils import check_env_specs

from icco_torchrl.envs import ResourceCollectionEnv
from icco_torchrl.objectives import total_loss
from icco_torchrl.training.build import build_components, compose_config
from icco_torchrl.training.config import ConfigError, validate
from icco_torchrl.training.segments import SegmentCutter

PER_ROBOT = ["method.reward_channels=per_robot", "env.num_envs=4"]


def _rollout(env, steps=60, seed=0):
    torch.manual_seed(seed)
    return env.rollout(steps, break_when_any_done=False)  # random actions


def test_own_reward_and_the_team_terms_add_up_to_the_team_reward():
    """Each step: team reward = the robots' own terms + 4 per defense - 4 per invasion (the
    paper's weights), and a robot's own terms are its reward minus its defense and its share of
    the invasion penalty. Without the option the key is absent and the rest is unchanged."""
    check_env_specs(ResourceCollectionEnv(num_envs=2, own_reward=True), seed=0)
    td = _rollout(ResourceCollectionEnv(num_envs=8, seed=3, own_reward=True), 145)["next"]
    own = td["agents", "own_reward"].squeeze(-1)  # [B, T, N]
    team = td["reward"].squeeze(-1)
    events = td["events"]
    expected = own.sum(-1) + 4.0 * events["defense"] - 4.0 * events["invasion"]
    torch.testing.assert_close(team, expected, atol=1e-4, rtol=0)
    assert events["defense"].sum() > 0 and events["invasion"].sum() > 0  # both terms exercised
    ref = _rollout(ResourceCollectionEnv(num_envs=8, seed=3), 145)["next"]
    assert ("agents", "own_reward") not in ref.keys(True)
    torch.testing.assert_close(ref["reward"], td["reward"], atol=0, rtol=0)


def test_the_agent_acts_on_the_sum_of_its_channels():
    run = build_components(compose_config(["method=icco", *PER_ROBOT]))
    net = run.agent.module
    assert net.channels == 2 and net.head[-1].out_features == 2 * net.n_actions
    torch.manual_seed(0)
    S, L, N = 2, 5, run.layout.n_agents
    obs = torch.randn(S, L, N, run.layout.obs_dim)
    prev = torch.randint(0, net.n_actions, (S, L, N))
    h0, z = torch.zeros(S, N, net.hidden), torch.randn(S, L, N, net.z_dim)
    split = net.sequence(obs, prev, h0, z=z, split=True)
    assert split.shape == (S, L, N, 2, net.n_actions)
    torch.testing.assert_close(net.sequence(obs, prev, h0, z=z), split.sum(-2))
    q, _ = net.step(obs[:, 0], prev[:, 0], h0, z[:, 0])
    torch.testing.assert_close(q, split[:, 0].sum(-2), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("method", ["icco", "qmix_full"])
def test_the_loss_gives_the_team_terms_to_the_mixer_and_the_own_terms_to_each_robot(method):
    """A robot that earns 1 more on its own terms (own reward and team reward both +1) changes
    only the per-robot term; a team that earns 1 more on the team's terms (team reward +1, own
    terms fixed) changes only the mixed term. Both channels carry gradient, and the replay stores
    the own terms."""
    run = build_components(compose_config([f"method={method}", *PER_ROBOT]))
    loss = run.loss
    assert ("next", "agents", "own_reward") in loss.in_keys
    torch.manual_seed(0)
    with torch.no_grad():
        rollout = run.env.rollout(32, run.policy, break_when_any_done=False)
    items = SegmentCutter(length=16)(rollout).select(*loss.in_keys, strict=True)

    def terms(batch):
        torch.manual_seed(1)
        with torch.no_grad():
            out = loss(batch)
        return out["loss_td"], out["loss_td_robot"]

    base = terms(items)
    own = items.clone()
    own["next", "agents", "own_reward"][..., 0, :] += 1.0  # robot 0 earns 1 more on its own
    own["next", "reward"] += 1.0
    by_own = terms(own)
    torch.testing.assert_close(by_own[0], base[0], atol=1e-5, rtol=1e-5)
    assert not torch.allclose(by_own[1], base[1])
    team = items.clone()
    team["next", "reward"] += 1.0  # the team earns 1 more on its terms
    by_team = terms(team)
    torch.testing.assert_close(by_team[1], base[1], atol=0, rtol=0)
    assert not torch.allclose(by_team[0], base[0])

    torch.manual_seed(1)
    total_loss(loss(items)).backward()
    head = loss.agent.module.head[-1].weight.grad.unflatten(0, (2, -1))
    assert head[0].abs().sum() > 0 and head[1].abs().sum() > 0  # both channels learn


def test_the_option_fails_in_one_line_naming_the_field():
    with pytest.raises(ConfigError, match="method.reward_channels"):
        validate(compose_config(["method.reward_channels=robots"]))


def test_training_with_per_robot_channels_through_the_cli(tmp_path):
    run_cli(
        "train",
        "experiment=smoke",
        "method.reward_channels=per_robot",
        "train.total_frames=512",
        "train.eval_interval=0",
        "logger.progress=false",
        f"hydra.run.dir={tmp_path / 'run'}",
    )
    assert (tmp_path / "run" / "checkpoint.pt").exists()
    out = run_cli("eval", f"checkpoint={tmp_path / 'run' / 'checkpoint.pt'}", "eval.trials=2")
    assert "reward" in out.stdout


def test_the_aux_variant_mixes_the_whole_q_on_the_whole_reward():
    """``per_robot_aux``: the mixer scores each robot's whole Q (both channels) against the whole
    team reward, so any change of the team reward moves the mixed term; the own channel still
    learns each robot's own terms only."""
    run = build_components(
        compose_config(["method=icco", "method.reward_channels=per_robot_aux", "env.num_envs=4"])
    )
    loss = run.loss
    assert loss.mix_sum and loss.channels == 2
    torch.manual_seed(0)
    with torch.no_grad():
        rollout = run.env.rollout(32, run.policy, break_when_any_done=False)
    items = SegmentCutter(length=16)(rollout).select(*loss.in_keys, strict=True)

    def terms(batch):
        torch.manual_seed(1)
        with torch.no_grad():
            out = loss(batch)
        return out["loss_td"], out["loss_td_robot"]

    base = terms(items)
    team = items.clone()
    team["next", "reward"] += 1.0
    by_team = terms(team)
    assert not torch.allclose(by_team[0], base[0])
    torch.testing.assert_close(by_team[1], base[1], atol=0, rtol=0)
    own = items.clone()
    own["next", "agents", "own_reward"] += 1.0
    by_own = terms(own)
    torch.testing.assert_close(by_own[0], base[0], atol=0, rtol=0)
    assert not torch.allclose(by_own[1], base[1])
