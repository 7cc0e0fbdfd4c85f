"""ICCOLoss and the networks as another TorchRL project would use them (issue 11, part 6).

Sizes and the action count come from the caller, a flat observation needs no layout, the agent
resets on TorchRL's ``is_init``, the loss calls the agent and the mixer through their keys (so
TorchRL's ``MultiAgentMLP``, ``QMixer`` and ``VDNMixer`` plug in), any trailing state shape is
flattened, per-agent rewards are reduced by a named option, a mask is built from done/is_init when
none is given, and ``make_value_estimator`` picks TD(0)/TD(1)/TD(lambda).
"""

import importlib.util
import math
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.modules import MultiAgentMLP, QMixer, VDNMixer, set_recurrent_mode
from torchrl.objectives import ValueEstimators

from icco_torchrl.modules import RecurrentQNet, make_agent, make_coordinator, make_posterior
from icco_torchrl.modules.policy import make_policy, make_primer
from icco_torchrl.objectives import ICCOLoss, total_loss
from icco_torchrl.objectives.defaults import LOSS_DEFAULTS

torch.set_num_threads(1)

S, T, N, F, A, H, Z = 5, 4, 3, 7, 9, 16, 4  # 9 actions, as VMAS's discrete navigation


def segments(
    seed=0,
    *,
    per_agent_reward=False,
    state_shape=(N * F,),
    with_z=False,
    is_init=None,
    done=None,
    mask=None,
):
    """Random segments ``[S, T]`` in TorchRL's multi-agent layout (time last)."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(S, T + 1, N, F, generator=g)
    reward = (
        torch.randn(S, T, N, 1, generator=g)
        if per_agent_reward
        else torch.randn(S, T, 1, generator=g)
    )
    state = torch.randn(S, T + 1, *state_shape, generator=g)
    flags = torch.zeros(S, T, 1, dtype=torch.bool)
    actions = torch.randint(
        0, A, (S, T + 1, N), generator=g
    )  # step k's previous action is step k-1's
    td = TensorDict(
        {
            "agents": TensorDict(
                {
                    "observation": obs[:, :T],
                    "action": actions[:, 1:],
                    "prev_action": actions[:, :T],
                    "rnn_hidden": torch.randn(S, T, N, H, generator=g),
                },
                [S, T],
            ),
            "state": state[:, :T],
            "step_count": torch.arange(T).expand(S, T).unsqueeze(-1).clone(),
            "next": TensorDict(
                {
                    "agents": TensorDict({"observation": obs[:, 1:]}, [S, T]),
                    "state": state[:, 1:],
                    "step_count": torch.arange(1, T + 1).expand(S, T).unsqueeze(-1).clone(),
                    "done": flags.clone() if done is None else done,
                    "terminated": flags.clone(),
                },
                [S, T],
            ),
        },
        [S, T],
    )
    td.set(("next", "agents", "reward") if per_agent_reward else ("next", "reward"), reward)
    if with_z:
        td.set(("agents", "z"), torch.randn(S, T, N, Z, generator=g))
        td.set(("agents", "z_noise"), torch.randn(S, T, N, Z, generator=g))
    if is_init is not None:
        td.set("is_init", is_init)
    if mask is not None:
        td.set("mask", mask)
    return td


def flat_agent(z_dim=0):
    torch.manual_seed(0)
    return make_agent(obs_dim=F, n_actions=A, hidden=H, z_dim=z_dim)


def sum_mixer(state_key="state"):
    """VDN: TorchRL's VDNMixer, which reads no state."""
    return TensorDictModule(
        VDNMixer(n_agents=N, device="cpu"),
        in_keys=[("agents", "chosen_action_value")],
        out_keys=["chosen_action_value"],
    )


def qmixer(state_shape=(N * F,), state_key="state"):
    torch.manual_seed(1)
    return TensorDictModule(
        QMixer(state_shape=state_shape, mixing_embed_dim=8, n_agents=N, device="cpu"),
        in_keys=[("agents", "chosen_action_value"), state_key],
        out_keys=["chosen_action_value"],
    )


# ============================================================================ networks from sizes
def test_flat_agent_needs_no_layout_and_takes_the_action_count():
    agent = flat_agent()
    net = agent.module
    assert net.prev_action_embed.num_embeddings == A and net.head[-1].out_features == A
    td = TensorDict(
        {
            "agents": TensorDict(
                {
                    "observation": torch.randn(2, N, F),
                    "prev_action": torch.full((2, N), A - 1),  # the 9th action embeds
                    "rnn_hidden": torch.zeros(2, N, H),
                },
                [2],
            ),
            "is_init": torch.ones(2, 1, dtype=torch.bool),
        },
        [2],
    )
    out = agent(td)
    assert out["agents", "action_value"].shape == (2, N, A) and out[
        "next", "agents", "rnn_hidden"
    ].shape == (2, N, H)
    with pytest.raises(ValueError, match="layout.*obs_dim"):
        RecurrentQNet(n_actions=A, hidden=H)
    with pytest.raises(ValueError, match="mlp"):
        RecurrentQNet(obs_dim=F, n_actions=A, hidden=H, encoder="attention")
    with pytest.raises(ValueError, match="n_actions"):
        RecurrentQNet(obs_dim=F, n_actions=0, hidden=H)


def test_primer_takes_the_action_count():
    primer = make_primer(N, H, n_actions=A)
    assert primer.primers["agents", "prev_action"].space.n == A


def test_agent_resets_on_is_init_else_on_step_count():
    net = flat_agent().module
    obs, prev, hidden = (
        torch.randn(3, N, F),
        torch.zeros(3, N, dtype=torch.long),
        torch.randn(3, N, H),
    )
    is_init = torch.tensor([[True], [False], [True]])
    _, h_init = net(obs, prev, hidden, is_init=is_init)
    _, h_zero = net.step(obs, prev, torch.zeros_like(hidden))
    _, h_kept = net.step(obs, prev, hidden)
    torch.testing.assert_close(h_init[[0, 2]], h_zero[[0, 2]])
    torch.testing.assert_close(h_init[1], h_kept[1])
    # per-agent is_init [B, N, 1] resets single agents
    per_agent = torch.zeros(3, N, 1, dtype=torch.bool)
    per_agent[1, 2] = True
    _, h = net(obs, prev, hidden, is_init=per_agent)
    torch.testing.assert_close(h[1, 2], h_zero[1, 2])
    torch.testing.assert_close(h[1, :2], h_kept[1, :2])
    # no is_init: step_count == 0 (this package's env), same result
    _, h_sc = net(obs, prev, hidden, step_count=torch.tensor([[0], [5], [0]]))
    torch.testing.assert_close(h_sc, h_init)
    with pytest.raises(KeyError, match="is_init"):
        net(obs, prev, hidden)


def test_agent_module_in_recurrent_mode_runs_the_sequence():
    agent = flat_agent()
    td = segments()
    with set_recurrent_mode(True):
        out = agent(td.clone())
    q_seq, h_seq = agent.module.sequence(
        td["agents", "observation"],
        td["agents", "prev_action"],
        td["agents", "rnn_hidden"][:, 0] * 0,
        return_hidden="all",
    )  # step 0: is_init
    torch.testing.assert_close(out["agents", "action_value"], q_seq)
    torch.testing.assert_close(out["next", "agents", "rnn_hidden"], h_seq)


# ============================================================================ the loss
@pytest.mark.parametrize("mixer_fn", [sum_mixer, qmixer], ids=["VDNMixer", "QMixer"])
def test_torchrl_mixers_plug_in(mixer_fn):
    loss = ICCOLoss(flat_agent(), mixer_fn(), ce_coef=0.0, entropy_coef=0.0)
    out = loss(segments())
    assert set(out.keys()) == set(loss.metric_keys)
    assert torch.isfinite(out["loss_td"]) and out["loss_td"] > 0
    total_loss(out).backward()
    assert loss.agent_params["module", "head", "2", "weight"].grad.abs().sum() > 0


def test_vdn_mixer_sums_the_agents():
    loss = ICCOLoss(flat_agent(), sum_mixer(), ce_coef=0.0, entropy_coef=0.0)
    td = segments()
    out = loss(td)
    with torch.no_grad():
        q = loss.agent.module.sequence(
            td["agents", "observation"],
            td["agents", "prev_action"],
            td["agents", "rnn_hidden"][:, 0],
        )
    chosen = q.gather(-1, td["agents", "action"].unsqueeze(-1)).squeeze(-1)
    assert out["q_tot"].item() == pytest.approx(chosen.sum(-1).mean().item(), abs=1e-5)

    # a mixer module called by keyword (dict in_keys) goes through a tensordict: same numbers
    class KwargSum(torch.nn.Module):
        def forward(self, values):
            return values.sum(-2)

    kw = TensorDictModule(
        KwargSum(),
        in_keys={"values": ("agents", "chosen_action_value")},
        out_keys=["chosen_action_value"],
    )
    other = ICCOLoss(flat_agent(), kw, ce_coef=0.0, entropy_coef=0.0)
    torch.testing.assert_close(other(td)["loss_td"], out["loss_td"])


def test_a_torchrl_network_plugs_in_as_the_agent():
    """TorchRL's MultiAgentMLP (no GRU, no prev_action), called through its keys on [S, T+1]."""
    torch.manual_seed(0)
    mlp = MultiAgentMLP(
        n_agent_inputs=F,
        n_agent_outputs=A,
        n_agents=N,
        centralised=False,
        share_params=True,
        depth=1,
        num_cells=16,
    )
    agent = TensorDictModule(
        mlp, in_keys=[("agents", "observation")], out_keys=[("agents", "action_value")]
    )
    td = segments().exclude(("agents", "rnn_hidden"), ("agents", "prev_action"))
    for double_q in (True, False):
        loss = ICCOLoss(agent, qmixer(), double_q=double_q, ce_coef=0.0, entropy_coef=0.0)
        out = loss(td)
        assert torch.isfinite(out["loss_td"])
        # its Q-values are the MLP's on the segment's observations
        with torch.no_grad():
            expected = (
                mlp(td["agents", "observation"])
                .gather(-1, td["agents", "action"].unsqueeze(-1))
                .mean()
            )
        assert out["q_taken"].item() == pytest.approx(expected.item(), abs=1e-5)


def test_a_torchrl_agent_reads_the_state_with_its_trailing_dims():
    """An agent that reads the state through its keys gets it as the batch holds it (``[.., N,
    F]``, not flattened): its Q-values are the MLP's on the segment's states."""
    torch.manual_seed(0)
    mlp = MultiAgentMLP(
        n_agent_inputs=F,
        n_agent_outputs=A,
        n_agents=N,
        centralised=False,
        share_params=True,
        depth=1,
        num_cells=16,
    )
    agent = TensorDictModule(mlp, in_keys=["state"], out_keys=[("agents", "action_value")])
    td = segments(state_shape=(N, F)).exclude(("agents", "rnn_hidden"), ("agents", "prev_action"))
    loss = ICCOLoss(agent, sum_mixer(), ce_coef=0.0, entropy_coef=0.0)
    assert loss.reads_state and not loss.recurrent and not loss.reads_prev_action
    assert loss.read_batch(td).state_shape == (N, F)
    out = loss(td)
    with torch.no_grad():
        expected = mlp(td["state"]).gather(-1, td["agents", "action"].unsqueeze(-1)).mean()
    assert out["q_taken"].item() == pytest.approx(expected.item(), abs=1e-5)


def test_generic_path_equals_the_sequence_path():
    """The same RecurrentQNet called through its keys (as any TorchRL network): the same loss."""
    agent = flat_agent()
    td = segments()
    td["agents", "rnn_hidden"][:, 0] = 0  # an episode start (is_init at step 0) stores a zero state
    fast = ICCOLoss(agent, qmixer(), ce_coef=0.0, entropy_coef=0.0)
    generic = ICCOLoss(agent, qmixer(), ce_coef=0.0, entropy_coef=0.0)
    generic._sequence_agent = False
    for double_q in (True, False):
        fast.double_q = generic.double_q = double_q
        torch.testing.assert_close(generic(td)["loss_td"], fast(td)["loss_td"])


def test_state_of_any_trailing_shape_is_flattened():
    """VMAS has no global state: TorchRL's QMIX example mixes stacked observations [.., N, F]."""
    key = ("agents", "observation")
    td = segments(with_z=True)
    torch.manual_seed(0)
    coordinator = make_coordinator(
        n_agents=N, state_dim=N * F, z_dim=Z, hidden=H, period=T, init_logvar=0.0, state_key=key
    )
    posterior = make_posterior(
        n_actions=A, n_agents=N, obs_dim=F, state_dim=N * F, z_dim=Z, hidden=H, combine="product"
    )
    loss = ICCOLoss(
        flat_agent(z_dim=Z), qmixer(state_shape=(N, F), state_key=key), coordinator, posterior
    )
    loss.set_keys(state=key)
    out = loss(td)
    assert torch.isfinite(out["loss_td"]) and torch.isfinite(out["loss_ce"])
    # same numbers as the flattened state under its own key
    flat = td.clone()
    flat["state"], flat["next", "state"] = flat[key].flatten(-2), flat[("next", *key)].flatten(-2)
    mixer = qmixer(state_shape=(N * F,))
    mixer.module.load_state_dict(loss.mixer.module.state_dict())
    ref = ICCOLoss(loss.agent, mixer, coordinator, posterior)
    torch.manual_seed(3)
    a = loss(td)
    torch.manual_seed(3)
    b = ref(flat)
    for name in ("loss_td", "loss_ce"):
        torch.testing.assert_close(a[name], b[name])
    # and the coordinator module flattens it at collection
    roll = TensorDict(
        {
            "agents": TensorDict(
                {
                    "observation": torch.randn(2, N, F),
                    "z": torch.zeros(2, N, Z),
                    "z_noise": torch.zeros(2, N, Z),
                },
                [2],
            ),
            "step_count": torch.zeros(2, 1, dtype=torch.long),
        },
        [2],
    )
    assert coordinator(roll)["agents", "z"].shape == (2, N, Z)


@pytest.mark.parametrize("reduction", ["mean", "sum"])
def test_per_agent_rewards_are_reduced_by_the_named_option(reduction):
    per_agent = segments(per_agent_reward=True)
    team = per_agent.clone()
    r = per_agent["next", "agents", "reward"]
    team["next", "reward"] = r.mean(-2) if reduction == "mean" else r.sum(-2)
    loss = ICCOLoss(
        flat_agent(), qmixer(), ce_coef=0.0, entropy_coef=0.0, reward_reduction=reduction
    )
    expected = loss(team)["loss_td"]
    loss.set_keys(reward=("agents", "reward"))
    torch.testing.assert_close(loss(per_agent)["loss_td"], expected)
    with pytest.raises(ValueError, match="reward_reduction"):
        ICCOLoss(flat_agent(), qmixer(), ce_coef=0.0, entropy_coef=0.0, reward_reduction="max")


def test_mask_is_built_from_done_and_is_init_when_absent():
    loss = ICCOLoss(flat_agent(), qmixer(), ce_coef=0.0, entropy_coef=0.0)
    done = torch.zeros(S, T, 1, dtype=torch.bool)
    done[0, 1] = True  # segment 0 ends after step 1: steps 2, 3 are another episode
    is_init = torch.zeros(S, T, 1, dtype=torch.bool)
    is_init[1, 3] = True  # segment 1 restarts at step 3
    is_init[2, 0] = True  # a segment that starts an episode keeps every step
    mask = torch.ones(S, T, dtype=torch.bool)
    mask[0, 2:] = False
    mask[1, 3] = False
    derived = loss(segments(done=done, is_init=is_init))["loss_td"]
    explicit = loss(segments(done=done, is_init=is_init, mask=mask))["loss_td"]
    everything = loss(
        segments(done=done, is_init=is_init, mask=torch.ones(S, T, dtype=torch.bool))
    )["loss_td"]
    torch.testing.assert_close(derived, explicit)
    assert not torch.allclose(derived, everything)


def test_make_value_estimator_td0_td1_tdlambda():
    td = segments()
    lam = {}
    for name, kwargs in [
        ("td0", dict(td_lambda=0.0)),
        ("td1", dict(td_lambda=1.0)),
        ("lambda", dict(td_lambda=0.7)),
    ]:
        lam[name] = ICCOLoss(
            flat_agent(), qmixer(), gamma=0.8, ce_coef=0.0, entropy_coef=0.0, **kwargs
        )(td)["loss_td"]
    loss = ICCOLoss(flat_agent(), qmixer(), ce_coef=0.0, entropy_coef=0.0)
    assert loss.make_value_estimator(ValueEstimators.TD0, gamma=0.8) is loss
    assert loss.value_type == ValueEstimators.TD0 and loss.gamma == 0.8 and loss.td_lambda == 0.0
    torch.testing.assert_close(loss(td)["loss_td"], lam["td0"])
    loss.make_value_estimator(ValueEstimators.TD1)
    torch.testing.assert_close(loss(td)["loss_td"], lam["td1"])
    loss.make_value_estimator(ValueEstimators.TDLambda, lmbda=0.7, gamma=0.8)
    torch.testing.assert_close(loss(td)["loss_td"], lam["lambda"])
    assert not torch.allclose(lam["td0"], lam["lambda"])
    loss.make_value_estimator()  # the default: TD(lambda), at the loss's lambda
    assert loss.td_lambda == 0.7 and loss.value_type == ValueEstimators.TDLambda
    loss.make_value_estimator(ValueEstimators.TD0)
    loss.make_value_estimator()  # ... or at the default lambda, icco train's
    assert loss.td_lambda == LOSS_DEFAULTS.td_lambda > 0
    with pytest.raises(NotImplementedError, match="GAE"):
        loss.make_value_estimator(ValueEstimators.GAE)
    with pytest.raises(TypeError, match="bogus"):
        loss.make_value_estimator(ValueEstimators.TD0, bogus=1)
    with pytest.raises(ValueError, match="gamma"):
        loss.make_value_estimator(ValueEstimators.TD0, gamma=2.0)


def test_metric_keys_name_what_forward_returns():
    td = segments(with_z=True)
    coordinator = make_coordinator(
        n_agents=N, state_dim=N * F, z_dim=Z, hidden=H, period=T, init_logvar=0.0
    )
    posterior = make_posterior(
        n_actions=A, n_agents=N, obs_dim=F, state_dim=N * F, z_dim=Z, hidden=H, combine="product"
    )
    for post, ce in ((posterior, 1e-3), (None, 0.0)):
        loss = ICCOLoss(flat_agent(z_dim=Z), qmixer(), coordinator, post, ce_coef=ce)
        assert set(loss(td).keys()) == set(loss.metric_keys)
    assert "log_q" in ICCOLoss(flat_agent(z_dim=Z), qmixer(), coordinator, posterior).metric_keys


def test_mixer_key_mismatch_is_named():
    mixer = TensorDictModule(
        VDNMixer(n_agents=N, device="cpu"),
        in_keys=[("robots", "chosen_action_value")],
        out_keys=["chosen_action_value"],
    )
    loss = ICCOLoss(flat_agent(), mixer, ce_coef=0.0, entropy_coef=0.0)
    with pytest.raises(KeyError, match="local_value"):
        loss(segments())


def test_policy_with_nine_actions_acts_in_range():
    agent = flat_agent()
    from torchrl.data import Categorical, Composite

    spec = Composite(agents=Composite(action=Categorical(A, (N,), dtype=torch.int64), shape=(N,)))
    policy = make_policy(agent, spec, eps_init=1.0)
    td = TensorDict(
        {
            "agents": TensorDict(
                {
                    "observation": torch.randn(64, N, F),
                    "prev_action": torch.zeros(64, N, dtype=torch.long),
                    "rnn_hidden": torch.zeros(64, N, H),
                },
                [64],
            ),
            "is_init": torch.ones(64, 1, dtype=torch.bool),
        },
        [64],
    )
    action = policy(td)["agents", "action"]
    assert (
        action.min() >= 0 and action.max() <= A - 1 and action.max() > 4
    )  # epsilon 1: every action occurs


# ============================================================================ the VMAS example
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "vmas_qmix.py"


@pytest.fixture(scope="module")
def vmas_example():
    pytest.importorskip(
        "vmas", reason="VMAS is a dev dependency (pip install -e .[dev]); the example needs it"
    )
    spec = importlib.util.spec_from_file_location("vmas_qmix_example", EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("method", ["qmix", "icco_qmix", "icco"])
def test_vmas_example_trains_a_few_updates(vmas_example, method):
    result = vmas_example.train(
        method,
        n_iters=2,
        frames_per_batch=400,
        minibatch_size=200,
        num_epochs=1,
        evaluation_episodes=4,
        max_steps=20,
    )
    assert result["frames"] == 800 and result["updates"] == 4
    for name in ("random", "before", "after", "first_loss", "last_loss"):
        assert math.isfinite(result[name]), name
