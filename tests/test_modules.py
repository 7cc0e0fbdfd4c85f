"""Behaviour of ICCO's networks: posterior maths, entropy, mixer, encoders, recurrent agent,
coordinator.

Every numeric check compares against either a hand computation on explicit numbers or an
independent implementation (``torch.distributions``); every structural check (masking,
invariance, holding z) is written so that a plausible regression makes it fail.
"""

import math

import pytest
import torch
from torch.distributions import Independent, Normal
from torchrl.envs.utils import ExplorationType, set_exploration_type

from icco_torchrl.envs.layout import ObsLayout
from icco_torchrl.modules import (
    EntityAttentionEncoder,
    Posterior,
    RecurrentQNet,
    combine_log_prob,
    diag_normal_log_prob,
    gaussian_entropy,
    make_mixer,
)
from icco_torchrl.modules.coordinator import Coordinator
from icco_torchrl.modules.posterior import log_prob_terms
from icco_torchrl.training.build import build_components, compose_config

torch.set_num_threads(1)

LOG_2PI = math.log(2 * math.pi)


# ---------------------------------------------------------------------------- Gaussian maths
def test_diag_normal_log_prob_hand_and_torch():
    x = torch.tensor([0.5, -1.0])
    loc = torch.tensor([0.0, 1.0])
    scale = torch.tensor([1.0, 2.0])
    # dim 0: -0.5*0.25 - log 1 - 0.5 log 2pi ; dim 1: -0.5*(2/2)^2 - log 2 - 0.5 log 2pi
    hand = (-0.125 - 0.5 * LOG_2PI) + (-0.5 - math.log(2.0) - 0.5 * LOG_2PI)
    assert diag_normal_log_prob(x, loc, scale).item() == pytest.approx(hand, abs=1e-6)

    g = torch.Generator().manual_seed(0)
    x, loc = torch.randn(4, 3, 5, generator=g), torch.randn(4, 3, 5, generator=g)
    scale = torch.rand(4, 3, 5, generator=g) + 0.1
    ref = Independent(Normal(loc, scale), 1).log_prob(x)
    torch.testing.assert_close(diag_normal_log_prob(x, loc, scale), ref, atol=1e-5, rtol=1e-5)


def _factors():
    """S=1, K=3 factors, N=1 robot, Z=2; the third factor is garbage and masked out."""
    loc = torch.tensor([[[[0.0, 1.0]], [[2.0, 1.0]], [[50.0, -40.0]]]])  # [1, 3, 1, 2]
    scale = torch.tensor([[[[1.0, 1.0]], [[1.0, 2.0]], [[0.01, 0.01]]]])
    mask = torch.tensor([[True, True, False]])
    z = torch.tensor([[[0.5, 1.0]]])  # [1, 1, 2]
    return z, loc, scale, mask


def test_product_of_gaussians_hand_computation():
    z, loc, scale, mask = _factors()
    # dim 0: N(0,1) x N(2,1) -> precision 2, mean 1, var 1/2;
    # z=0.5: -0.5*0.25/0.5 - 0.5*log(2pi*0.5)
    d0 = -0.25 - 0.5 * math.log(math.pi)
    # dim 1: N(1,1) x N(1,4) -> precision 1.25, mean 1, var 0.8; z=1: -0.5*log(2pi*0.8)
    d1 = -0.5 * math.log(2 * math.pi * 0.8)
    out = combine_log_prob(z, loc, scale, mask, "product")
    assert out.shape == (1, 1)
    assert out.item() == pytest.approx(d0 + d1, abs=1e-5)
    # against torch.distributions with the precision-weighted mean and variance
    ref = Independent(
        Normal(torch.tensor([1.0, 1.0]), torch.tensor([0.5, 0.8]).sqrt()), 1
    ).log_prob(z[0, 0])
    assert out.item() == pytest.approx(ref.item(), abs=1e-5)


def test_sum_of_log_likelihoods_hand_computation():
    z, loc, scale, mask = _factors()
    # factor 0: dim0 N(0.5;0,1) = -0.125-c, dim1 N(1;1,1) = -c ;
    # factor 1: dim0 N(0.5;2,1) = -1.125-c, dim1 N(1;1,2) = -log 2 - c ; c = 0.5 log 2pi
    hand = -0.125 - 1.125 - math.log(2.0) - 4 * 0.5 * LOG_2PI
    out = combine_log_prob(z, loc, scale, mask, "sum")
    assert out.item() == pytest.approx(hand, abs=1e-5)
    ref = sum(
        Independent(Normal(loc[0, k, 0], scale[0, k, 0]), 1).log_prob(z[0, 0]) for k in (0, 1)
    )
    assert out.item() == pytest.approx(ref.item(), abs=1e-5)


@pytest.mark.parametrize("combine", ["product", "sum"])
def test_masked_factors_are_ignored(combine):
    g = torch.Generator().manual_seed(1)
    S, K, N, Z = 3, 4, 2, 3
    loc, z = torch.randn(S, K, N, Z, generator=g), torch.randn(S, N, Z, generator=g)
    scale = torch.rand(S, K, N, Z, generator=g) + 0.2
    mask = torch.tensor(
        [[True, True, False, False], [True, False, True, False], [True, True, True, True]]
    )
    out = combine_log_prob(z, loc, scale, mask, combine)
    loc2, scale2 = loc.clone(), scale.clone()
    loc2[~mask] = 1e3 * torch.randn_like(loc2[~mask])
    scale2[~mask] = 1e-3
    torch.testing.assert_close(combine_log_prob(z, loc2, scale2, mask, combine), out)
    # each row equals the same computation on its valid factors only
    for s in range(S):
        keep = mask[s]
        if combine == "product":
            prec = (1 / scale[s, keep] ** 2).sum(0)
            mean = (loc[s, keep] / scale[s, keep] ** 2).sum(0) / prec
            ref = Independent(Normal(mean, prec.rsqrt()), 1).log_prob(z[s])
        else:
            ref = (
                Independent(Normal(loc[s, keep], scale[s, keep]), 1)
                .log_prob(z[s].unsqueeze(0))
                .sum(0)
            )
        torch.testing.assert_close(out[s], ref, atol=1e-4, rtol=1e-5)


def test_log_prob_terms_are_the_clamped_terms_hand_computed():
    """ce_clamp's terms: one per dimension of the product (its sum is the product's log q), one per
    step and dimension of the sum (masked steps 0)."""
    z, loc, scale, mask = _factors()
    product = log_prob_terms(z, loc, scale, mask, "product")
    assert product.shape == (1, 1, 1, 2)
    d0, d1 = -0.25 - 0.5 * math.log(math.pi), -0.5 * math.log(2 * math.pi * 0.8)
    torch.testing.assert_close(product.flatten(), torch.tensor([d0, d1]))
    summed = log_prob_terms(z, loc, scale, mask, "sum")
    c = 0.5 * LOG_2PI
    hand = torch.tensor([[-0.125 - c, -c], [-1.125 - c, -math.log(2.0) - c], [0.0, 0.0]])
    torch.testing.assert_close(summed[0, :, 0], hand)
    for combine in ("product", "sum"):
        torch.testing.assert_close(
            log_prob_terms(z, loc, scale, mask, combine).sum((1, -1)),
            combine_log_prob(z, loc, scale, mask, combine),
        )
    # a sharp factor's density exceeds 1: the term COPA's clamp sets to 0
    sharp = log_prob_terms(z, loc, torch.full_like(scale, 0.05), mask, "sum")
    assert sharp[0, 0, 0, 1] > 0


def test_combine_rejects_unknown_mode():
    z, loc, scale, mask = _factors()
    with pytest.raises(ValueError, match="combine"):
        combine_log_prob(z, loc, scale, mask, "mean")


def test_posterior_scores_its_own_factors():
    layout = ObsLayout(
        n_agents=2,
        n_waypoints=2,
        own_dim=4,
        n_entities=2,
        entity_dim=3,
        state_tokens=3,
        state_token_dim=4,
    )
    torch.manual_seed(0)
    post = Posterior(layout, n_actions=5, z_dim=3, hidden=8, combine="product")
    S, T, N = 2, 4, 2
    state, obs = torch.randn(S, T, layout.state_dim), torch.randn(S, T, N, layout.obs_dim)
    action, z = torch.randint(0, 5, (S, T, N)), torch.randn(S, N, 3)
    mask = torch.tensor([[True, True, True, False], [True, False, False, False]])
    loc, scale = post.factors(state, action, obs)
    assert loc.shape == scale.shape == (S, T, N, 3)
    torch.testing.assert_close(
        post(z, state, action, obs, mask), combine_log_prob(z, loc, scale, mask, "product")
    )
    torch.testing.assert_close(
        post.log_prob_terms(z, state, action, obs, mask).sum((1, -1)),
        post(z, state, action, obs, mask),
    )
    # later factors read only their own step: changing a masked step's observation changes nothing
    obs2 = obs.clone()
    obs2[0, 3] += 5.0
    torch.testing.assert_close(
        post(z, state, action, obs2, mask), post(z, state, action, obs, mask)
    )


def test_gaussian_entropy_closed_form_and_torch():
    scale = torch.tensor([1.0, math.e])
    assert gaussian_entropy(scale).item() == pytest.approx(
        math.log(2 * math.pi * math.e) + 1.0, abs=1e-6
    )
    g = torch.Generator().manual_seed(2)
    scale = torch.rand(5, 3, 7, generator=g) * 2 + 0.01
    ref = Normal(torch.zeros_like(scale), scale).entropy().sum(-1)
    torch.testing.assert_close(gaussian_entropy(scale), ref, atol=1e-5, rtol=1e-5)
    closed = 0.5 * 7 * math.log(2 * math.pi * math.e) + scale.log().sum(-1)
    torch.testing.assert_close(gaussian_entropy(scale), closed, atol=1e-5, rtol=1e-5)


# ---------------------------------------------------------------------------- mixer
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_qmixer_is_monotone_in_every_local_q(seed):
    torch.manual_seed(seed)
    N, D = 3, 7
    mixer = make_mixer(D, N, kind="qmix", embed_dim=8).module
    with torch.no_grad():
        for p in mixer.parameters():
            p.normal_(0.0, 1.0)  # random weights, negative ones included
    q = (torch.randn(4, 5, N, 1) * 5).requires_grad_(True)  # leading [S, T]
    state = torch.randn(4, 5, D)
    out = mixer(q, state)
    assert out.shape == (4, 5, 1)
    (grad,) = torch.autograd.grad(out.sum(), q)  # rows are independent: d out[s,t] / d q[s,t,i]
    assert (grad >= 0).all(), grad.min()
    assert (grad > 0).any()
    # and a direct check: raising one agent's Q never lowers Q_tot
    bumped = q.detach().clone()
    bumped[..., 1, :] += 1.0
    assert (mixer(bumped, state) >= out.detach() - 1e-5).all()


# ---------------------------------------------------------------------------- encoders
def _encoder_input(g, B=6, own=3, E=4, F=5):
    x = torch.randn(B, own + E * F, generator=g)
    tokens = x[:, own:].view(B, E, F)
    tokens[..., -1] = (torch.rand(B, E, generator=g) > 0.4).float()
    tokens[0, :, -1] = torch.tensor([1.0, 0.0, 1.0, 0.0])
    return x


def test_entity_attention_ignores_invisible_tokens():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(3)
    enc = EntityAttentionEncoder(own_dim=3, n_entities=4, entity_dim=5, hidden=16, flag_column=4)
    x = _encoder_input(g)
    out = enc(x)
    tokens = x[:, 3:].view(6, 4, 5)
    invisible = tokens[..., -1] == 0
    assert invisible.any() and (~invisible).any()
    x2 = x.clone()
    t2 = x2[:, 3:].view(6, 4, 5)
    t2[..., :-1] = torch.where(
        invisible[..., None], 100 * torch.randn(6, 4, 4, generator=g), t2[..., :-1]
    )
    torch.testing.assert_close(enc(x2), out)
    # a visible token does matter (the test can fail)
    x3 = x.clone()
    x3[0, 3:8] += 3.0  # entity 0 of row 0 is visible
    assert not torch.allclose(enc(x3)[0], out[0])
    # nothing visible: the read-out is zero, so the output equals the one with all tokens zeroed
    x4 = x.clone()
    x4[:, 3:].view(6, 4, 5)[..., -1] = 0
    x5 = x4.clone()
    x5[:, 3:] = 0
    torch.testing.assert_close(enc(x4), enc(x5))


def test_entity_attention_is_permutation_invariant():
    torch.manual_seed(1)
    g = torch.Generator().manual_seed(4)
    enc = EntityAttentionEncoder(own_dim=3, n_entities=4, entity_dim=5, hidden=16, flag_column=4)
    x = _encoder_input(g)
    perm = torch.tensor([2, 0, 3, 1])
    xp = x.clone()
    xp[:, 3:] = x[:, 3:].view(6, 4, 5)[:, perm].reshape(6, 20)
    torch.testing.assert_close(enc(xp), enc(x), atol=1e-5, rtol=1e-5)


# ---------------------------------------------------------------------------- recurrent agent
LAYOUT = ObsLayout(
    n_agents=3,
    n_waypoints=2,
    own_dim=9,
    n_entities=4,
    entity_dim=5,
    state_tokens=4,
    state_token_dim=6,
)


def _agent_inputs(g, B=2, L=6):
    N = LAYOUT.n_agents
    obs = torch.randn(B, L, N, LAYOUT.obs_dim, generator=g)
    obs[..., LAYOUT.own_dim :].view(B, L, N, 4, 5)[..., -1] = (
        torch.rand(B, L, N, 4, generator=g) > 0.5
    ).float()
    prev = torch.randint(0, 5, (B, L, N), generator=g)
    z = torch.randn(B, L, N, 4, generator=g)
    state = torch.randn(B, L, LAYOUT.state_dim, generator=g)
    h0 = torch.randn(B, N, 16, generator=g)
    return obs, prev, z, state, h0


@pytest.mark.parametrize(
    "encoder,full_state,z_dim",
    [("attention", False, 4), ("mlp", True, 0), ("attention", True, 4)],
)
def test_agent_one_step_forward_equals_sequence(encoder, full_state, z_dim):
    torch.manual_seed(0)
    net = RecurrentQNet(
        LAYOUT,
        n_actions=5,
        hidden=16,
        z_dim=z_dim,
        full_state=full_state,
        encoder=encoder,
    )
    obs, prev, z, state, h0 = _agent_inputs(torch.Generator().manual_seed(5))
    z = z if z_dim else None
    B, L = obs.shape[:2]
    seq = net.sequence(obs, prev, h0, z=z, state=state if full_state else None)
    assert seq.shape == (B, L, 3, 5)
    h, steps = h0, []
    step_count = torch.full((B, 1), 3)  # never a reset
    for t in range(L):
        q, h = net(
            obs[:, t],
            prev[:, t],
            h,
            step_count,
            z=None if z is None else z[:, t],
            state=state[:, t] if full_state else None,
        )
        steps.append(q)
    torch.testing.assert_close(torch.stack(steps, 1), seq, atol=1e-5, rtol=1e-5)
    # the hidden state carries information: another h0 gives other values after step 0
    other = net.sequence(obs, prev, torch.zeros_like(h0), z=z, state=state if full_state else None)
    assert not torch.allclose(other, seq)


def test_agent_hidden_restarts_at_step_zero():
    torch.manual_seed(0)
    net = RecurrentQNet(LAYOUT, n_actions=5, hidden=16, z_dim=4)
    obs, prev, z, _, h = _agent_inputs(torch.Generator().manual_seed(6), B=4, L=1)
    obs, prev, z = obs[:, 0], prev[:, 0], z[:, 0]
    step_count = torch.tensor([[0], [5], [0], [1]])
    q, h_new = net(obs, prev, h, step_count, z=z)
    q0, h0_new = net(obs, prev, torch.zeros_like(h), step_count, z=z)
    restart = step_count.squeeze(-1) == 0
    torch.testing.assert_close(q[restart], q0[restart])
    torch.testing.assert_close(h_new[restart], h0_new[restart])
    assert not torch.allclose(q[~restart], q0[~restart])
    # the returned hidden state is the GRU output fed to the next step
    q1, _ = net(obs, prev, h_new, torch.full_like(step_count, 7), z=z)
    seq = net.sequence(
        torch.stack([obs, obs], 1),
        torch.stack([prev, prev], 1),
        h * (~restart)[:, None, None],
        z=torch.stack([z, z], 1),
    )
    torch.testing.assert_close(q1, seq[:, 1], atol=1e-5, rtol=1e-5)


# ------------------------------------------------------------------ coordinator in rollouts
@pytest.fixture(scope="module")
def icco_short_episodes():
    torch.manual_seed(0)
    cfg = compose_config(["method=icco", "env.params.max_steps=10"])
    return build_components(cfg, num_envs=4)


def _blocks(step_count, period):
    """Id of the hold period each step belongs to, per env: increments at every broadcast step."""
    return torch.cumsum((step_count % period == 0).long(), dim=1)


def test_coordinator_holds_z_for_period_steps(icco_short_episodes):
    parts = icco_short_episodes
    env, policy = parts["env"], parts["policy"]
    period = parts["coordinator"].module.period
    env.set_seed(0)
    with torch.no_grad():
        ro = env.rollout(26, policy, break_when_any_done=False)
    sc = ro["step_count"].squeeze(-1)
    assert (sc == 0).sum() >= 2 * ro.shape[0], "the rollout should cross episode ends"
    z, noise = ro["agents", "z"], ro["agents", "z_noise"]
    blocks = _blocks(sc, period)
    same_block = blocks[:, 1:] == blocks[:, :-1]
    dz = (z[:, 1:] - z[:, :-1]).abs().flatten(2).amax(-1)
    assert (dz[same_block] == 0).all(), "z must be held within a hold period"
    assert (dz[~same_block] > 1e-4).all(), "z must be redrawn at every broadcast step"
    dn = (noise[:, 1:] - noise[:, :-1]).abs().flatten(2).amax(-1)
    assert (dn[same_block] == 0).all()
    # at broadcast steps z is the reparameterised draw loc + scale * noise (and not the mean)
    fresh = sc % period == 0
    with torch.no_grad():
        loc, scale = parts["coordinator"].module.distribution(ro["state"])
    torch.testing.assert_close(z[fresh], (loc + scale * noise)[fresh])
    assert not torch.allclose(z[fresh], loc[fresh])


def test_coordinator_emits_mean_when_deterministic(icco_short_episodes):
    parts = icco_short_episodes
    env, policy = parts["env"], parts["policy"]
    period = parts["coordinator"].module.period
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        ro = env.rollout(14, policy, break_when_any_done=False)
    sc = ro["step_count"].squeeze(-1)
    z = ro["agents", "z"]
    with torch.no_grad():
        loc, _ = parts["coordinator"].module.distribution(ro["state"])
    fresh = sc % period == 0
    torch.testing.assert_close(z[fresh], loc[fresh])
    # in between, the mean computed at the block's broadcast step is held
    blocks = _blocks(sc, period)
    for b in range(sc.shape[0]):
        for t in range(sc.shape[1]):
            start = int((fresh[b, : t + 1].nonzero()[-1]).item())
            assert blocks[b, start] == blocks[b, t]
            torch.testing.assert_close(z[b, t], loc[b, start])
    assert (ro["agents", "z_noise"] == 0).all()


def test_coordinator_redraws_only_envs_at_a_broadcast_step():
    torch.manual_seed(0)
    coord = Coordinator(LAYOUT, z_dim=4, hidden=8, period=4, init_logvar=0.0)
    B, N = 4, LAYOUT.n_agents
    state = torch.randn(B, LAYOUT.state_dim)
    z_prev, noise_prev = torch.randn(B, N, 4), torch.randn(B, N, 4)
    with torch.no_grad():
        loc, scale = coord.distribution(state)
        # envs out of phase: only env 0 (step 8) redraws, the others hold exactly
        z, noise, sent = coord(state, torch.tensor([[8], [1], [2], [7]]), z_prev, noise_prev)
        assert sent.squeeze(-1).tolist() == [[True] * N] + [[False] * N] * 3
        torch.testing.assert_close(z[0], loc[0] + scale[0] * noise[0])
        assert not torch.equal(noise[0], noise_prev[0])
        assert torch.equal(z[1:], z_prev[1:]) and torch.equal(noise[1:], noise_prev[1:])
        # no env at a broadcast step (the network is skipped): everything held
        z, noise, sent = coord(state, torch.tensor([[1], [2], [3], [5]]), z_prev, noise_prev)
        assert torch.equal(z, z_prev) and torch.equal(noise, noise_prev) and not sent.any()


def test_coordinator_rejects_bad_period():
    with pytest.raises(ValueError, match="period"):
        Coordinator(LAYOUT, z_dim=4, hidden=8, period=0, init_logvar=0.0)


# ---------------------------------------------------------------------------- TensorModule
def test_tensor_module_writes_what_tensordict_module_writes():
    from tensordict import TensorDict
    from tensordict.nn import TensorDictModule

    from icco_torchrl.modules.tdmodule import TensorModule

    def two(x):
        return x + 1, (x * 2).sum(-1)

    keys = dict(in_keys=[("a", "x")], out_keys=[("a", "y"), ("next", "s")])
    td = TensorDict({"a": {"x": torch.arange(6.0).view(2, 3)}}, [2])
    ours, ref = TensorModule(two, **keys)(td.clone()), TensorDictModule(two, **keys)(td.clone())
    assert set(ours.keys(True, True)) == set(ref.keys(True, True))
    for key in ref.keys(True, True):
        torch.testing.assert_close(ours.get(key), ref.get(key))
    torch.testing.assert_close(ours["next", "s"], torch.tensor([6.0, 24.0]))
    # a non-inplace module still returns a fresh tensordict with only the outputs
    out = TensorModule(two, inplace=False, **keys)(td)
    assert ("a", "x") not in out.keys(True, True) and ("a", "y") in out.keys(True, True)


# ============================================================================ relative state tokens
def _relative_scene():
    from icco_torchrl.envs import ResourceCollectionEnv

    env = ResourceCollectionEnv(num_envs=1, seed=0)
    env.reset()
    env.pos[0] = torch.tensor([[1.0, 0.0], [-1.0, -1.0], [2.0, 2.0]])
    env.vel.zero_()
    env.res_pos[0] = torch.tensor(
        [[1.0, 1.0], [3.0, 0.0], [-2.0, 2.0], [0.5, -2.5], [-3.0, -3.0], [2.5, -1.0]]
    )
    env.inv_active[0] = False
    env.waypoints = env.pos.unsqueeze(-2).expand(1, 3, env.n_waypoints, 2) + 0.5
    return env, env._observe()[1]


def test_relative_tokens_hand_built_scene():
    from icco_torchrl.modules.relative import relative_dims, relative_tokens

    env, state = _relative_scene()
    L = env.layout
    own_dim, E, D = relative_dims(L)
    x = relative_tokens(state, L)[0]  # [N, own + E * D]
    own, tok = x[:, :own_dim], x[:, own_dim:].unflatten(-1, (E, D))
    N = L.n_agents
    torch.testing.assert_close(own[0, :2], torch.tensor([1.0, 0.0]))
    torch.testing.assert_close(
        own[0, 6:], torch.full((2 * L.n_waypoints,), 0.5)
    )  # own waypoints, relative
    res0 = tok[0, N]  # robot 0 sees resource 0
    torch.testing.assert_close(res0[:3], torch.tensor([0.0, 1.0, 1.0]))  # dx, dy, distance
    assert res0[5:9].tolist() == [0.0, 1.0, 0.0, 0.0] and res0[-1] == 1  # type resource, present
    home = tok[0, -1]
    torch.testing.assert_close(home[:3], torch.tensor([-1.0, 0.0, 1.0]))
    assert home[5:9].tolist() == [0.0, 0.0, 0.0, 1.0]
    assert tok[:, N + L.n_agents * 0 + env.n_resources, -1].eq(0).all()  # inactive invader: masked
    assert [tok[i, i, -1].item() for i in range(N)] == [0.0] * N  # a robot is not its own entity
    other = tok[0, 1]  # robot 1 seen from robot 0, its waypoints too
    torch.testing.assert_close(other[:2], torch.tensor([-2.0, -1.0]))
    torch.testing.assert_close(
        other[-1 - 2 * L.n_waypoints : -1], torch.tensor([-1.5, -0.5] * L.n_waypoints)
    )


def test_relative_encoder_ignores_resource_order():
    from icco_torchrl.modules.relative import RelativeStateEncoder

    env, state = _relative_scene()
    L = env.layout
    enc = RelativeStateEncoder(L, hidden=16)
    tok = state.unflatten(-1, (L.state_tokens, L.state_token_dim)).clone()
    perm = torch.tensor([0, 1, 2] + [3 + i for i in (5, 2, 0, 4, 1, 3)] + [9])
    shuffled = tok[:, perm].flatten(-2)
    torch.testing.assert_close(enc(state), enc(shuffled), atol=1e-6, rtol=1e-6)
    assert not torch.allclose(enc(state)[:, 0], enc(state)[:, 1])  # robots get their own views


def test_guided_exploration_takes_the_guides_actions_with_probability_eps():
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from icco_torchrl.envs.reference_policies import make_reference_policy
    from icco_torchrl.modules.policy import exploration_module, make_policy
    from icco_torchrl.training.build import build_components

    parts = build_components(method="qmix", num_envs=16)
    env = parts["env"]
    guide = make_reference_policy("heuristic", env)
    policy = make_policy(parts["agent"], env.full_action_spec_unbatched, guide=guide)
    explore = exploration_module(policy)
    td = env.reset()
    with torch.no_grad():
        wanted = guide(td.clone())["agents", "action"]
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            best = policy(td.clone())["agents", "action"]
        assert (wanted != best).any()  # the test can tell them apart
        for eps, expected in ((1.0, wanted), (0.0, best)):
            explore.eps.fill_(eps)
            with set_exploration_type(ExplorationType.RANDOM):
                assert torch.equal(policy(td.clone())["agents", "action"], expected)
        explore.eps.fill_(1.0)
        with set_exploration_type(ExplorationType.DETERMINISTIC):  # evaluation never asks the guide
            assert torch.equal(policy(td.clone())["agents", "action"], best)
        explore.eps.fill_(0.5)
        torch.manual_seed(0)
        with set_exploration_type(ExplorationType.RANDOM):
            got = torch.stack([policy(td.clone())["agents", "action"] for _ in range(20)])
        from_guide = (got == wanted).float().mean().item()
        # Half the agents follow the guide, the others act greedily (and agree with it where
        # the greedy action is the guide's): 960 draws, so 0.1 is about 6 standard deviations.
        agree = (best == wanted).float().mean().item()
        assert abs(from_guide - (0.5 + 0.5 * agree)) < 0.1, (from_guide, agree)


# ---------------------------------------------------------------------------- waypoint features
def test_path_features_give_the_direction_the_instruction_reward_scores():
    from icco_torchrl.envs._kernels import instruction_reward
    from icco_torchrl.modules.waypoint_features import path_features

    g = torch.Generator().manual_seed(3)
    rel = torch.randn(64, 4, 2, generator=g)  # K = 4 waypoints relative to the robot
    disp = torch.randn(64, 2, generator=g) * 0.2
    f = path_features(rel)
    # hand-picked: the nearest waypoint is the one of least norm
    nearest = rel[torch.arange(64), rel.norm(dim=-1).argmin(-1)]
    torch.testing.assert_close(f[:, :2], nearest)
    torch.testing.assert_close(f[:, 2:].norm(dim=-1), torch.ones(64))
    # e_cossim of the env's reward (dist_coef 0) is the cosine of the displacement with the feature
    # direction
    zero = torch.zeros(64, 2)
    r = instruction_reward(
        rel.permute(1, 2, 0).unsqueeze(0), zero.t().unsqueeze(0), disp.t().unsqueeze(0), 1.0, 0.0
    )  # batch-last layout [N=1, K, 2, B]
    cos = torch.nn.functional.cosine_similarity(disp, f[:, 2:], dim=-1)
    torch.testing.assert_close(r.squeeze(0), cos, atol=1e-5, rtol=1e-5)


def test_path_features_tie_goes_to_lower_index_and_zero_path_is_zero():
    from icco_torchrl.modules.waypoint_features import path_features

    rel = torch.tensor([[[0.0, 1.0], [1.0, 0.0], [1.0, 0.0], [3.0, 3.0]]])
    f = path_features(rel)
    torch.testing.assert_close(f, torch.tensor([[0.0, 1.0, 2**-0.5, -(2**-0.5)]]))
    same = torch.tensor([[[0.5, 0.0], [0.5, 0.0], [2.0, 2.0]]])
    torch.testing.assert_close(path_features(same), torch.tensor([[0.5, 0.0, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="K>=2"):
        path_features(torch.zeros(3, 1, 2))


@pytest.mark.parametrize(
    "full_state,state_encoder", [(False, "flat"), (True, "relative"), (True, "flat")]
)
def test_agent_reads_waypoint_features(full_state, state_encoder):
    from icco_torchrl.envs import ResourceCollectionEnv

    env = ResourceCollectionEnv(num_envs=2, seed=0)
    torch.manual_seed(0)
    net = RecurrentQNet(
        env.layout,
        n_actions=5,
        hidden=16,
        z_dim=4,
        full_state=full_state,
        state_encoder=state_encoder,
        waypoint_features=True,
    )
    td = env.reset()
    obs, state = (
        td["agents", "observation"].unsqueeze(1),
        td["state"].unsqueeze(1),
    )  # segments of length 1
    prev, z, h0 = (
        torch.zeros(2, 1, 3, dtype=torch.long),
        torch.randn(2, 1, 3, 4),
        torch.randn(2, 3, 16),
    )
    s = state if full_state else None
    seq = net.sequence(obs, prev, h0, z=z, state=s)
    q, _ = net.step(obs[:, 0], prev[:, 0], h0, z[:, 0], None if s is None else s[:, 0])
    torch.testing.assert_close(q, seq[:, 0], atol=1e-5, rtol=1e-5)
    # the features are read: putting waypoint 0 on the robot (now the nearest) changes Q
    moved = obs.clone()
    moved[..., 5:7] = 0.0
    assert not torch.allclose(net.sequence(moved, prev, h0, z=z, state=s), seq)
    with pytest.raises(ValueError, match="needs a layout"):
        RecurrentQNet(None, n_actions=5, hidden=16, obs_dim=8, waypoint_features=True)


def test_z_reaches_the_q_head_of_its_own_step_only():
    # z joins the Q head (COPA), not the GRU: changing z at step 0 alone changes Q at step 0 only
    obs, prev, z, state, h0 = _agent_inputs(torch.Generator().manual_seed(5))
    other = z.clone()
    other[:, 0] += 1.0
    torch.manual_seed(0)
    net = RecurrentQNet(LAYOUT, n_actions=5, hidden=16, z_dim=4)
    q, q_other = net.sequence(obs, prev, h0, z=z), net.sequence(obs, prev, h0, z=other)
    assert not torch.allclose(q[:, 0], q_other[:, 0])
    assert torch.allclose(q[:, 1], q_other[:, 1])


def test_layer_norm_makes_the_agent_blind_to_the_scale_of_its_embedding():
    """With ``layer_norm`` the GRU's input is normalised: scaling the embedding (weights, bias and
    previous-action rows) by 3 leaves Q unchanged; without it, Q changes. One step equals the
    sequence's first step either way."""
    from icco_torchrl.envs import ResourceCollectionEnv

    env = ResourceCollectionEnv(num_envs=2, seed=0)
    td = env.reset()
    obs = td["agents", "observation"].unsqueeze(1)
    prev, h0 = torch.zeros(2, 1, 3, dtype=torch.long), torch.randn(2, 3, 16)
    for layer_norm in (True, False):
        torch.manual_seed(0)
        net = RecurrentQNet(env.layout, n_actions=5, hidden=16, layer_norm=layer_norm)
        assert any(isinstance(m, torch.nn.LayerNorm) for m in net.modules()) == layer_norm
        q = net.sequence(obs, prev, h0)
        torch.testing.assert_close(net.step(obs[:, 0], prev[:, 0], h0)[0], q[:, 0])
        with torch.no_grad():
            for p in (net.embed.weight, net.embed.bias, net.prev_action_embed.weight):
                p.mul_(3.0)
        scaled = net.sequence(obs, prev, h0)
        if layer_norm:
            torch.testing.assert_close(scaled, q, atol=1e-4, rtol=1e-4)
        else:
            assert not torch.allclose(scaled, q, atol=1e-3)
