"""Reference policies: the yardsticks behave as their names say, on small batched runs; role
blends act as hand-computed on a built scene; the scripted frontier's search runs on a tiny grid."""

import doctest
import importlib.util
import json
import math
from pathlib import Path

import pytest
import torch

from icco_torchrl.envs import ResourceCollectionEnv, reference_policies
from icco_torchrl.envs.reference_policies import (
    BEST_SCRIPTED,
    REFERENCE_POLICIES,
    BlendPolicy,
    HeuristicPolicy,
    RoleRadii,
    make_reference_policy,
    parse_reference,
    reference_key,
    reference_label,
)
from icco_torchrl.evaluation import episode_metrics
from icco_torchrl.training.build import EVAL_SEED_OFFSET, compose_config, make_env
from icco_torchrl.training.config import ConfigError, validate

CALIBRATION = Path(__file__).resolve().parents[1] / "experiments" / "calibration"

EPISODES = 96


def run(name, radius=None, scale=1.0, seed=0, **env_kwargs):
    env = ResourceCollectionEnv(num_envs=EPISODES, seed=seed, inst_reward_scale=scale, **env_kwargs)
    policy = make_reference_policy(name, env, radius=radius)
    with torch.no_grad():
        m = episode_metrics(env.rollout(env.max_steps, policy, break_when_any_done=False))
    m["task_reward"] = m["reward"] - m["inst_reward"]
    return {k: v.mean().item() for k, v in m.items()}


@pytest.fixture(scope="module")
def results():
    out = {name: run(name) for name in ("random", "follower", "heuristic")}
    for r in (0.0, 1.0, 1.75, 2.5, math.inf):
        out[r] = run("blend", radius=r)
    return out


def test_heuristic_does_the_task_far_better_than_random(results):
    h, rnd = results["heuristic"], results["random"]
    assert h["pick"] > 5 * rnd["pick"] and h["collect"] > 20 * max(rnd["collect"], 0.05)
    assert h["defense"] > 4 * rnd["defense"]
    assert h["invasion"] < 0.5 * rnd["invasion"]
    assert h["task_reward"] > rnd["task_reward"] + 80


def test_follower_follows_far_better_than_random(results):
    f, rnd = results["follower"], results["random"]
    assert f["inst_reward"] > rnd["inst_reward"] + 300  # unit scale, 3 robots x 145 steps
    assert f["inst_reward"] > 0.7 * 3 * 145  # mean cosine > 0.7 per robot-step


def test_blend_moves_monotonically_from_follower_to_heuristic(results):
    radii = (0.0, 1.0, 1.75, 2.5, math.inf)
    task = [results[r]["task_reward"] for r in radii]
    inst = [results[r]["inst_reward"] for r in radii]
    assert all(b > a for a, b in zip(task, task[1:])), task
    assert all(b < a for a, b in zip(inst, inst[1:])), inst
    # the ends are the pure policies (same episodes, same seed: identical totals)
    assert results[0.0] == pytest.approx(results["follower"])
    assert results[math.inf] == pytest.approx(results["heuristic"])


def test_calibrated_preset_rewards_a_policy_that_follows_and_works():
    scale = compose_config([]).env.params.inst_reward_scale
    assert scale < 1.3, "the default reward is the calibrated one, not the paper's constant"
    team = {r: run("blend", radius=r, scale=scale, seed=5)["reward"] for r in (0.0, 1.75, math.inf)}
    assert team[1.75] > team[0.0] + 5 and team[1.75] > team[math.inf] + 5, team
    paper = {r: run("blend", radius=r, scale=1.3, seed=5)["reward"] for r in (0.0, 1.75, math.inf)}
    assert paper[0.0] > paper[1.75] > paper[math.inf], "under the paper's constant following wins"


def test_heuristic_targets_on_a_hand_built_scene():
    env = ResourceCollectionEnv(num_envs=1, seed=0)
    env.reset()
    env.pos[0] = torch.tensor([[2.0, 2.0], [-2.0, -2.0], [2.5, -2.5]])
    env.vel.zero_()
    env.carry[0] = torch.tensor([True, False, False])
    env.res_pos[0] = torch.tensor(
        [[-2.0, -1.0], [-1.5, -2.0], [3.0, 3.0], [-3.0, 3.0], [0.0, 3.0], [1.0, -3.0]]
    )
    env.inv_active[0] = True
    env.inv_pos[0] = torch.tensor([[3.0, -2.0]])  # robot 2 is next to its path home
    target, _ = HeuristicPolicy(env).targets()
    assert torch.allclose(target[0, 0], torch.zeros(2))  # the carrier goes home
    assert torch.allclose(target[0, 1], torch.tensor([-1.5, -2.0]))  # nearest resource
    inv_path = target[0, 2] / target[0, 2].norm()
    assert torch.allclose(
        inv_path, torch.tensor([3.0, -2.0]) / math.hypot(3, 2), atol=1e-4
    )  # on the invader's path
    assert target[0, 2].norm() < math.hypot(3, 2)  # ahead of the invader, not behind it
    # Steering: a robot at rest west of its target pushes +x.
    env.pos[0, 1] = torch.tensor([-2.5, -2.0])
    assert HeuristicPolicy(env).act()[0, 1].item() == 2


def test_bad_requests_fail_with_one_clear_line():
    env = ResourceCollectionEnv(num_envs=2)
    with pytest.raises(ValueError, match="needs radius"):
        make_reference_policy("blend", env)
    with pytest.raises(ValueError, match="radius must be"):
        BlendPolicy(env, -1.0)
    with pytest.raises(TypeError, match="drive a ResourceCollectionEnv"):
        make_reference_policy("heuristic", object())


def test_reference_policies_drive_the_training_env_and_are_deterministic():
    cfg = compose_config(["experiment=smoke"])
    for name in REFERENCE_POLICIES:
        outs = []
        for _ in range(2):
            env = make_env(cfg, num_envs=4, seed=7)  # TransformedEnv with the policy primer
            policy = make_reference_policy(name, env, radius=1.0, seed=3)
            outs.append(env.rollout(20, policy, break_when_any_done=False)["agents", "action"])
        assert torch.equal(outs[0], outs[1]), name


def test_seeded_evaluations_replay_the_same_episodes():
    from icco_torchrl.evaluation import evaluate

    cfg = compose_config(["experiment=smoke"])
    env = make_env(cfg, num_envs=4, seed=1)
    policy = make_reference_policy("heuristic", env)
    first, again = evaluate(env, policy, seed=11), evaluate(env, policy, seed=11)
    assert first == again  # a deterministic policy on re-seeded envs: identical totals
    assert evaluate(env, policy) != first  # without a seed the env moves on to new episodes


# Actions: 0 no-op, 1 -x, 2 +x, 3 -y, 4 +y.
FOLLOW, DEFEND, COLLECT, DELIVER = [3, 4, 3], 4, 1, 4


def role_scene(num_envs=1):
    """Robot 0 is next to the invader's path home (the interceptor: its point is (1.83, 0), 0.82 m
    up and a little east: +y); robot 1 is 1 m east of a resource (collects: -x); robot 2 carries,
    1.2 m below home (delivers: +y).
    Each robot's waypoints run from it along -y, +y, -y: following is -y, +y, -y."""
    env = ResourceCollectionEnv(num_envs=num_envs, seed=0)
    env.reset()
    pos = torch.tensor([[1.4, -0.7], [-2.0, 2.0], [0.0, -1.2]])
    env.pos[:] = pos
    env.vel.zero_()
    env.carry[:] = torch.tensor([False, False, True])
    env.res_pos[:] = torch.tensor(
        [[-3.0, 2.0], [3.0, 3.0], [-3.0, -3.0], [3.0, -3.0], [0.0, 3.0], [-3.2, -0.5]]
    )
    env.inv_active[:] = True
    env.inv_pos[:] = torch.tensor([[2.4, 0.0]])  # walking home along -x
    k = torch.arange(env.n_waypoints, dtype=torch.float32)
    along = torch.tensor([-1.0, 1.0, -1.0])  # -y, +y, -y
    wp = pos[:, None, :].repeat(1, env.n_waypoints, 1)
    wp[..., 1] += 0.2 * k * along[:, None]
    env.waypoints = wp.expand(num_envs, *wp.shape).clone()
    return env


@pytest.mark.parametrize(
    "name, actions",
    [
        ("follower", FOLLOW),
        ("heuristic", [DEFEND, COLLECT, DELIVER]),
        ("blend(1.75)", [DEFEND, COLLECT, DELIVER]),  # one radius: every role works
        ("blend(defend=1.75)", [DEFEND, 4, 3]),  # defend-first: the others follow
        ("blend(defend=0.8)", FOLLOW),  # the interception point is 0.82 m away
        ("blend(collect=1.75)", [3, COLLECT, 3]),
        ("blend(deliver=1.75)", [3, 4, DELIVER]),
        ("blend(defend=1.75, collect=1, deliver=1)", [DEFEND, COLLECT, 3]),  # home is 1.2 m away
        ("blend(defend=1.75, follow=pursuit)", [DEFEND, 4, 3]),  # the others pursue: -y, +y
    ],
)
def test_role_blends_act_as_hand_computed(name, actions):
    env = role_scene()
    target, dist, role = HeuristicPolicy(env).plan()
    assert role[0].tolist() == [0, 1, 2]  # defend, collect, deliver
    assert torch.allclose(target[0, 1], torch.tensor([-3.0, 2.0]))
    assert torch.allclose(target[0, 2], torch.zeros(2))
    assert torch.allclose(target[0, 0], torch.tensor([1.83, 0.0]), atol=1e-4)  # on its path
    assert dist[0, 0] == pytest.approx(math.hypot(0.43, 0.7), abs=1e-4)
    assert make_reference_policy(name, env, radius=0.0).act()[0].tolist() == actions


def test_a_grid_of_role_blends_runs_in_one_batch():
    """A tensor of radii per env acts as each env's blend alone (a frontier's grid in one env)."""
    env = role_scene(num_envs=3)
    radii = torch.tensor([[0.0, 0.0, 0.0], [1.75, 0.0, 0.0], [math.inf, math.inf, math.inf]])
    actions = BlendPolicy(env, radii).act()
    assert actions.tolist() == [FOLLOW, [DEFEND, 4, 3], [DEFEND, COLLECT, DELIVER]]


def test_one_radius_is_every_role_and_best_scripted_is_its_blend():
    def actions(name):
        env = ResourceCollectionEnv(num_envs=8, seed=3)
        policy = make_reference_policy(name, env, radius=1.75)
        return env.rollout(30, policy, break_when_any_done=False)["agents", "action"]

    same = actions("blend")
    assert torch.equal(same, actions("blend(1.75)"))
    assert torch.equal(same, actions("blend(defend=1.75, collect=1.75, deliver=1.75)"))
    radii = ", ".join(f"{k}={v}" for k, v in BEST_SCRIPTED._asdict().items())
    assert torch.equal(actions("best_scripted"), actions(f"blend({radii})"))


def test_a_blend_that_pursues_is_pursuit_outside_its_radii_and_the_heuristic_inside():
    """``follow=pursuit``: radius 0 everywhere plays the path follower, inf the heuristic, and in
    between it differs from the greedy follower's blend (the switch is wired)."""

    def actions(name):
        env = ResourceCollectionEnv(num_envs=8, seed=3)
        policy = make_reference_policy(name, env)
        return env.rollout(40, policy, break_when_any_done=False)["agents", "action"]

    assert torch.equal(actions("blend(0, follow=pursuit)"), actions("pursuit"))
    assert torch.equal(actions("blend(inf, follow=pursuit)"), actions("heuristic"))
    assert not torch.equal(
        actions("blend(defend=1.75, follow=pursuit)"), actions("blend(defend=1.75)")
    )


def test_reference_names_parse_label_and_key_round_trip():
    assert parse_reference("blend") == ("blend", None, "follower")
    assert parse_reference(" blend( collect = inf ) ")[:2] == ("blend", RoleRadii(0, math.inf, 0))
    assert parse_reference("best_scripted") == ("blend", BEST_SCRIPTED, "follower")
    assert parse_reference("blend(1, follow = pursuit)") == ("blend", RoleRadii(1, 1, 1), "pursuit")
    for name in ("blend(defend=1.75, follow=pursuit)", "blend(2, follow=pursuit)"):
        assert parse_reference(reference_key(reference_label(name))) == parse_reference(name)
    assert reference_label("blend") == "blend (r=1.75 m)"
    assert reference_label("blend", 1.0) == reference_label("blend(1)") == "blend (r=1 m)"
    label = reference_label("blend(defend=1.75, deliver=2)")
    assert label == "blend (defend=1.75, collect=0, deliver=2 m)"
    assert parse_reference(reference_key(label)) == parse_reference("blend(defend=1.75,deliver=2)")
    assert reference_key(reference_label("best_scripted")) == "best_scripted"
    assert reference_key("blend (r=1.75 m)") == "blend" and reference_key("ICCO") is None
    for name in ("random", "follower", "heuristic"):
        assert reference_key(reference_label(name)) == name


@pytest.fixture(scope="module")
def base_config():
    cfg = compose_config(["eval.references=['blend(defend=1.75)', best_scripted]"])
    assert list(cfg.eval.references) == ["blend(defend=1.75)", "best_scripted"]  # valid names
    return cfg


@pytest.mark.parametrize(
    "name, message",
    [
        ("greedy", "unknown reference policy 'greedy'"),
        ("blend(defend=-1)", "radius 'defend' must be a number >= 0"),
        ("blend(collect=far)", "radius 'collect' must be a number >= 0 (metres), got 'far'"),
        ("blend(deliver=nan)", "radius 'deliver' must be a number >= 0"),
        ("blend(-0.5)", "radius must be a number >= 0"),
        ("blend(attack=1)", "unknown role 'attack'; roles are defend, collect, deliver"),
        ("blend(defend=1, defend=2)", "role 'defend' is given twice"),
        ("blend()", "gives no radius"),
        ("blend(1, 2)", "'1' is not role=radius"),
        ("blend(1, follow=greedy)", "follow must be one of follower, pursuit, got 'greedy'"),
        ("blend(follow=pursuit)", "gives no radius"),
    ],
)
def test_bad_reference_names_fail_in_one_line_naming_the_field(name, message, base_config):
    env = ResourceCollectionEnv(num_envs=2)
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")) as err:
        make_reference_policy(name, env)
    assert "\n" not in str(err.value)
    cfg = base_config.copy()
    cfg.eval.references = ["follower", name]
    with pytest.raises(ConfigError, match="config field 'eval.references'") as err:
        validate(cfg)
    assert "\n" not in str(err.value) and name in str(err.value)


def test_bad_radii_fail_naming_the_role():
    env = ResourceCollectionEnv(num_envs=2)
    with pytest.raises(ValueError, match="blend radius 'collect' must be a number >= 0"):
        BlendPolicy(env, {"defend": 1.0, "collect": -1})
    with pytest.raises(ValueError, match="blend radius must be a number >= 0.*got True"):
        BlendPolicy(env, True)
    with pytest.raises(ValueError, match="blend role 'intercept' is unknown"):
        BlendPolicy(env, {"intercept": 1.0})
    with pytest.raises(ValueError, match=r"radii tensor must be \[3\] or \[num_envs=2, 3\]"):
        BlendPolicy(env, torch.tensor([[1.0, -1.0, 0.0]] * 2))


def test_module_examples_run():
    assert doctest.testmod(reference_policies).failed == 0


def _best_scripted_script():
    spec = importlib.util.spec_from_file_location("best_scripted", CALIBRATION / "best_scripted.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_frontier_search_on_a_tiny_grid(tmp_path):
    bs = _best_scripted_script()
    presets = bs.reward_presets()
    assert {"calibrated", "paper"} <= set(presets)
    assert [n for n, p in presets.items() if p["default"]] == ["calibrated"]
    grid = {"defend": (0.0, math.inf), "collect": (0.0, 1.0), "deliver": (0.0,)}
    result = bs.search(grid, presets=presets, search_trials=2, confirm_trials=2, top=1, steps=4)
    found = result["search"]["points"]
    assert [RoleRadii(**p["radii"]) for p in found] == bs.grid_points(grid)
    assert len(found) == 4 and all(p["trials"] == 2 for p in found)
    # the search and the confirmation play episodes no evaluation plays
    assert EVAL_SEED_OFFSET not in (result["search"]["seed"], result["confirm"]["seed"])
    assert result["search"]["seed"] != result["confirm"]["seed"]
    confirmed = result["confirm"]["points"]
    for name in presets:
        top = max(confirmed, key=lambda p: p["team"][name]["mean"])
        assert result["best"][name] == top["radii"]
        c = result["collecting"][name]
        assert c["with"]["collect"] > 0 and c["without"]["collect"] == 0
        team = {bs.blend_name(p["radii"]): p["team"][name]["mean"] for p in confirmed}
        worth = team[bs.blend_name(c["with"])] - team[bs.blend_name(c["without"])]
        assert c["worth"] == pytest.approx(worth)
    # one rollout scores every preset: the instruction reward is the only difference
    p = found[0]
    inst = p["team"]["paper"]["mean"] - p["team"]["calibrated"]["mean"]
    assert inst == pytest.approx((1.3 - 0.3) * p["metrics"]["inst_reward"], abs=1e-3)
    # the README section renders from the json alone
    result.update(presets=presets, default_preset="calibrated", top=1, wall_s=1.0)
    result["evaluation"] = bs.replay(result, trials=2, steps=4)
    decoded = bs._decode(json.loads(json.dumps(bs._encode(result))))
    section = bs.render(decoded)
    assert section.startswith(bs.BEGIN) and "### `reward=paper`" in section
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n\n{bs.BEGIN}\nold\n{bs.END}\ntail\n")
    bs.write_readme(section, readme)
    assert readme.read_text() == f"intro\n\n{section}tail\n"


def test_best_scripted_is_the_frontier_result_on_file():
    result = json.loads((CALIBRATION / "results" / "best_scripted.json").read_text())
    best = {k: float(v) for k, v in result["best"][result["default_preset"]].items()}
    assert RoleRadii(**best) == BEST_SCRIPTED
