"""The coordination measures (icco_torchrl/evaluation/consistency.py; docs/consistency.md).

Swap consistency is checked on scripted teams whose answers are computed by hand (a team that
follows its z, one that ignores it, one that reads it in opposite ways, a mixed one); the
mutual-information bound on a Gaussian case whose information is known in closed form, with the
exact posterior and with a fitted one; and both on real (untrained) ICCO rollouts for their
plumbing: determinism, replayed actions, the refusal of a team without a coordinator.
"""

import doctest
import math

import pytest
import torch
from torch import nn

from icco_torchrl.evaluation import consistency
from icco_torchrl.evaluation.consistency import (
    agent_actions,
    coordinator_rollouts,
    mi_estimate,
    mi_lower_bound,
    swap_consistency,
)
from icco_torchrl.modules.posterior import Posterior
from icco_torchrl.training.build import build_components

torch.set_num_threads(1)


# ============================================================================ swap consistency
def follow(z):
    """Every robot's action is its z's first entry: one shared reading of z."""
    return z[..., 0].long()


def ignoring(own_actions):
    """Every robot takes the action its own situation dictates (``own_actions [M, N]``)."""
    return lambda z: own_actions.expand(*z.shape[:-1])


Z_STEPS = torch.tensor([[[0.0], [1.0], [1.0]], [[2.0], [2.0], [4.0]]])  # M=2 steps, N=3 robots


def test_a_team_that_follows_its_z_scores_one():
    c = swap_consistency(follow, Z_STEPS)
    # own z: step 0 actions (0, 1, 1): the ordered pairs (1,2), (2,1) agree; step 1 (2, 2, 4):
    # (0,1), (1,0) agree -> 4 of 12. Swapped: robot i handed j's z acts as j did, always.
    assert (c.swap, c.own, c.pairs) == (1.0, pytest.approx(4 / 12), 12)
    assert c.kappa == pytest.approx(1.0)


def test_a_team_that_ignores_its_z_scores_zero():
    own = torch.tensor([[0, 3, 3], [1, 1, 2]])
    c = swap_consistency(ignoring(own), Z_STEPS)
    assert c.swap == c.own == pytest.approx(4 / 12)  # another's z changes no action
    assert c.kappa == 0.0


def test_robots_that_read_z_in_opposite_ways_score_below_zero():
    z = torch.tensor([[[0.0], [1.0]], [[1.0], [1.0]]])  # M=2, N=2

    def mirrored(z):  # robot 0 takes its z's action, robot 1 the other one of {0, 1}
        a = z[..., 0].long()
        a[..., 1] = 1 - a[..., 1]
        return a

    c = swap_consistency(mirrored, z)
    # own: step 0 (0, 0) agree, step 1 (1, 0) do not -> 1/2; swapped: never -> 0
    assert (c.swap, c.own) == (0.0, 0.5)
    assert c.kappa == pytest.approx(-1.0)


def test_a_mixed_team_hand_computed_and_absent_robots_left_out():
    z = torch.tensor([[[0.0], [1.0], [1.0]]])  # one step; robots 0 and 1 follow, robot 2 not

    def mixed(z):
        a = z[..., 0].long()
        a[..., 2] = 3  # robot 2 always takes action 3
        return a

    c = swap_consistency(mixed, z)
    # own actions (0, 1, 3): no pair agrees. Swapped, robot i handed j's z vs j's own action:
    # 0<-1: 1 = 1 yes; 0<-2: 1 vs 3; 1<-0: 0 = 0 yes; 1<-2: 1 vs 3; 2<-0: 3 vs 0; 2<-1: 3 vs 1
    assert (c.swap, c.own, c.pairs) == (pytest.approx(2 / 6), 0.0, 6)
    assert c.kappa == pytest.approx(1 / 3)
    without_2 = swap_consistency(mixed, z, present=torch.tensor([[True, True, False]]))
    assert (without_2.swap, without_2.own, without_2.pairs) == (1.0, 0.0, 2)


def test_swap_consistency_calls_act_once_and_needs_two_robots():
    calls = []

    def act(z):
        calls.append(z.shape)
        return follow(z)

    swap_consistency(act, Z_STEPS)
    assert calls == [(3, 2, 3, 1)]  # every shift of z at once: [K = N, M, N, Z]
    with pytest.raises(ValueError, match="2"):
        swap_consistency(follow, Z_STEPS[:, :1])
    agreeing = swap_consistency(ignoring(torch.zeros(1, 3, dtype=torch.long)), Z_STEPS)
    assert agreeing.own == 1.0 and math.isnan(agreeing.kappa)  # nothing to explain


# ============================================================================ the MI bound
class ExactPosterior(nn.Module):
    """The exact posterior of a Gaussian case: each step observes ``x_k = (z - mu) + tau * eta``
    (``obs``), so each factor is ``N(z - mu; x_k, tau^2)``, and with the coordinator's
    ``N(0, sigma^2)`` as the anchor their product is ``p(z | x, s, v)``."""

    def __init__(self, tau: float):
        super().__init__()
        self.tau = tau

    def factors(self, state, action, obs):
        return obs, torch.full_like(obs, self.tau)


def gaussian_windows(episodes, *, sigma, tau, reveal=True, windows=50, steps=1, n=2, z_dim=2):
    """Broadcast windows of a team whose every step shows ``z - mu`` plus noise of std ``tau``
    (``reveal``), or an independent draw instead (a team whose behaviour ignores z)."""
    g = torch.Generator().manual_seed(0)
    shape = (episodes, windows, n, z_dim)
    loc = 3.0 * torch.randn(shape, generator=g)  # the coordinator's mean, varying with the state
    residual = sigma * torch.randn(shape, generator=g)
    shown = residual if reveal else sigma * torch.randn(shape, generator=g)
    obs = shown.unsqueeze(2) + tau * torch.randn(episodes, windows, steps, n, z_dim, generator=g)
    return dict(
        z=loc + residual,
        loc=loc,
        scale=torch.full(shape, sigma),
        state=torch.zeros(episodes, windows, steps, 1),
        action=torch.zeros(episodes, windows, steps, n, dtype=torch.long),
        obs=obs,
        present=torch.ones(episodes, windows, n, dtype=torch.bool),
    )


def test_the_bound_of_a_known_gaussian_case_hand_computed():
    """sigma = tau = 1, one observation per dimension: I = 0.5 log(1 + sigma^2/tau^2) = 0.5 log 2
    per dimension, which the bound reaches with the exact posterior (2 dimensions per robot).
    With z redrawn independently of what was observed, the same q gives (per dimension, the
    posterior variance v = 1/2, its mean m = x/2 of variance 1/2):
    0.5 log(sigma^2 / v) + 0.5 - 0.5 (sigma^2 + Var m) / v = 0.5 log 2 + 0.5 - 1.5."""
    windows = gaussian_windows(100, sigma=1.0, tau=1.0)
    est = mi_estimate(None, windows, fit_steps=0, posterior_factory=lambda: ExactPosterior(1.0))
    assert est.windows == (75 * 50, 25 * 50)
    assert est.entropy == pytest.approx(2 * 0.5 * math.log(2 * math.pi * math.e), abs=1e-5)
    assert est.bound == pytest.approx(2 * 0.5 * math.log(2.0), abs=0.1)
    assert est.null == pytest.approx(2 * (0.5 * math.log(2.0) + 0.5 - 1.5), abs=0.2)
    assert est.bound == pytest.approx(est.log_q + est.entropy)


def test_a_fitted_posterior_finds_what_the_behaviour_reveals():
    """A posterior of the project's architecture, fitted on 3/4 of the episodes: behaviour that
    shows z - mu lifts the held-out bound well above its floor (z redrawn); behaviour that
    ignores z does not."""
    n, z_dim = 2, 2

    def make():
        return Posterior(
            None,
            n_actions=2,
            z_dim=z_dim,
            hidden=32,
            n_agents=n,
            obs_dim=z_dim,
            state_dim=1,
            combine="product",
        )

    kwargs = dict(sigma=1.0, tau=0.1, steps=2, n=n, z_dim=z_dim)
    shows = mi_estimate(None, gaussian_windows(16, **kwargs), posterior_factory=make)
    ignores = mi_estimate(
        None, gaussian_windows(16, reveal=False, **kwargs), posterior_factory=make
    )
    # the exact posterior would gain z_dim * 0.5 log(1 + sigma^2 / (tau^2 / 1)) = 4.6 nats
    assert shows.bound - shows.null > 1.0
    assert shows.bound > 0.5
    assert abs(ignores.bound - ignores.null) < 0.5
    assert ignores.bound < 0.3


# ============================================================================ on ICCO rollouts
@pytest.fixture(scope="module")
def icco():
    return build_components(method="icco", num_envs=4)


def test_replayed_inputs_give_the_actions_the_agents_took(icco):
    rollout = coordinator_rollouts(icco, seed=3)
    z = rollout["agents", "z"]
    act = agent_actions(icco, rollout)
    torch.testing.assert_close(
        act(z.flatten(0, 1)[None])[0], rollout["agents", "action"].flatten(0, 1)
    )
    # z is drawn around the coordinator's mean, not the mean itself (the measures need the draw)
    loc, _ = icco.coordinator.module.distribution(rollout["state"][:, 0])
    assert not torch.allclose(z[:, 0], loc)


def test_the_measures_are_deterministic_given_a_seed(icco):
    before = torch.get_rng_state()
    a = consistency.measure_coordination(icco, fit_steps=5, seed=1)
    b = consistency.measure_coordination(icco, fit_steps=5, seed=1)
    assert torch.equal(torch.get_rng_state(), before)  # the caller's random stream is untouched
    assert a == b
    assert set(consistency.COLUMNS) <= set(a)
    assert a["mi"]["windows"] == (3 * 36, 36)  # 145-step episodes: 36 whole windows of 4
    assert a["mi_bound"] == pytest.approx(a["mi_log_q"] + a["mi_entropy"])
    assert -1.0 <= a["consistency"] <= 1.0
    c = consistency.measure_coordination(icco, fit_steps=5, seed=2)
    assert c["mi_bound"] != a["mi_bound"]


def test_a_team_without_a_coordinator_is_refused():
    qmix = build_components(method="qmix", num_envs=2)
    with pytest.raises(ValueError, match="coordinator"):
        mi_lower_bound(qmix, fit_steps=1)


def test_summary_columns_pool_checkpoints_and_leave_others_nan():
    summary = [
        {"method": "ICCO", "segment": "episode"},
        {"method": "QMIX", "segment": "episode"},
    ]
    one = {c: 1.0 for c in consistency.COLUMNS}
    three = {c: 3.0 for c in consistency.COLUMNS}
    consistency.add_columns(summary, {"ICCO": [one, three]})
    assert (summary[0]["mi_bound"], summary[0]["mi_bound_std"]) == (2.0, 1.0)
    assert math.isnan(summary[1]["consistency"])
    table = consistency.coordination_table(summary)
    assert "| ICCO | 2.0 ± 1.0 |" in table and "QMIX" not in table


def test_docstring_examples():
    assert doctest.testmod(consistency).failed == 0
