"""Potential-based shaping of the training env: hand-computed potentials, the telescoping sum
over an episode, bad input, and its absence from every evaluation."""

from __future__ import annotations

import pytest
import torch
from conftest import run_cli
from torchrl.envs import TransformedEnv

from icco_torchrl.envs import ResourceCollectionEnv
from icco_torchrl.envs.shaping import PotentialShaping, StatePotential
from icco_torchrl.training.build import build, compose_config
from icco_torchrl.training.config import ConfigError
from icco_torchrl.training.restore import restore

torch.set_num_threads(1)


def _state(env, robots, carry, resources, invaders, active):
    """A global state with the given positions and the type flags (other features zero), as the
    env lays it out (a robot's type flag, column 4, marks it present)."""
    L = env.layout
    tokens = torch.zeros(1, L.state_tokens, L.state_token_dim)
    N, R = env.n_agents, env.n_resources
    tokens[0, :N, 4], tokens[0, N : N + R, 5], tokens[0, N + R :, 6] = 1.0, 1.0, 1.0
    tokens[0, :N, 0:2] = torch.tensor(robots)
    tokens[0, :N, 7] = torch.tensor(carry, dtype=torch.float32)
    tokens[0, N : N + R, 0:2] = torch.tensor(resources)
    tokens[0, N + R :, 0:2] = torch.tensor(invaders)
    tokens[0, N + R :, 7] = torch.tensor(active, dtype=torch.float32)
    return tokens.flatten(1)


def test_potentials_match_a_hand_computation():
    env = ResourceCollectionEnv(num_envs=1, n_agents=2, n_resources=2, n_invaders=1)
    state = _state(
        env,
        robots=[[3.0, 4.0], [0.0, 0.0]],  # a carrier 5 m from home, a free robot at home
        carry=[1, 0],
        resources=[[0.0, 3.0], [-1.0, 0.0]],  # trips from home: 3 + 3 and 1 + 1
        invaders=[[0.0, -2.0]],
        active=[1],
    )
    collect = StatePotential(env.layout, 2, ["collect"], weight=0.5)(state)
    torch.testing.assert_close(collect, torch.tensor([[-2.5, -1.0]]))
    defend = StatePotential(env.layout, 2, ["defend"], weight=1.0)(state)
    torch.testing.assert_close(defend, torch.tensor([[0.0, -2.0]]))  # the carrier does not defend
    idle = _state(env, [[3.0, 4.0], [0.0, 0.0]], [1, 0], [[0.0, 3.0], [-1.0, 0.0]], [[0, -2]], [0])
    both = StatePotential(env.layout, 2, ["collect", "defend"], weight=1.0)(idle)
    torch.testing.assert_close(both, torch.tensor([[-5.0, -2.0]]))  # no invader: no defend term


@pytest.mark.parametrize("potentials", [["collect"], ["collect", "defend"]])
def test_shaping_over_an_episode_telescopes_to_the_potentials_at_its_ends(potentials):
    """Same seeds, same actions: the shaped rewards differ from the plain ones by F_t, and
    sum_t gamma^t F_t = gamma^T Phi(s_T) - Phi(s_0) (summed over robots)."""
    gamma, steps = 0.9, 30
    params = dict(num_envs=3, max_steps=steps, seed=5)
    plain = ResourceCollectionEnv(**params)
    base = ResourceCollectionEnv(**params)
    shaping = PotentialShaping.for_env(base, potentials, 0.7, gamma)
    shaped = TransformedEnv(base, shaping)
    actions = torch.randint(
        0, 5, (steps, 3, plain.n_agents), generator=torch.Generator().manual_seed(0)
    )
    td_plain, td_shaped = plain.reset(), shaped.reset()
    phi0 = shaping.potential(td_shaped["state"]).sum(-1)
    total = torch.zeros(3)
    for t in range(steps):
        td_plain["agents", "action"] = actions[t]
        td_shaped["agents", "action"] = actions[t]
        td_plain, td_shaped = plain.step(td_plain), shaped.step(td_shaped)
        f = (td_shaped["next", "reward"] - td_plain["next", "reward"]).squeeze(-1)
        f_agents = (
            td_shaped["next", "agents", "reward"] - td_plain["next", "agents", "reward"]
        ).sum((-2, -1))
        torch.testing.assert_close(f, f_agents, atol=1e-5, rtol=0)  # each robot gets its own F_i
        total += gamma**t * f
        last_state = td_shaped["next", "state"]
        assert td_shaped["next", "done"].all() == (t == steps - 1)
        td_plain, td_shaped = td_plain["next"], td_shaped["next"]
    expected = gamma**steps * shaping.potential(last_state).sum(-1) - phi0
    torch.testing.assert_close(total, expected, atol=1e-4, rtol=1e-5)
    assert expected.abs().min() > 0  # the check is not vacuous


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["train.shaping.potentials=[gold]"], "unknown potential 'gold'"),
        (
            ["env.params.n_invaders=0", "train.shaping.potentials=[defend]"],
            "'defend' needs invaders",
        ),
        (["train.shaping.weight=-1"], "train.shaping.weight"),
    ],
)
def test_bad_shaping_fails_naming_the_field(overrides, message):
    with pytest.raises(ConfigError, match=message) as info:
        compose_config(["experiment=smoke", *overrides])
    assert "train.shaping" in str(info.value)


def test_shaping_shapes_the_training_env_only(tmp_path):
    """The training env carries it; the evaluation env during training, icco eval's restore and
    the evaluations written by a run do not (their rewards match an unshaped run's)."""
    cfg = compose_config(["experiment=smoke", "train.shaping.potentials=[collect]"])
    run = build(cfg, for_training=True)
    assert any(isinstance(t, PotentialShaping) for t in run.env.transform)
    assert not isinstance(run.eval_env.transform, PotentialShaping)
    assert "PotentialShaping" not in repr(run.eval_env.transform)
    common = ("experiment=smoke", "logger.progress=false", "train.total_frames=1024")
    run_cli("train", *common, "train.shaping.potentials=[collect]", f"hydra.run.dir={tmp_path}/s")
    run_cli("train", *common, "train.shaping.potentials=[]", f"hydra.run.dir={tmp_path}/p")
    restored = restore(tmp_path / "s" / "checkpoint.pt")
    assert "PotentialShaping" not in repr(restored.env.transform)
    # the references are scored by the evaluation env: identical with and without shaping
    assert (tmp_path / "s" / "references.json").read_text() == (
        tmp_path / "p" / "references.json"
    ).read_text()
    shaped_train = (tmp_path / "s" / "train.csv").read_text()
    assert shaped_train != (tmp_path / "p" / "train.csv").read_text()
