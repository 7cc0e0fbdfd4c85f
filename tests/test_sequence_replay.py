"""Sequence replay: items of L steps spanning several broadcasts, lambda-returns, burn-in."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from conftest import run_cli

from icco_torchrl.objectives import lambda_returns, total_loss
from icco_torchrl.training.build import build_components, compose_config
from icco_torchrl.training.config import ConfigError
from icco_torchrl.training.segments import SegmentCutter

torch.set_num_threads(1)
REFERENCE = Path(__file__).parent / "data" / "loss_reference_t4.json"


def _fingerprint(loss) -> dict:
    """Per gradient: sum, norm and a projection on a seeded random vector (tests/data/README)."""
    generator, out = torch.Generator().manual_seed(7), {}
    for name, p in sorted(loss.named_parameters()):
        if p.grad is not None:
            grad = p.grad.double().flatten()
            proj = torch.randn(grad.numel(), generator=generator, dtype=torch.float64)
            out[name] = [grad.sum().item(), grad.norm().item(), (grad @ proj).item()]
    return out


@pytest.mark.parametrize("method", ["icco", "qmix_full"])
def test_one_broadcast_items_with_one_step_targets_reproduce_the_previous_loss(method):
    """L = T, lambda = 0: the loss terms and every gradient of the 4-step learner, to float
    precision (the reference was computed by the loss before sequence replay)."""
    expected = json.loads(REFERENCE.read_text())[method]
    # The reference predates method.layer_norm: it is the paper's agent, without it.
    one_step = [
        "train.sequence_length=4",
        "train.td_lambda=0",
        "train.burn_in=0",
        "method.layer_norm=false",
        # and predates the consistency term's default (1e-3, clamped): it was 1e-4, unclamped
        *(["method.ce_coef=1e-4", "method.entropy_coef=1e-4"] if method == "icco" else []),
        "train.ce_clamp=false",
    ]
    cfg = compose_config([f"method={method}", *one_step])
    torch.manual_seed(0)
    # When the reference was recorded, checking the config built a throwaway env, whose seed
    # took one draw from the global stream before the networks were initialised.
    torch.empty((), dtype=torch.int64).random_()
    parts = build_components(cfg, num_envs=8)
    torch.manual_seed(0)
    parts["env"].set_seed(0)
    with torch.no_grad():
        rollout = parts["env"].rollout(24, parts["policy"], break_when_any_done=False)
    items = SegmentCutter(length=4)(rollout)
    assert items.shape[0] == expected["segments"]
    torch.manual_seed(123)
    out = parts["loss"](items)
    total_loss(out).backward()
    for name, value in expected["losses"].items():
        assert out[name].item() == pytest.approx(value, rel=1e-5, abs=1e-7), name
    grads = _fingerprint(parts["loss"])
    assert grads.keys() == expected["grads"].keys()
    for name, values in expected["grads"].items():
        # float32 roundoff is relative to the gradient's size (its norm), not to each entry: a
        # projection can cancel to near 0 (the coordinator now runs on another batch shape)
        tol = 1e-6 * max(values[1], 1.0)
        assert grads[name] == pytest.approx(values, rel=1e-4, abs=tol), name


def test_lambda_return_with_an_episode_end_matches_a_hand_computation():
    """Four steps, the episode terminating at step 1 (no bootstrap there, no return across it)."""
    reward = torch.tensor([1.0, 2.0, 3.0, 4.0]).view(1, 4, 1)
    next_value = torch.tensor([10.0, 20.0, 30.0, 40.0]).view(1, 4, 1)
    alive = torch.tensor([1.0, 0.0, 1.0, 1.0]).view(1, 4, 1)
    cont = torch.tensor([True, False, True, False]).view(1, 4, 1)
    out = lambda_returns(reward, alive, next_value, cont, gamma=0.9, lmbda=0.5).flatten()
    # G3 = 4 + .9 * 40 = 40; G2 = 3 + .9 * (.5 * 30 + .5 * 40) = 34.5; G1 = 2 (terminal);
    # G0 = 1 + .9 * (.5 * 10 + .5 * G1) = 6.4
    torch.testing.assert_close(out, torch.tensor([6.4, 2.0, 34.5, 40.0]))
    one_step = lambda_returns(reward, alive, next_value, cont, gamma=0.9, lmbda=0.0).flatten()
    torch.testing.assert_close(one_step, torch.tensor([10.0, 2.0, 30.0, 40.0]))


@pytest.fixture(scope="module")
def long_rollout():
    """ICCO on 64 steps of episodes long enough to hold no end."""
    torch.manual_seed(0)
    parts = build_components(method="icco", num_envs=4)
    parts["env"].set_seed(0)
    with torch.no_grad():
        rollout = parts["env"].rollout(64, parts["policy"], break_when_any_done=False)
    return parts, rollout


def test_consistency_over_long_items_averages_the_same_windows_as_short_items(long_rollout):
    """Every broadcast window of 16-step items is scored as the 4-step item it would be."""
    parts, rollout = long_rollout
    loss = parts["loss"]
    short = loss(SegmentCutter(length=4)(rollout))
    long = loss(SegmentCutter(length=16)(rollout))
    for key in ("entropy", "log_q"):
        assert long[key].item() == pytest.approx(short[key].item(), rel=1e-5), key


def test_burn_in_steps_are_left_out_of_the_loss(long_rollout):
    """With lambda = 0 the burn-in changes which steps are scored, not their values."""
    parts, rollout = long_rollout
    loss = parts["loss"]
    assert loss.burn_in == 0
    items = SegmentCutter(length=16)(rollout)
    masked = items.clone()
    masked["mask"][:, :6] = False
    torch.manual_seed(1)
    plain = loss(masked)["loss_td"]
    loss.burn_in = 6
    try:
        torch.manual_seed(1)
        burned = loss(items)["loss_td"]
        items["next", "reward"][:, :6] += 100.0  # rewards of burn-in steps feed no target
        torch.manual_seed(1)
        shifted = loss(items)["loss_td"]
    finally:
        loss.burn_in = 0
    assert burned.item() == pytest.approx(plain.item(), rel=1e-5)
    assert shifted.item() == pytest.approx(burned.item(), rel=1e-5)


def test_lambda_changes_the_targets_of_long_items(long_rollout):
    parts, rollout = long_rollout
    loss = parts["loss"]
    items = SegmentCutter(length=16)(rollout)
    default = loss.td_lambda
    try:
        loss.td_lambda = 0.0
        torch.manual_seed(1)
        one_step = loss(items)["loss_td"].item()
        loss.td_lambda = 0.6
        torch.manual_seed(1)
        assert loss(items)["loss_td"].item() != pytest.approx(one_step, rel=1e-3)
    finally:
        loss.td_lambda = default


@pytest.mark.parametrize(
    "override, message",
    [
        ("train.sequence_length=6", "'train.sequence_length' (6) must be a multiple of"),
        ("train.burn_in=16", "'train.burn_in' (16) must be less than"),
        ("train.td_lambda=1.5", "train.td_lambda"),
        ("train.td_lambda=-0.1", "train.td_lambda"),
    ],
)
def test_bad_sequence_settings_fail_naming_the_field(override, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        compose_config(["experiment=smoke", "train.sequence_length=16", override])


def test_long_items_train_end_to_end_through_the_cli(tmp_path):
    run_cli(
        "train",
        "experiment=smoke",
        "logger.progress=false",
        "train.sequence_length=16",
        "train.burn_in=4",
        "train.td_lambda=0.6",
        "train.batch_segments=4",
        "train.warmup_segments=4",
        "eval.references=[]",  # the scripted policies: not this test's
        f"hydra.run.dir={tmp_path}",
    )
    ckpt = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert ckpt["updates"] > 0 and ckpt["cfg"]["train"]["sequence_length"] == 16
    proc = run_cli(
        "train",
        "experiment=smoke",
        "train.sequence_length=10",
        f"hydra.run.dir={tmp_path}/x",
        check=False,
    )
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "train.sequence_length" in proc.stderr
