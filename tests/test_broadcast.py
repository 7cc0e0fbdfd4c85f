"""Adaptive broadcast (COPA's beta, ``method.broadcast_threshold``): the coordinator computes z
every T steps and robot i receives it only when it moved more than beta from the z it holds;
the loss replays the z the agents held; evaluations report the broadcast rate."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from icco_torchrl.evaluation.rollout import episode_metrics, greedy_rollout
from icco_torchrl.objectives.inputs import assemble
from icco_torchrl.training.build import build_components, compose_config
from icco_torchrl.training.config import ConfigError, validate
from icco_torchrl.training.segments import SegmentCutter


def _parts(beta: float, seed: int = 0):
    torch.manual_seed(seed)
    cfg = compose_config(["method=icco", f"method.broadcast_threshold={beta}", "device=cpu"])
    return build_components(cfg, num_envs=4)


def _rollout(parts, steps: int = 48, seed: int = 0):
    parts["env"].set_seed(seed)
    torch.manual_seed(seed)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        return parts["env"].rollout(steps, parts["policy"], break_when_any_done=False)


def test_beta_zero_sends_every_robot_every_t_steps():
    ro = _rollout(_parts(0.0))
    sent = ro["agents", "z_sent"].squeeze(-1)  # [B, L, N]
    broadcast = (ro["step_count"] % 4 == 0).expand_as(sent)
    assert torch.equal(sent, broadcast)
    z = ro["agents", "z"]
    changed = (z[:, 1:] != z[:, :-1]).any(-1)
    assert not changed[~broadcast[:, 1:]].any()  # held between broadcasts
    assert episode_metrics(ro)["broadcast_rate"].tolist() == [0.25] * 4


@pytest.mark.parametrize("beta", [0.8, 1.5])
def test_a_robot_gets_a_new_z_only_when_it_moved_more_than_beta(beta):
    ro = _rollout(_parts(beta))
    sent = ro["agents", "z_sent"].squeeze(-1)
    z = ro["agents", "z"]
    broadcast = (ro["step_count"] % 4 == 0).expand_as(sent)
    assert not sent[~broadcast].any()  # never between broadcasts
    assert sent[:, 0].all()  # every robot at the episode's first step
    changed = (z[:, 1:] != z[:, :-1]).any(-1)
    assert torch.equal(changed, sent[:, 1:])  # z changes exactly where it was sent
    moved = (z[:, 1:] - z[:, :-1]).norm(dim=-1)
    assert (moved[sent[:, 1:]] > beta).all()
    assert 0 < sent[broadcast].float().mean() < 1


def test_the_rate_falls_as_beta_grows():
    rates = [episode_metrics(_rollout(_parts(b)))["broadcast_rate"].mean() for b in (0, 1.0, 5, 50)]
    assert rates[0] == 0.25 and all(a >= b for a, b in zip(rates, rates[1:]))
    assert rates[-1] == pytest.approx(1 / 48)  # only the episode's first step


def test_the_loss_replays_the_z_the_agents_held():
    """With beta > 0, z rebuilt by the loss with the collection weights equals the z stored at
    collection on every step of the sequence's episode, across broadcasts that were not sent."""
    parts = _parts(1.0)
    ro = _rollout(parts, steps=48)
    items = SegmentCutter(length=16)(ro)
    loss = parts["loss"]
    x = assemble(loss.read_batch(items), reads_state=True)
    assert ("agents", "z_sent") in loss.in_keys
    assert not x.z_sent[x.step_count % 4 == 0].all()  # some broadcasts were not sent
    with torch.no_grad():
        z, _, _ = loss._z_sequence(x, loss.coordinator_params, torch.randn_like(x.z[:, 0]))
    valid = x.mask
    torch.testing.assert_close(z[:, :16][valid], x.z[valid])


def test_a_negative_beta_fails_naming_the_field():
    with pytest.raises(ConfigError, match="method.broadcast_threshold"):
        validate(compose_config(["method.broadcast_threshold=-0.1"]))


def test_greedy_evaluation_reports_the_broadcast_rate():
    parts = _parts(2.0)
    parts["env"].set_seed(3)
    ro = greedy_rollout(parts["env"], parts["policy"], 40)
    rate = episode_metrics(ro)["broadcast_rate"]
    assert rate.shape == (4,) and ((rate > 0) & (rate <= 0.25 + 1e-6)).all()
