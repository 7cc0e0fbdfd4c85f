"""Networks that read any team: a team of 3 padded to 6 robots gives the numbers of the same team
unpadded (Q-values, z, Q_tot, every loss term and gradient), the token mixer is monotone in every
present robot's Q and blind to absent ones, and checkpoints load across team sizes.

The padding follows the env's contract for an absent robot: an all-zero state token (type flags
included) inserted after the robot tokens, an all-zero observation row, a zero (invisible) entity
token in every other robot's observation, after the other-robot tokens, and zeros for every
per-robot tensor (action, prev_action, rnn_hidden, z, z_noise, ...).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from icco_torchrl.envs import ResourceCollectionEnv
from icco_torchrl.envs.layout import ObsLayout
from icco_torchrl.modules.mixer import TokenMixer, make_mixer
from icco_torchrl.modules.posterior import Posterior
from icco_torchrl.objectives import total_loss
from icco_torchrl.training.build import build, compose_config, make_loss, make_modules
from icco_torchrl.training.checkpoint import (
    load_checkpoint,
    load_weights,
    policy_weights,
    save_checkpoint,
)
from icco_torchrl.training.config import check_command_line, validate
from icco_torchrl.training.run_folder import CheckpointError
from icco_torchrl.training.segments import SegmentCutter

torch.set_num_threads(1)
N_ACTIONS = 5
ANY_TEAM = ["method.mixer=attention", "method.posterior_input=tokens"]
DEMO = Path(__file__).resolve().parents[1] / "assets" / "demo_icco.pt"


def pad_state(state, layout, extra: int):
    tok = state.unflatten(-1, (layout.state_tokens, layout.state_token_dim))
    N = layout.n_agents
    zeros = tok.new_zeros(*tok.shape[:-2], extra, tok.shape[-1])
    return torch.cat([tok[..., :N, :], zeros, tok[..., N:, :]], -2).flatten(-2)


def pad_observation(obs, layout, extra: int):
    own, ents = obs[..., : layout.own_dim], obs[..., layout.own_dim :]
    ents = ents.unflatten(-1, (layout.n_entities, layout.entity_dim))
    others = layout.n_agents - 1
    zeros = ents.new_zeros(*ents.shape[:-2], extra, ents.shape[-1])
    ents = torch.cat([ents[..., :others, :], zeros, ents[..., others:, :]], -2)
    obs = torch.cat([own, ents.flatten(-2)], -1)
    return torch.cat([obs, obs.new_zeros(*obs.shape[:-2], extra, obs.shape[-1])], -2)


def pad_robots(value, extra: int):
    """Zeros for ``extra`` absent robots along the robot dim (dim 2 of ``[S, L, N, ...]``)."""
    return torch.cat([value, value.new_zeros(*value.shape[:2], extra, *value.shape[3:])], 2)


def pad_batch(items: TensorDict, layout, n_agents: int) -> TensorDict:
    extra = n_agents - layout.n_agents
    out = TensorDict({}, batch_size=items.batch_size)
    for key, value in items.items(True, True):
        key = key if isinstance(key, tuple) else (key,)
        if key[-1] == "state":
            value = pad_state(value, layout, extra)
        elif key[-2:] == ("agents", "observation"):
            value = pad_observation(value, layout, extra)
        elif "agents" in key:
            assert value.shape[2] == layout.n_agents, key
            value = pad_robots(value, extra)
        out.set(key, value)
    return out


def networks(cfg, layout):
    mods = make_modules(cfg, layout, "cpu", n_actions=N_ACTIONS)
    return mods, make_loss(cfg, mods, layout)


@pytest.fixture(scope="module", params=["icco", "icco_flat_state", "qmix_full"])
def team(request):
    """A seeded 3-robot batch, the same batch padded to 6, and the networks for 3 and for 6 robots
    with the same weights (the 3-robot loss's state dict loaded into the 6-robot one)."""
    method = {"icco": ["method=icco"], "icco_flat_state": ["method=icco"]}.get(
        request.param, [f"method={request.param}"]
    )
    if request.param == "icco_flat_state":
        method = [*method, "method.state_encoder=flat"]
    cfg = compose_config([*method, *ANY_TEAM, "seed=0"])
    torch.manual_seed(0)
    run = build(cfg, num_envs=3)
    run.env.set_seed(0)
    with torch.no_grad():
        rollout = run.env.rollout(24, run.policy, break_when_any_done=False)
    items = SegmentCutter(length=8)(rollout)
    layout6 = run.layout.with_agents(6)
    torch.manual_seed(1)  # other initial weights: the load below must overwrite every one
    mods6, loss6 = networks(cfg, layout6)
    load_weights(loss6, run.loss.state_dict(), "3-robot weights", cfg.method.name)
    return dict(
        cfg=cfg,
        run=run,
        items=items,
        padded=pad_batch(items, run.layout, 6),
        layout6=layout6,
        mods6=mods6,
        loss6=loss6,
    )


def close(a, b):
    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_padding_follows_the_layout(team):
    """The padded batch is what a 6-robot env holding 3 robots writes: robot mask from the state."""
    padded, layout6 = team["padded"], team["layout6"]
    assert padded["state"].shape[-1] == layout6.state_dim
    assert padded["agents", "observation"].shape[-2:] == (6, layout6.obs_dim)
    present = layout6.robot_mask(padded["state"])
    assert present[..., :3].all() and not present[..., 3:].any()
    assert team["run"].layout.robot_mask(team["items"]["state"]).all()


def test_present_robots_get_the_same_z_and_q_values(team):
    run, items, padded, mods6 = team["run"], team["items"], team["padded"], team["mods6"]
    with torch.no_grad():
        if run.coordinator is not None:
            loc3, scale3 = run.coordinator.module.distribution(items["state"])
            loc6, scale6 = mods6["coordinator"].module.distribution(padded["state"])
            close(loc6[..., :3, :], loc3)
            close(scale6[..., :3, :], scale3)
            noise = items["agents", "z_noise"]
            z6 = loc6 + scale6 * padded["agents", "z_noise"]
            close(z6[..., :3, :], loc3 + scale3 * noise)
        z = items.get(("agents", "z"), None)
        args3 = (items["agents", "observation"], items["agents", "prev_action"])
        args6 = (padded["agents", "observation"], padded["agents", "prev_action"])
        state3 = items["state"] if run.agent.module.full_state else None
        state6 = padded["state"] if state3 is not None else None
        q3 = run.agent.module.sequence(
            *args3, items["agents", "rnn_hidden"][:, 0], z=z, state=state3
        )
        z6 = None if z is None else padded["agents", "z"]
        q6 = mods6["agent"].module.sequence(
            *args6, padded["agents", "rnn_hidden"][:, 0], z=z6, state=state6
        )
        close(q6[..., :3, :], q3)
        chosen3 = q3.gather(-1, items["agents", "action"].unsqueeze(-1))
        chosen6 = q6.gather(-1, padded["agents", "action"].unsqueeze(-1))
        q_tot3 = run.mixer.module(chosen3, items["state"])
        q_tot6 = mods6["mixer"].module(chosen6, padded["state"])
    assert q_tot3.shape == q_tot6.shape == (*items.batch_size, 1)
    close(q_tot6, q_tot3)
    if run.posterior is not None:  # every factor of the posterior, for the present robots
        with torch.no_grad():
            inputs = [
                (b["state"], b["agents", "action"], b["agents", "observation"])
                for b in (items, padded)
            ]
            loc3, scale3 = run.posterior.factors(*inputs[0])
            loc6, scale6 = mods6["posterior"].factors(*inputs[1])
        close(loc6[..., :3, :], loc3)
        close(scale6[..., :3, :], scale3)


def test_every_loss_term_and_gradient_matches_the_unpadded_team(team, monkeypatch):
    """ICCOLoss on the padded and the unpadded batch, the same seed for the bootstrap noise (drawn
    per robot, so robot i's draw does not depend on the team size)."""
    run, loss6 = team["run"], team["loss6"]
    base = torch.randn(64, 64, 6, 64, generator=torch.Generator().manual_seed(5))

    def seeded(like, **kwargs):  # robot i's noise is the same in both teams
        return base[tuple(slice(n) for n in like.shape)].to(like.dtype).clone()

    monkeypatch.setattr(torch, "randn_like", seeded)
    outs, grads = [], []
    for loss, batch in ((run.loss, team["items"]), (loss6, team["padded"])):
        loss.zero_grad(set_to_none=True)
        out = loss(batch.clone())
        total_loss(out).backward()
        outs.append(out)
        grads.append({k: p.grad for k, p in loss.named_parameters() if p.grad is not None})
    out3, out6 = outs
    assert sorted(out3.keys()) == sorted(out6.keys()) and "loss_td" in out3.keys()
    if run.coordinator is not None:
        assert {"loss_ce", "log_q", "entropy"} <= set(out3.keys())
    for key in out3.keys():
        torch.testing.assert_close(out6[key], out3[key], rtol=2e-5, atol=1e-6, msg=key)
    assert grads[0].keys() == grads[1].keys() and len(grads[0]) > 10
    for key, grad in grads[0].items():  # roundoff relative to the gradient's scale
        atol = 1e-5 * grad.abs().max().item() + 1e-12
        torch.testing.assert_close(grads[1][key], grad, rtol=1e-4, atol=atol, msg=key)


def test_the_token_mixer_is_monotone_in_present_robots_and_blind_to_absent_ones(team):
    layout6, padded = team["layout6"], team["padded"]
    state = padded["state"].flatten(0, 1)[:32].clone()  # [B, state_dim]: robots 0-2 present
    # robot 1 leaves instead (a hole in the middle), robot 4 joins with robot 0's token
    tok = state.view(32, layout6.state_tokens, layout6.state_token_dim)
    tok[:, 4] = tok[:, 0] + 0.5
    tok[:, 1] = 0.0
    present = layout6.robot_mask(state)
    assert present[:, [0, 2, 4]].all() and not present[:, [1, 3, 5]].any()
    torch.manual_seed(0)
    mixer = TokenMixer(layout6, embed_dim=8, hidden=16)
    q = torch.randn(32, 6, 1, requires_grad=True)
    q_tot = mixer(q, state)
    (grad,) = torch.autograd.grad(q_tot.sum(), q)
    assert (grad[:, [0, 2, 4]] > 0).all()  # strictly: every present robot's Q counts
    assert (grad[:, [1, 3, 5]] == 0).all()
    # finite differences: raising a present robot's Q never lowers Q_tot
    with torch.no_grad():
        for i in (0, 2, 4):
            up = q.detach().clone()
            up[:, i] += torch.rand(32, 1) * 3
            assert (mixer(up, state) >= q_tot - 1e-6).all()
        # absent robots' Q is never read: any value (huge, NaN) leaves Q_tot exactly as it is
        wild = q.detach().clone()
        wild[:, [1, 3]] = 1e6
        wild[:, 5] = float("nan")
        assert torch.equal(mixer(wild, state), q_tot.detach())


def test_default_options_build_todays_networks():
    """method.mixer=qmix and method.posterior_input=flat (the defaults) are TorchRL's QMixer and
    the flat posterior, under the parameter names of today's checkpoints."""
    from torchrl.modules import QMixer

    cfg = compose_config(["method=icco"])
    assert cfg.method.mixer == "qmix" and cfg.method.posterior_input == "flat"
    ckpt = load_checkpoint(DEMO)
    assert ckpt["cfg"]["method"]["mixer"] == "qmix"  # written before the field: converted
    assert ckpt["cfg"]["method"]["posterior_input"] == "flat"
    demo_cfg = validate(OmegaConf.create(ckpt["cfg"]))
    mods, loss = networks(demo_cfg, ObsLayout(**ckpt["layout"]))
    assert type(mods["mixer"].module) is QMixer and mods["posterior"].inputs == "flat"
    weights = policy_weights(ckpt, loss)  # an exported policy: no target copies
    load_weights(loss, weights, DEMO, "icco")  # every name and shape as written
    for name, value in weights.items():
        assert torch.equal(loss.state_dict()[name], value), name


def test_a_checkpoint_with_the_any_team_options_loads_at_other_team_sizes(team, tmp_path):
    cfg, run = team["cfg"], team["run"]
    path = save_checkpoint(tmp_path / "checkpoint.pt", {"loss": run.loss.state_dict()})
    weights = load_checkpoint(path, require=())["loss"]
    for n in (1, 2, 6):
        _, loss = networks(cfg, run.layout.with_agents(n))
        load_weights(loss, weights, path, cfg.method.name)
        for name, value in weights.items():
            assert torch.equal(loss.state_dict()[name], value), (n, name)
    # the fixed-size default is refused at another size, in one line naming the shapes
    fixed = compose_config([f"method={cfg.method.name}", "method.mixer=qmix"])
    _, loss3 = networks(fixed, run.layout)
    _, loss6 = networks(fixed, team["layout6"])
    with pytest.raises(CheckpointError, match="other shapes") as err:
        load_weights(loss6, loss3.state_dict(), path, "qmix")
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    "override, field",
    [
        ("method.mixer=vdn", "method.mixer"),
        ("method.posterior_input=graph", "method.posterior_input"),
    ],
)
def test_bad_options_fail_in_one_line_naming_the_field(override, field):
    message = check_command_line(["experiment=smoke", override])
    assert message is not None and f"'{field}'" in message and "\n" not in message


def test_bad_module_arguments_fail_in_one_line():
    layout = ResourceCollectionEnv(num_envs=1).layout
    sizes = dict(z_dim=4, hidden=8)
    with pytest.raises(ValueError, match="mixer must be one of"):
        make_mixer(layout.state_dim, layout.n_agents, kind="vdn", layout=layout)
    with pytest.raises(ValueError, match="needs the env's layout"):
        make_mixer(layout.state_dim, layout.n_agents, kind="attention")
    with pytest.raises(ValueError, match="posterior inputs must be one of"):
        Posterior(layout, n_actions=N_ACTIONS, inputs="graph", combine="product", **sizes)
    with pytest.raises(ValueError, match="needs a layout"):
        Posterior(
            n_actions=N_ACTIONS,
            n_agents=3,
            obs_dim=8,
            state_dim=8,
            inputs="tokens",
            combine="product",
            **sizes,
        )
    mixer = TokenMixer(layout, embed_dim=8, hidden=16)
    with pytest.raises(ValueError, match="TokenMixer mixes q"):
        mixer(torch.zeros(2, layout.n_agents + 1, 1), torch.zeros(2, layout.state_dim))


def test_the_envs_absent_robots_are_what_the_networks_mask():
    """A 6-robot env of teams 2-4, a robot taken out mid-team: the mask read off the state is the
    env's, and every env's present robots get the z and Q_tot of its team without the absent."""
    env = ResourceCollectionEnv(num_envs=4, n_agents=6, team_sizes=(2, 3, 4), seed=0)
    td = env.reset()
    largest = int(env.present.sum(1).argmax())
    assert env.present[largest].sum() >= 3
    env.remove_robot(largest, 1, tensordict=td)  # a hole in the middle of the team
    assert not env.present[largest, 1] and env.present[largest, 2]
    cfg = compose_config(["method=icco", *ANY_TEAM])
    torch.manual_seed(0)
    mods6 = make_modules(cfg, env.layout, "cpu", n_actions=N_ACTIONS)
    q = torch.randn(4, 6, 1)
    for _ in range(3):
        state, present = td["state"], env.present
        assert torch.equal(env.layout.robot_mask(state), present)
        with torch.no_grad():
            loc6, _ = mods6["coordinator"].module.distribution(state)
            q_tot6 = mods6["mixer"].module(q, state)
        for b in range(4):
            idx = present[b].nonzero().squeeze(-1)
            layout = env.layout.with_agents(len(idx))
            tok = state[b].view(env.layout.state_tokens, -1)
            compact = torch.cat([tok[idx], tok[env.n_agents :]]).flatten()
            mods = make_modules(cfg, layout, "cpu", n_actions=N_ACTIONS)
            for name in ("coordinator", "mixer"):
                mods[name].load_state_dict(mods6[name].state_dict())
            with torch.no_grad():
                loc, _ = mods["coordinator"].module.distribution(compact)
                q_tot = mods["mixer"].module(q[b, idx], compact)
            close(loc6[b, idx], loc)
            close(q_tot6[b], q_tot)
        action = torch.randint(0, N_ACTIONS, (4, 6))
        td = env.step(td.set(("agents", "action"), action))["next"]


def test_the_layout_names_the_state_columns_the_env_writes_and_its_rule_for_any_team():
    """ObsLayout's columns read back what the env wrote (positions, velocities, type, flag,
    waypoints), its presence rule is the env's ``present``, and ``with_agents`` is the layout
    of the env built for another team size (what a checkpoint is resized with)."""
    from icco_torchrl.training.restore import resized_layout

    env = ResourceCollectionEnv(num_envs=3, n_agents=4, team_sizes=[2, 3, 4], seed=2)
    td = env.reset()
    L = env.layout
    assert L == ObsLayout.for_env(4, env.n_resources, env.n_invaders, env.n_waypoints)
    tok, present = L.tokens(td["state"]), env.present
    robots, N, R = tok[:, : env.n_agents], env.n_agents, env.n_resources
    assert torch.equal(L.robot_mask(td["state"]), present) and not present.all()
    here = present.unsqueeze(-1)
    torch.testing.assert_close(robots[..., L.POSITION], env.pos * here)
    torch.testing.assert_close(robots[..., L.VELOCITY], env.vel * here)
    assert torch.equal(robots[..., L.FLAG].bool(), env.carry & present)
    torch.testing.assert_close(robots[..., L.waypoints], env.waypoints.flatten(-2) * here)
    torch.testing.assert_close(tok[:, N : N + R, L.POSITION], env.res_pos)
    assert (tok[:, N : N + R, L.RESOURCE] == 1).all() and (tok[:, N + R :, L.INVADER] == 1).all()
    assert torch.equal(
        L.typed(td["state"]), torch.cat([present, torch.ones(3, R + env.n_invaders)], 1) > 0
    )
    for n in (1, 2, 6):
        other = ResourceCollectionEnv(num_envs=1, n_agents=n).layout
        assert L.with_agents(n) == other
        assert resized_layout(vars(L), n) == vars(other)
    assert ObsLayout.from_dict({**vars(L), "unknown": 0}) == L
