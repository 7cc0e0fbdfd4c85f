"""Behaviour of ICCOLoss, the target updaters and the segment cutter.

The TD target is checked against hand-computed numbers with stand-in networks (a Q table and
a sum mixer); gradients, recurrent replay and segment cutting are checked on real rollouts of
the resource-collection env.
"""

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from icco_torchrl.modules.coordinator import Coordinator, gaussian_entropy
from icco_torchrl.objectives import ICCOLoss, NonFiniteLossError, make_target_updater, total_loss
from icco_torchrl.objectives.inputs import assemble
from icco_torchrl.training.build import build_components, compose_config
from icco_torchrl.training.segments import SegmentCutter

torch.set_num_threads(1)


# ============================================================================ stand-in networks
class TableAgent(nn.Module):
    """Q(obs) = table[obs[..., 0]]: a learnable lookup keyed by an integer id in the observation."""

    hidden, z_dim, full_state = 4, 0, False

    def __init__(self, table):
        super().__init__()
        self.table = nn.Parameter(torch.as_tensor(table, dtype=torch.float32).clone())

    def sequence(self, obs, prev_action, hidden0, z=None, state=None):
        assert hidden0.shape[-1] == self.hidden and z is None and state is None
        return self.table[obs[..., 0].long()]


class SumMixer(nn.Module):
    def forward(self, q, state):
        return q.sum(-2)


def table_loss(online, target, *, gamma, double_q, td_lambda=0.0):
    agent = TensorDictModule(
        TableAgent(online),
        in_keys=[("agents", "observation")],
        out_keys=[("agents", "action_value")],
    )
    mixer = TensorDictModule(
        SumMixer(),
        in_keys=[("agents", "chosen_action_value"), "state"],
        out_keys=["chosen_action_value"],
    )
    loss = ICCOLoss(
        agent,
        mixer,
        gamma=gamma,
        double_q=double_q,
        td_lambda=td_lambda,
        ce_coef=0.0,
        entropy_coef=0.0,
    )
    loss.target_agent_params["module", "table"].data.copy_(
        torch.as_tensor(target, dtype=torch.float32)
    )
    return loss


def segment_batch(ids, actions, rewards, terminated=None, mask=None):
    """Segments from observation ids ``[S, T+1, N]`` (step k reads ids[:, k], its next step
    ids[:, k+1])."""
    ids = torch.as_tensor(ids, dtype=torch.float32)
    S, T1, N = ids.shape
    T = T1 - 1
    obs = ids.unsqueeze(-1).expand(S, T1, N, 2).clone()  # feature 0: the id, feature 1: copy
    if terminated is None:
        terminated = torch.zeros(S, T, 1, dtype=torch.bool)
    terminated = torch.as_tensor(terminated).reshape(S, T, 1)
    td = TensorDict(
        {
            "agents": TensorDict(
                {
                    "observation": obs[:, :T],
                    "action": torch.as_tensor(actions).reshape(S, T, N),
                    "prev_action": torch.zeros(S, T, N, dtype=torch.long),
                    "rnn_hidden": torch.zeros(S, T, N, 4),
                },
                [S, T, N],
            ),
            "state": torch.zeros(S, T, 3),
            "step_count": torch.arange(T).expand(S, T).unsqueeze(-1).clone(),
            "next": TensorDict(
                {
                    "agents": TensorDict({"observation": obs[:, 1:]}, [S, T, N]),
                    "state": torch.zeros(S, T, 3),
                    "reward": torch.as_tensor(rewards, dtype=torch.float32).reshape(S, T, 1),
                    "done": terminated.clone(),
                    "terminated": terminated,
                },
                [S, T],
            ),
        },
        [S, T],
    )
    if mask is not None:
        td["mask"] = torch.as_tensor(mask).reshape(S, T)
    return td


# Online / target tables over 6 ids and 2 actions (numbers chosen so the two argmaxes differ).
Q_ONLINE = [[1, 2], [3, 0], [0, 5], [2, 1], [4, 1], [0, 2]]
Q_TARGET = [[0, 0], [0, 0], [1, 3], [2, 6], [2, 7], [5, 1]]
IDS = [[[0, 1], [2, 3], [4, 5]]]  # S=1, T=2, N=2
ACTIONS = [[[1, 0], [0, 1]]]
REWARDS = [[1.0, -3.0]]
# chosen: step 0 = Qo[0][1] + Qo[1][0] = 5 ; step 1 = Qo[2][0] + Qo[3][1] = 1. gamma = 0.5.
# double-Q: step 0 -> argmax Qo[2]=1, Qo[3]=0 -> Qt[2][1] + Qt[3][0] = 3 + 2 = 5
#             -> y0 = 1 + 2.5 = 3.5
#           step 1 -> argmax Qo[4]=0, Qo[5]=1 -> Qt[4][0] + Qt[5][1] = 2 + 1 = 3
#             -> y1 = -3 + 1.5 = -1.5
# max-Q:    step 0 -> 3 + 6 = 9 -> y0 = 5.5 ; step 1 -> 7 + 5 = 12 -> y1 = 3
CASES = [
    # double_q, terminated, mask, expected loss_td
    (True, None, None, ((5 - 3.5) ** 2 + (1 + 1.5) ** 2) / 2),  # 4.25
    (False, None, None, ((5 - 5.5) ** 2 + (1 - 3) ** 2) / 2),  # 2.125
    (True, [[False, True]], None, ((5 - 3.5) ** 2 + (1 + 3) ** 2) / 2),  # y1 = r1 = -3: 9.125
    (
        True,
        [[True, False]],
        [[True, True]],
        ((5 - 1) ** 2 + (1 + 1.5) ** 2) / 2,
    ),  # y0 = r0 = 1: 11.125
    (
        True,
        [[True, False]],
        None,
        (5 - 1) ** 2,
    ),  # no mask: derived from done, step 1 (after the end) dropped
    (True, None, [[True, False]], (5 - 3.5) ** 2),  # only step 0: 2.25
    (True, None, [[False, True]], (1 + 1.5) ** 2),  # only step 1: 6.25
    (False, [[False, True]], [[True, True]], ((5 - 5.5) ** 2 + (1 + 3) ** 2) / 2),  # 8.125
]


@pytest.mark.parametrize("double_q,terminated,mask,expected", CASES)
def test_td_target_hand_computed(double_q, terminated, mask, expected):
    loss = table_loss(Q_ONLINE, Q_TARGET, gamma=0.5, double_q=double_q)
    out = loss(segment_batch(IDS, ACTIONS, REWARDS, terminated, mask))
    assert out["loss_td"].item() == pytest.approx(expected, abs=1e-6)
    assert "loss_ce" not in out.keys()
    # gradient reaches only the online table, at the chosen entries: d/dQ = 2 (q_tot - y) / n_valid
    out["loss_td"].backward()
    grad = loss.agent_params["module", "table"].grad
    assert grad is not None and loss.target_agent_params["module", "table"].grad is None
    assert grad[0, 0] == 0 and grad[2, 1] == 0 and grad[4:].abs().sum() == 0


# TD(lambda), double-Q, gamma 0.5: bootstraps 5 (step 0) and 3 (step 1) as above.
# lambda 0.5: y1 = -3 + 0.5 * 3 = -1.5; y0 = 1 + 0.5 * (0.5 * 5 + 0.5 * y1) = 1.875.
# lambda 1, terminated at step 1: y1 = -3; y0 = 1 + 0.5 * y1 = -0.5.
# an episode end after step 0 (mask [T, F]) cuts the return: y0 = 1 + 0.5 * 5 = 3.5.
LAMBDA_CASES = [
    (0.5, None, None, ((5 - 1.875) ** 2 + (1 + 1.5) ** 2) / 2),
    (1.0, [[False, True]], None, ((5 + 0.5) ** 2 + (1 + 3) ** 2) / 2),
    (0.5, None, [[True, False]], (5 - 3.5) ** 2),
    (0.0, None, None, ((5 - 3.5) ** 2 + (1 + 1.5) ** 2) / 2),
]


@pytest.mark.parametrize("lam,terminated,mask,expected", LAMBDA_CASES)
def test_td_lambda_target_hand_computed(lam, terminated, mask, expected):
    loss = table_loss(Q_ONLINE, Q_TARGET, gamma=0.5, double_q=True, td_lambda=lam)
    out = loss(segment_batch(IDS, ACTIONS, REWARDS, terminated, mask))
    assert out["loss_td"].item() == pytest.approx(expected, abs=1e-6)


def test_td_lambda_out_of_range_is_refused():
    with pytest.raises(ValueError, match="td_lambda"):
        table_loss(Q_ONLINE, Q_TARGET, gamma=0.5, double_q=True, td_lambda=1.5)


def test_td_gradient_hand_computed():
    loss = table_loss(Q_ONLINE, Q_TARGET, gamma=0.5, double_q=True)
    loss(segment_batch(IDS, ACTIONS, REWARDS))["loss_td"].backward()
    grad = loss.agent_params["module", "table"].grad
    expected = torch.zeros(6, 2)
    expected[0, 1] = expected[1, 0] = 2 * (5 - 3.5) / 2  # step 0 chosen entries
    expected[2, 0] = expected[3, 1] = 2 * (1 + 1.5) / 2  # step 1 chosen entries
    torch.testing.assert_close(grad, expected)


def _reference_td(ids, actions, rewards, terminated, mask, q_on, q_tg, gamma, double_q):
    """Plain-python TD loss for the table agent and sum mixer."""
    q_on = torch.as_tensor(q_on, dtype=torch.float64).tolist()
    q_tg = torch.as_tensor(q_tg, dtype=torch.float64).tolist()
    total, count = 0.0, 0
    for s in range(len(ids)):
        for k in range(len(ids[s]) - 1):
            if not mask[s][k]:
                continue
            chosen = sum(q_on[ids[s][k][i]][actions[s][k][i]] for i in range(len(ids[s][k])))
            boot = 0.0
            for nid in ids[s][k + 1]:
                src = q_on[nid] if double_q else q_tg[nid]
                a = max(range(len(src)), key=lambda j: src[j])
                boot += q_tg[nid][a]
            y = rewards[s][k] + (0.0 if terminated[s][k] else gamma * boot)
            total += (chosen - y) ** 2
            count += 1
    return total / count


@pytest.mark.parametrize("double_q", [True, False])
def test_td_target_random_batch_matches_reference(double_q):
    g = torch.Generator().manual_seed(0)
    S, T, N, A, n_ids = 2, 5, 3, 4, 20
    q_on, q_tg = torch.randn(n_ids, A, generator=g), torch.randn(n_ids, A, generator=g)
    ids = torch.randint(0, n_ids, (S, T + 1, N), generator=g)
    actions = torch.randint(0, A, (S, T, N), generator=g)
    rewards = torch.randn(S, T, generator=g)
    terminated = torch.zeros(S, T, dtype=torch.bool)
    terminated[0, 2] = True
    mask = torch.ones(S, T, dtype=torch.bool)
    mask[0, 3:] = False
    mask[1, 4] = False
    loss = table_loss(q_on, q_tg, gamma=0.9, double_q=double_q)
    out = loss(segment_batch(ids, actions, rewards, terminated, mask))
    ref = _reference_td(
        ids.tolist(),
        actions.tolist(),
        rewards.tolist(),
        terminated.tolist(),
        mask.tolist(),
        q_on,
        q_tg,
        0.9,
        double_q,
    )
    assert out["loss_td"].item() == pytest.approx(ref, rel=1e-5)


# ============================================================================ real ICCO batches
def _rollout_segments(parts, steps=24, seed=0, length=4):
    """A rollout and its items of ``length`` steps (default: one broadcast period each; the
    tests of longer items cut their own)."""
    torch.manual_seed(seed)
    parts["env"].set_seed(seed)
    with torch.no_grad():
        ro = parts["env"].rollout(steps, parts["policy"], break_when_any_done=False)
    return ro, SegmentCutter(length=length)(ro)


@pytest.fixture(scope="module")
def icco():
    parts = build_components(method="icco", num_envs=8)
    ro, seg = _rollout_segments(parts)
    return parts, ro, seg


def _grads(params):
    return {k: v.grad for k, v in params.items(True, True)}


def _has_grad(params):
    return any(g is not None and g.abs().sum() > 0 for g in _grads(params).values())


def _zero(loss):
    for p in loss.parameters():
        p.grad = None


def test_coordinator_gets_gradient_from_td_alone(icco):
    parts, _, seg = icco
    loss = parts["loss"]
    _zero(loss)
    out = loss(seg)
    out["loss_td"].backward()
    cp = loss.coordinator_params
    assert _has_grad(cp.select(("module", "loc"))), (
        "L_RL must reach the coordinator's mean through z"
    )
    assert _has_grad(cp.select(("module", "logvar"))), (
        "L_RL must reach the coordinator's scale through z"
    )
    assert _has_grad(cp.select(("module", "encoder")))
    assert _has_grad(loss.agent_params) and _has_grad(loss.mixer_params)
    assert not any(
        p.grad is not None and p.grad.abs().sum() > 0 for p in loss.posterior.parameters()
    ), "the posterior appears only in L_CE"


def test_coordinator_gets_gradient_from_ce_alone(icco):
    parts, _, seg = icco
    loss = parts["loss"]
    _zero(loss)
    out = loss(seg)
    assert {"loss_td", "loss_ce"} <= set(out.keys())
    torch.testing.assert_close(out["loss_ce"], out["ce_nll"] + out["ce_neg_entropy"])
    out["loss_ce"].backward()
    assert _has_grad(loss.coordinator_params.select(("module", "loc")))
    assert _has_grad(loss.coordinator_params.select(("module", "logvar")))
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in loss.posterior.parameters())
    assert not _has_grad(loss.agent_params) and not _has_grad(loss.mixer_params)
    # total_loss is the sum of both terms
    torch.testing.assert_close(total_loss(out), out["loss_td"] + out["loss_ce"])


@pytest.mark.parametrize("combine", ["product", "sum"])
def test_ce_term_scores_the_z_the_agents_acted_on(combine):
    overrides = [f"method.posterior={combine}", "env.params.max_steps=10", "train.ce_clamp=false"]
    cfg = compose_config(["method=icco", *overrides])  # unclamped: the terms as written
    parts = build_components(cfg, num_envs=4)
    _, seg = _rollout_segments(parts, steps=16)
    loss = parts["loss"]
    assert loss.posterior.module.combine == combine
    out = loss(seg)
    z0 = seg["agents", "z"][:, 0]  # stored at the broadcast step
    with torch.no_grad():
        log_q = loss.posterior.module(
            z0, seg["state"], seg["agents", "action"], seg["agents", "observation"], seg["mask"]
        )  # [S, N]
        _, scale0 = loss.coordinator.module.distribution(seg["state"][:, 0])
    entropy = gaussian_entropy(scale0).mean()
    assert out["log_q"].item() == pytest.approx(log_q.mean().item(), abs=1e-4)
    assert out["entropy"].item() == pytest.approx(entropy.item(), abs=1e-4)
    assert out["loss_ce"].item() == pytest.approx(
        -loss.ce_coef * log_q.mean().item() - loss.entropy_coef * entropy.item(), abs=1e-6
    )


def test_target_params_receive_no_grad(icco):
    parts, _, seg = icco
    loss = parts["loss"]
    _zero(loss)
    total_loss(loss(seg)).backward()
    names = [n for n in ("agent", "mixer", "coordinator") if hasattr(loss, f"target_{n}_params")]
    assert names == ["agent", "mixer", "coordinator"]
    target_ids = set()
    for n in names:
        for key, p in getattr(loss, f"target_{n}_params").items(True, True):
            assert p.grad is None, (n, key)
            target_ids.add(p.data_ptr())
    online_ids = {p.data_ptr() for p in loss.parameters()}
    assert not target_ids & online_ids, (
        "target params must be distinct tensors that the optimiser never sees"
    )


def test_target_params_never_require_grad():
    parts = build_components(method="icco", num_envs=2)
    loss = parts["loss"]
    _, seg = _rollout_segments(parts, steps=8)
    loss(seg)
    for n in ("agent", "mixer", "coordinator"):
        for key, p in getattr(loss, f"target_{n}_params").items(True, True):
            assert not p.requires_grad, (n, key)
    make_target_updater(loss, "hard", interval=5)  # TorchRL refuses targets that require grad


def test_target_update_after_forward_reaches_the_loss():
    """The loss bootstraps from the very tensors the updater writes, also after forward passes."""
    loss = table_loss(Q_ONLINE, Q_TARGET, gamma=0.5, double_q=True)
    updater = make_target_updater(
        loss, "hard", interval=1
    )  # TorchRL's init_ copies online -> target
    loss.target_agent_params["module", "table"].data.copy_(
        torch.tensor(Q_TARGET, dtype=torch.float32)
    )
    batch = segment_batch(IDS, ACTIONS, REWARDS)
    assert loss(batch)["loss_td"].item() == pytest.approx(4.25)
    updater.step()  # target := online
    # with Qt = Qo: y0 = 1 + 0.5 * (Qo[2][1] + Qo[3][0]) = 4.5,
    #               y1 = -3 + 0.5 * (Qo[4][0] + Qo[5][1]) = 0
    assert loss(batch)["loss_td"].item() == pytest.approx(((5 - 4.5) ** 2 + (1 - 0) ** 2) / 2)


def test_icco_wo_ce_has_no_posterior_and_no_ce():
    parts = build_components(method="icco_wo_ce", num_envs=4)
    _, seg = _rollout_segments(parts, steps=12)
    loss = parts["loss"]
    assert parts["posterior"] is None and loss.posterior is None
    assert not any("posterior" in n for n, _ in loss.named_parameters())
    out = loss(seg)
    assert "loss_ce" not in out.keys() and "log_q" not in out.keys()
    out["loss_td"].backward()
    assert _has_grad(loss.coordinator_params), "w/o CE the coordinator is trained by L_RL alone"


def test_qmix_has_no_coordinator():
    parts = build_components(method="qmix", num_envs=4)
    _, seg = _rollout_segments(parts, steps=12)
    loss = parts["loss"]
    assert parts["coordinator"] is None and not loss.has_coordinator
    assert not any(isinstance(m, Coordinator) for m in parts["policy"].modules())
    assert not any("coordinator" in n for n, _ in loss.named_parameters())
    assert ("agents", "z") not in seg.keys(True)
    out = loss(seg)
    assert set(k for k in out.keys() if k.startswith("loss_")) == {"loss_td"}


def test_ce_without_posterior_is_refused(icco):
    parts = icco[0]
    with pytest.raises(ValueError, match="posterior"):
        ICCOLoss(parts["agent"], parts["mixer"], parts["coordinator"], None, ce_coef=1e-3)
    # ... and a coordinator must match an agent that takes z
    with pytest.raises(ValueError, match="z"):
        ICCOLoss(parts["agent"], parts["mixer"], None, None, ce_coef=0.0)


# ============================================================================ target updates
def _small_loss():
    return build_components(method="icco", num_envs=2)["loss"]


def _online_target_pairs(loss):
    for n in ("agent", "mixer", "coordinator"):
        online, target = getattr(loss, f"{n}_params"), getattr(loss, f"target_{n}_params")
        for key, p in online.items(True, True):
            yield p, target.get(key)


def _perturb(loss, value):
    with torch.no_grad():
        for p, _ in _online_target_pairs(loss):
            p.add_(value)


@pytest.mark.parametrize("k", [1, 3])
def test_hard_update_copies_exactly_every_k_steps(k):
    loss = _small_loss()
    updater = make_target_updater(loss, "hard", interval=k)
    for call in range(1, 3 * k + 1):
        _perturb(loss, 0.5)  # online moves away before every call
        before = [t.clone() for _, t in _online_target_pairs(loss)]
        updater.step()
        pairs = list(_online_target_pairs(loss))
        if call % k == 0:
            assert all(torch.equal(t, p) for p, t in pairs), f"call {call} must copy (interval {k})"
        else:
            assert all(torch.equal(t, b) for (_, t), b in zip(pairs, before)), (
                f"call {call} must not copy"
            )
            assert not all(torch.equal(t, p) for p, t in pairs)


def test_soft_update_moves_by_tau():
    loss = _small_loss()
    tau = 0.1
    updater = make_target_updater(loss, "soft", tau=tau)
    _perturb(loss, 1.0)
    before = [(p.detach().clone(), t.clone()) for p, t in _online_target_pairs(loss)]
    updater.step()
    for (p0, t0), (_, t1) in zip(before, _online_target_pairs(loss)):
        torch.testing.assert_close(t1, (1 - tau) * t0 + tau * p0)
    assert any(
        not torch.equal(t0, t1) for (_, t0), (_, t1) in zip(before, _online_target_pairs(loss))
    )


def test_target_updater_rejects_bad_arguments():
    loss = _small_loss()
    with pytest.raises(ValueError):
        make_target_updater(loss, "hard", interval=0)
    with pytest.raises(ValueError):
        make_target_updater(loss, "soft", tau=0.0)
    with pytest.raises(ValueError):
        make_target_updater(loss, "polyak")


def _z_on_every_state(loss, x, fresh):
    """z for the L+1 inputs written out step by step: a draw at each broadcast, held otherwise."""
    T, L = loss.period, x.step_count.shape[1]
    with loss.coordinator_params.to_module(loss.coordinator, preserve_module_state=False):
        loc, scale = loss.coordinator.module.distribution(x.state_seq)
    noise = torch.cat([x.z_noise, fresh.unsqueeze(1)], 1)
    z = [
        torch.where(
            (x.step_count[:, 0] % T == 0)[:, None, None],
            loc[:, 0] + scale[:, 0] * noise[:, 0],
            x.z[:, 0],
        )
    ]
    for j in range(1, L + 1):
        new = (x.next_step_count[:, j - 1] % T == 0)[:, None, None]
        z.append(torch.where(new, loc[:, j] + scale[:, j] * noise[:, j], z[-1]))
    return torch.stack(z, 1)


def _inputs(loss, seg):
    """The loss's assembled inputs of ``seg`` (what its tensor part reads)."""
    return assemble(loss.read_batch(seg), reads_state=True)


@pytest.mark.parametrize("cut_key,length", [("step_count", 4), ("step_count", 16), ("cut_at", 4)])
def test_z_on_the_broadcast_inputs_equals_every_input(icco, cut_key, length):
    """The coordinator runs on a fixed grid of broadcast inputs: the same z as on every input,
    on every input a loss term reads (the steps of the sequence's episode and the next-state
    after its last one), for items of one broadcast, of four, and items that start mid-period
    (every even step)."""
    parts, ro, _ = icco
    loss = parts["loss"]
    ro = ro.clone()
    ro["cut_at"] = ro["step_count"] * 2
    x = _inputs(loss, SegmentCutter(length=length, step_key=cut_key)(ro))
    fresh = torch.randn_like(x.z_noise[:, 0])
    z, _, _ = loss._z_sequence(x, loss.coordinator_params, fresh)
    read = torch.cat([torch.ones_like(x.mask[:, :1]), x.mask], 1)  # input j: step j - 1
    torch.testing.assert_close(z[read], _z_on_every_state(loss, x, fresh)[read])


@pytest.mark.parametrize("method", ["icco", "qmix_full"])
@pytest.mark.parametrize("burn_in", [0, 3])
def test_online_pass_in_pieces_equals_one_sequence(method, burn_in):
    """Burn-in, learned steps and the bootstrap input run as pieces from one another's hidden
    state: the same Q-values as one L+1 sequence."""
    parts = build_components(
        compose_config([f"method={method}", "env.params.max_steps=10"]), num_envs=4
    )
    _, seg = _rollout_segments(parts, steps=24)
    seg = SegmentCutter(length=8)(_rollout_segments(parts, steps=24)[0])
    loss = parts["loss"]
    loss.burn_in = burn_in
    x = _inputs(loss, seg)
    z = None
    if loss.has_coordinator:
        z, _, _ = loss._z_sequence(x, loss.coordinator_params, torch.randn_like(x.z_noise[:, 0]))
    with torch.no_grad():
        full = loss._q_sequence(loss.agent_params, x, z)  # [S, L+1, N, A]
        q, q_boot = loss._q_online(x, z)
    L = seg.shape[1]
    torch.testing.assert_close(q, full[:, :L], atol=1e-6, rtol=0)
    torch.testing.assert_close(q_boot, full[:, L], atol=1e-6, rtol=0)
    loss.double_q = False
    q_single, none = loss._q_online(x, z)
    assert none is None
    torch.testing.assert_close(q_single, full[:, :L], atol=1e-6, rtol=0)


# ============================================================================ recurrent replay
@pytest.mark.parametrize("method", ["icco", "qmix_full"])
@pytest.mark.parametrize("length", [4, 16])
def test_replay_reproduces_collection_action_values(method, length):
    """Replayed with the collection weights, every step of an item, across its broadcasts and
    across an episode end, has the Q-values and z the policy acted on."""
    cfg = compose_config([f"method={method}", "env.params.max_steps=10"])  # ends inside items
    parts = build_components(cfg, num_envs=6)
    ro, _ = _rollout_segments(parts, steps=48)
    seg = SegmentCutter(length=length)(ro)
    assert (~seg["mask"]).any() and (seg["step_count"][:, 0] == 0).any()
    loss = parts["loss"]
    x = _inputs(loss, seg)
    valid = seg["mask"]
    with torch.no_grad():
        z_seq = None
        if loss.has_coordinator:
            fresh = torch.randn_like(x.z_noise[:, 0])
            z_seq, _, _ = loss._z_sequence(x, loss.coordinator_params, fresh)
            torch.testing.assert_close(
                z_seq[:, :-1][valid], seg["agents", "z"][valid], atol=1e-5, rtol=0
            )
            broadcasts = (seg["step_count"].squeeze(-1) % loss.period == 0) & valid
            # several inside one item (3 fit in a 10-step episode)
            assert broadcasts.sum(1).max() == min(length // loss.period, 3)
        q = loss._q_sequence(loss.agent_params, x, z_seq)
    L = seg.shape[1]
    torch.testing.assert_close(
        q[:, :L][valid], seg["agents", "action_value"][valid], atol=1e-5, rtol=0
    )
    # forward itself: its q_taken / q_tot summaries are the collection values of the taken actions
    out = loss(seg)
    action = seg["agents", "action"].unsqueeze(-1)
    chosen = seg["agents", "action_value"].gather(-1, action).squeeze(-1)
    assert out["q_taken"].item() == pytest.approx(chosen[valid].mean().item(), abs=1e-5)
    with torch.no_grad():
        q_tot = loss.mixer.module(chosen.unsqueeze(-1), seg["state"]).squeeze(-1)
    assert out["q_tot"].item() == pytest.approx(q_tot[valid].mean().item(), abs=1e-5)


# ============================================================================ segment cutter
@pytest.fixture(scope="module")
def short_episode_rollout():
    cfg = compose_config(["method=icco", "env.params.max_steps=10"])
    parts = build_components(cfg, num_envs=3)
    torch.manual_seed(1)
    with torch.no_grad():
        ro = parts["env"].rollout(37, parts["policy"], break_when_any_done=False)
    B, L = ro.shape
    ro["tid"] = torch.arange(L).expand(B, L).clone()
    ro["eid"] = torch.arange(B)[:, None].expand(B, L).clone()
    return ro, parts["cfg"].method.period


def _sorted(seg):
    order = torch.argsort(seg["eid"][:, 0] * 10_000 + seg["tid"][:, 0])
    return seg[order]


def test_segments_start_at_broadcast_steps(short_episode_rollout):
    ro, T = short_episode_rollout
    seg = SegmentCutter(T)(ro)
    assert seg.shape[1] == T
    assert (seg["step_count"][:, 0] % T == 0).all()
    torch.testing.assert_close(seg["tid"], seg["tid"][:, :1] + torch.arange(T))
    assert (seg["eid"] == seg["eid"][:, :1]).all()
    # exactly one segment per complete broadcast start
    L = ro.shape[1]
    starts = (ro["step_count"].squeeze(-1) % T == 0) & (ro["tid"] <= L - T)
    assert seg.shape[0] == int(starts.sum())
    # contents are the rollout's own steps
    got = _sorted(seg)
    e, t = starts.nonzero(as_tuple=True)
    for j in range(T):
        torch.testing.assert_close(
            got["agents", "observation"][:, j], ro["agents", "observation"][e, t + j]
        )


@pytest.mark.parametrize("chunks", [[7, 5], [4], [13, 1, 3]])
def test_segments_stitched_across_batches(short_episode_rollout, chunks):
    ro, T = short_episode_rollout
    whole = _sorted(SegmentCutter(T)(ro))
    cutter, parts, start, i = SegmentCutter(T), [], 0, 0
    while start < ro.shape[1]:
        size = chunks[i % len(chunks)]
        parts.append(cutter(ro[:, start : start + size]))
        start, i = start + size, i + 1
    stitched = _sorted(torch.cat([p for p in parts if p.shape[0]], 0))
    assert stitched.shape == whole.shape
    assert (stitched == whole).all()


def test_segments_stitched_across_tiny_batches(short_episode_rollout):
    ro, T = short_episode_rollout
    whole = _sorted(SegmentCutter(T)(ro))
    cutter = SegmentCutter(T)
    out = [cutter(ro[:, s : s + 2]) for s in range(0, ro.shape[1], 2)]
    stitched = _sorted(torch.cat([p for p in out if p.shape[0]], 0))
    assert (stitched == whole).all()


def test_mask_false_after_episode_end(short_episode_rollout):
    ro, T = short_episode_rollout
    seg = SegmentCutter(T)(ro)
    done = seg["next", "done"].squeeze(-1)
    mask = seg["mask"]
    assert mask[:, 0].all()
    crossing = done[:, :-1].any(-1)
    assert crossing.any(), "max_steps=10 with T=4 puts an episode end inside some segments"
    for s in range(seg.shape[0]):
        end = done[s].nonzero()
        last = int(end[0]) if len(end) else T - 1
        expected = torch.arange(T) <= last
        assert torch.equal(mask[s], expected), (seg["step_count"][s].squeeze(-1), done[s], mask[s])
    # the masked steps really belong to the next episode
    assert (seg["step_count"][~mask] < T).all()


def test_cutter_rejects_bad_input():
    with pytest.raises(ValueError):
        SegmentCutter(0)
    with pytest.raises(ValueError, match="batch"):
        SegmentCutter(4)(TensorDict({"step_count": torch.zeros(5, 1)}, [5]))


# ============================================================================ bad input
def _seg_copy(icco):
    return icco[2].clone()


def _named(key):
    """How the message names a key: the full nested key, e.g. ('next', 'agents', 'observation')."""
    return repr(key)


@pytest.mark.parametrize(
    "key,expected",
    [
        (("agents", "observation"), "[S, T, N, obs_dim]"),
        (("agents", "rnn_hidden"), "[S, T, N, 64]"),
        ("state", "[S, T, state_dim]"),
        (("next", "reward"), "[S, T, 1]"),
        (("agents", "z_noise"), "[S, T, N, 32]"),
        ("step_count", "[S, T, 1]"),
    ],
)
def test_missing_key_names_key_and_shape(icco, key, expected):
    td = _seg_copy(icco)
    del td[key]
    with pytest.raises(KeyError) as err:
        icco[0]["loss"](td)
    msg = err.value.args[0]
    assert _named(key) in msg and expected in msg


@pytest.mark.parametrize(
    "key,bad_shape_fn,expected",
    [
        (("agents", "rnn_hidden"), lambda v: v[..., :10], "[S, T, N, 64]"),
        (("next", "reward"), lambda v: v.squeeze(-1), "[S, T, 1]"),
        (("agents", "action"), lambda v: v.unsqueeze(-1), "[S, T, N]"),
        (("agents", "z"), lambda v: v[..., :5], "[S, T, N, 32]"),
        (("next", "agents", "observation"), lambda v: v[..., :7], "[S, T, N, obs_dim]"),
    ],
)
def test_wrong_shape_names_key_and_shape(icco, key, bad_shape_fn, expected):
    td = _seg_copy(icco)
    value = bad_shape_fn(td.get(key))
    td = td.exclude(key)
    td.set(key, value)
    with pytest.raises(ValueError) as err:
        icco[0]["loss"](td)
    msg = str(err.value)
    assert _named(key) in msg and expected in msg


def test_wrong_mask_shape_names_key(icco):
    td = _seg_copy(icco)
    S, T = td.shape
    td["mask"] = torch.ones(S, T, 2, dtype=torch.bool)
    with pytest.raises(ValueError, match="mask"):
        icco[0]["loss"](td)


def test_segments_without_time_dim_are_refused(icco):
    with pytest.raises(ValueError, match=r"\[S, T\]"):
        icco[0]["loss"](_seg_copy(icco)[:, 0])


def test_non_finite_loss_raises(icco):
    td = _seg_copy(icco)
    td["next", "reward"][0, 1] = float("nan")
    with pytest.raises(NonFiniteLossError, match="loss_td"):
        icco[0]["loss"](td)
    assert issubclass(NonFiniteLossError, FloatingPointError)


def test_loss_rejects_bad_coefficients(icco):
    parts = icco[0]
    with pytest.raises(ValueError, match="gamma"):
        ICCOLoss(
            parts["agent"], parts["mixer"], parts["coordinator"], parts["posterior"], gamma=1.5
        )
    with pytest.raises(ValueError, match="ce_coef"):
        ICCOLoss(
            parts["agent"], parts["mixer"], parts["coordinator"], parts["posterior"], ce_coef=-1.0
        )


# ======================================================================= defaults, COPA clamps
def test_loss_defaults_are_icco_train():
    """ICCOLoss with no keyword arguments is the method `icco train method=icco` builds: the same
    settings, and the same losses on the same batch."""
    parts = build_components(compose_config(["method=icco"]), num_envs=4)
    _, seg = _rollout_segments(parts, steps=16, length=16)
    trained = parts["loss"]
    plain = ICCOLoss(parts["agent"], parts["mixer"], parts["coordinator"], parts["posterior"])
    assert plain.settings == trained.settings
    assert plain.settings["td_lambda"] > 0 and plain.settings["ce_coef"] > 0
    torch.manual_seed(1)
    a = trained(seg)
    torch.manual_seed(1)
    b = plain(seg)
    assert set(a.keys()) == set(b.keys())
    for key in a.keys():
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0)
    # TorchRL's default value estimator keeps that method: TD(lambda) at the loss's lambda
    plain.make_value_estimator()
    assert plain.td_lambda == trained.td_lambda


def _sharp_icco(ce_clamp: bool, z_loc: float = 10.0):
    """An ICCO loss whose coordinator draws z = z_loc + e^-5 * noise (logvar -10 in every
    dimension) and whose posterior factors are N(0, e^-10) whatever they read: every dimension's
    log q is below -1e6, and every dimension's entropy is 1.419 - 5 < 0."""
    parts = build_components(method="icco", num_envs=4)
    _, seg = _rollout_segments(parts, steps=16)
    loss = ICCOLoss(
        parts["agent"],
        parts["mixer"],
        parts["coordinator"],
        parts["posterior"],
        ce_coef=1e-3,
        entropy_coef=1e-4,
        ce_clamp=ce_clamp,
    )
    Z = parts["coordinator"].module.z_dim
    with torch.no_grad():
        for name, value in (("loc", z_loc), ("logvar", -10.0)):
            linear = getattr(loss.coordinator.module, name)
            linear.weight.zero_()
            linear.bias.fill_(value)
        for head in (loss.posterior.module.first, loss.posterior.module.later):
            head[-1].weight.zero_()
            head[-1].bias[:Z].fill_(0.0)
            head[-1].bias[Z:].fill_(-10.0)
    return loss, seg, Z


def test_ce_clamp_caps_each_dimension_hand_computed():
    """COPA's clamps: each dimension's log q at -1000 and each dimension's entropy at 0. With z
    ten units from the mean of a posterior of std e^-5, -log q costs exactly 1000 per dimension,
    and a narrow z (entropy 1.419 - 5 per dimension) costs nothing."""
    clamped, seg, Z = _sharp_icco(ce_clamp=True)
    out = clamped(seg)
    assert out["log_q"].item() < -1e6 * Z  # the entry stays the unclamped log q
    assert out["entropy"].item() == pytest.approx(Z * (1.4189385 - 5.0), abs=1e-3)
    assert out["ce_nll"].item() == pytest.approx(1e-3 * 1000.0 * Z, rel=1e-6)
    assert out["ce_neg_entropy"].item() == 0.0
    free, seg, Z = _sharp_icco(ce_clamp=False)
    out = free(seg)
    assert out["ce_nll"].item() == pytest.approx(-1e-3 * out["log_q"].item(), rel=1e-6)
    assert out["ce_neg_entropy"].item() == pytest.approx(-1e-4 * Z * (1.4189385 - 5.0), rel=1e-4)


def test_ce_clamp_changes_nothing_inside_its_range():
    """Where every dimension's log q is in [-1000, 0] and entropy in [0, 10] (a wide posterior
    and z of std 1), the clamped loss is the plain one."""
    parts = build_components(method="icco", num_envs=4)
    _, seg = _rollout_segments(parts, steps=16)
    with torch.no_grad():
        parts["coordinator"].module.logvar.weight.zero_()
        parts["coordinator"].module.logvar.bias.fill_(0.0)  # entropy 1.419 per dimension
        for head in (parts["posterior"].first, parts["posterior"].later):
            head[-1].bias[parts["coordinator"].module.z_dim :].fill_(0.0)
            head[-1].weight[parts["coordinator"].module.z_dim :].zero_()  # factor std 1
    args = (parts["agent"], parts["mixer"], parts["coordinator"], parts["posterior"])
    torch.manual_seed(2)
    a = ICCOLoss(*args, ce_clamp=True)(seg)
    torch.manual_seed(2)
    b = ICCOLoss(*args, ce_clamp=False)(seg)
    for key in ("ce_nll", "ce_neg_entropy", "log_q", "entropy"):
        torch.testing.assert_close(a[key], b[key])


def test_ce_clamp_is_the_train_option():
    off = build_components(compose_config(["method=icco", "train.ce_clamp=false"]), num_envs=2)
    assert build_components(method="icco", num_envs=2)["loss"].ce_clamp  # the default: clamped
    assert not off["loss"].ce_clamp
