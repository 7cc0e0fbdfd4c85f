"""ICCOLoss reused on another env with renamed keys (``examples/reuse_loss.py``)."""

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from icco_torchrl.modules.policy import make_policy
from icco_torchrl.objectives import ICCOLoss

torch.set_num_threads(1)

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "reuse_loss.py"


def _load():
    spec = importlib.util.spec_from_file_location("reuse_loss_example", EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


ex = _load()


def _has_agents_key(td):
    return any((k[0] if isinstance(k, tuple) else k) == "agents" for k in td.keys(True, True))


@pytest.fixture(scope="module")
def segments():
    parts = ex.build(num_envs=4, seed=0)
    parts["env"].set_seed(0)
    with torch.no_grad():
        ro = parts["env"].rollout(20, parts["policy"], break_when_any_done=False)
    return parts, ro, parts["cutter"](ro)


def test_rendezvous_env_specs_and_dynamics():
    env = ex.RendezvousEnv(num_envs=3, n_agents=3, max_steps=20, seed=0)
    check_env_specs(env)
    check_env_specs(ex.make_env(3, 3, hidden=8, z_dim=4, seed=0))
    assert env.reward_keys == ["team_reward"] and env.action_keys == [("robots", "move")]
    td = env.reset()
    # hand-made scene: robots at (0,0), (0.3,0), (0,0.4); robot 0 moves +x, robot 1 stays, robot 2
    # moves -y
    env.pos = torch.tensor([[0.0, 0.0], [0.3, 0.0], [0.0, 0.4]]).expand(3, 3, 2).clone()
    td["robots", "move"] = torch.tensor([2, 0, 3]).expand(3, 3).clone()
    out = env.step(td)["next"]
    # new positions (0.1,0), (0.3,0), (0,0.3): distances 0.2, sqrt(0.01+0.09), sqrt(0.09+0.09)
    expected = -(0.2 + math.sqrt(0.1) + math.sqrt(0.18)) / 3
    torch.testing.assert_close(out["team_reward"], torch.full((3, 1), expected))
    torch.testing.assert_close(
        out["robots", "obs"][0, 1], torch.tensor([0.3, 0.0, -0.2, 0.0, -0.3, 0.3])
    )
    torch.testing.assert_close(out["world"][0], torch.tensor([0.1, 0.0, 0.3, 0.0, 0.0, 0.3]))
    ro = env.rollout(25, break_when_any_done=False)
    done = ro["next", "done"].squeeze(-1)
    assert done[:, 19].all() and done.sum() == 3 and not ro["next", "terminated"].any()
    assert (ro["step_count"][:, 20] == 0).all()


def test_data_uses_renamed_keys_only(segments):
    _, ro, seg = segments
    assert not _has_agents_key(ro) and not _has_agents_key(seg)
    for key in [
        ("robots", "obs"),
        ("robots", "move"),
        "world",
        ("next", "team_reward"),
        ("robots", "z_noise"),
        ("robots", "rnn_hidden"),
        ("robots", "prev_action"),
        "mask",
    ]:
        assert key in seg.keys(True, True), key
    assert "reward" not in seg["next"].keys() and "state" not in seg.keys()


def test_loss_reads_renamed_keys(segments):
    parts, _, seg = segments
    loss = parts["loss"]
    # the posterior declares no keys of its own: the loss reads the segment through its renamed keys
    assert not hasattr(parts["posterior"], "in_keys")
    out = loss(seg)
    for name in ("loss_td", "loss_ce", "log_q", "entropy"):
        assert torch.isfinite(out[name]), name
    assert out["loss_td"] > 0
    # the reward it bootstraps from is ("next", "team_reward"): shifting it changes the TD loss
    seg2 = seg.clone()
    seg2["next", "team_reward"] += 1.0
    assert not torch.allclose(loss(seg2)["loss_td"], out["loss_td"])
    # and gradients flow into the coordinator through z and into the posterior through L_CE
    loss.zero_grad()
    (out["loss_td"] + out["loss_ce"]).backward()
    assert loss.coordinator_params["module", "loc", "weight"].grad.abs().sum() > 0
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in loss.posterior.parameters())


def test_loss_without_set_keys_names_the_missing_key(segments):
    parts, _, seg = segments
    plain = ICCOLoss(
        parts["agent"],
        parts["mixer"],
        parts["coordinator"],
        parts["posterior"],
        gamma=parts["loss"].gamma,
    )
    with pytest.raises(KeyError) as err:
        plain(seg)
    msg = err.value.args[0]
    assert "('agents', 'action')" in msg and "[S, T, N]" in msg
    # renaming only the action moves the complaint on to the next default key it reads
    plain.set_keys(action=("robots", "move"))
    with pytest.raises(KeyError) as err:
        plain(seg)
    assert "('agents', 'observation')" in err.value.args[0]
    plain.set_keys(**ex.LOSS_KEYS)
    torch.manual_seed(0)  # the bootstrap z at the next broadcast uses fresh noise
    mine = plain(seg)["loss_td"]
    torch.manual_seed(0)
    torch.testing.assert_close(mine, parts["loss"](seg)["loss_td"], atol=0.0, rtol=0.0)


def test_make_policy_accepts_another_action_name(segments):
    parts = segments[0]
    policy = make_policy(
        parts["agent"],
        parts["env"].full_action_spec_unbatched,
        parts["coordinator"],
        group="robots",
        action_name="move",
    )
    td = policy(parts["env"].reset())
    move = td.get(("robots", "move"))  # the action lands under the renamed key, in range
    assert move.shape[:2] == td.get(("robots", "obs")).shape[:2] and (
        "robots",
        "action",
    ) not in td.keys(True)


def test_main_tiny_budget():
    result = ex.main(total_frames=640, seed=0)
    assert result["frames"] == 640 and result["updates"] > 0 and len(result["history"]) > 0
    for name in (
        "first_loss_td",
        "last_loss_td",
        "first_loss_ce",
        "last_loss_ce",
        "eval_return_before",
        "eval_return_after",
    ):
        assert math.isfinite(result[name]), name
    for row in result["history"]:
        assert all(math.isfinite(v) for v in row.values())
    # an episode of 20 steps with rewards in [-3, 0]: a sane greedy return
    assert -60 < result["eval_return_before"] < 0 and -60 < result["eval_return_after"] < 0
    keys = result["sample_keys"]
    assert "('robots', 'obs')" in keys and "('next', 'team_reward')" in keys and "world" in keys
    assert not any("agents" in k for k in keys)
    # seeded CPU runs are reproducible
    again = ex.main(total_frames=640, seed=0)
    assert again["last_loss_td"] == result["last_loss_td"]
    assert again["eval_return_after"] == result["eval_return_after"]


def test_example_runs_as_a_script():
    proc = subprocess.run(
        [sys.executable, str(EXAMPLE), "--total-frames", "320", "--seed", "1"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=EXAMPLE.parent,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout[proc.stdout.index("{") :])
    assert result["frames"] == 320 and math.isfinite(result["last_loss_td"])
