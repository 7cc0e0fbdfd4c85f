"""Per-env team sizes: ``team_sizes`` drawn at reset, robots removed and added mid-episode, and
the absent-robot contract (masked out of observations, rewards, events, others' views and the
state). The fixed-team env (``team_sizes=None``) must keep the dynamics of the env before team
sizes existed: :data:`FINGERPRINTS` was recorded from that env.
"""

import hashlib
import math

import pytest
import torch
from torchrl.envs.utils import check_env_specs, step_mdp

from icco_torchrl.envs import N_ACTIONS, ResourceCollectionEnv
from icco_torchrl.envs.reference_policies import BlendPolicy, HeuristicPolicy
from icco_torchrl.envs.shaping import StatePotential

torch.set_num_threads(1)

PRESENT = ("agents", "present")

# Every tensor of a seeded 300-step rollout (auto-reset, so the partial resets are in it) of the
# env at commit 91df3ae, before team sizes: see `fingerprint`. Integer and bool tensors (actions,
# events, dones, step counts) are held exactly, by sha256 (first 16 hex digits); float tensors by
# (sum, norm, projection on a seeded random vector) in float64, to FLOAT_RTOL. Float bits are not
# held: Intel and AMD cores round the last bit of the same float32 sums differently (docs/task.md,
# "Reproducibility"), while the discrete outcomes agree on both.
FINGERPRINT_CASES = (
    dict(seed=0, num_envs=16, kwargs={}),
    dict(seed=1, num_envs=5, kwargs={}),
    dict(seed=2, num_envs=8, kwargs=dict(spawn="copa", waypoint_path_prob=0.3)),
)
FINGERPRINTS = (
    {
        "agents/action": "9c43806f43275d5c",
        "agents/observation": (512.547834, 355.07617, 589.940254),
        "agents/waypoints": (-35160.046011, 625.383143, 766.126179),
        "events/collect": "d2812ab51a470ceb",
        "events/defense": "29ada1c88bb24dba",
        "events/inst_reward": (-1800.279368, 112.707866, 77.650108),
        "events/invasion": "35c196b67ce07806",
        "events/pick": "42f8a198d0f08b53",
        "next/agents/observation": (475.32626, 355.355283, 608.15275),
        "next/agents/reward": (-2401.16087, 123.379402, -98.922667),
        "next/agents/waypoints": (-35406.997779, 625.651382, 818.826292),
        "next/done": "297907d49dfd2334",
        "next/events/collect": "1f31187e0bd159de",
        "next/events/defense": "974ff9714a384e99",
        "next/events/inst_reward": (-1808.16084, 113.256317, 114.986468),
        "next/events/invasion": "04831f8bb5ff9c73",
        "next/events/pick": "e234787f1a648fe9",
        "next/reward": (-2401.160867, 136.069337, 175.37944),
        "next/state": (9696.747985, 865.498822, 2121.415294),
        "next/step_count": "054d72e7744b4787",
        "next/terminated": "24ddaa4710480313",
        "next/truncated": "297907d49dfd2334",
        "done": "24ddaa4710480313",
        "state": (9970.257526, 865.267841, 2300.507396),
        "step_count": "5fd60496b9574903",
        "terminated": "24ddaa4710480313",
        "truncated": "24ddaa4710480313",
    },
    {
        "agents/action": "92c498a45131f630",
        "agents/observation": (3887.368469, 197.999218, 279.840898),
        "agents/waypoints": (3283.37353, 347.166474, -321.574326),
        "events/collect": "c343e2bd32f31f78",
        "events/defense": "bccccfa7db35957c",
        "events/inst_reward": (-586.438544, 61.459716, -22.829574),
        "events/invasion": "474e7170358cef29",
        "events/pick": "89b90248e99db73d",
        "next/agents/observation": (3876.777315, 198.167028, 262.863681),
        "next/agents/reward": (-776.674177, 68.818153, -89.459066),
        "next/agents/waypoints": (3258.394816, 347.440702, -337.137268),
        "next/done": "78f1037002a0b2a8",
        "next/events/collect": "18b67d9cb9dd6c22",
        "next/events/defense": "3014a1ff77debb2e",
        "next/events/inst_reward": (-587.674166, 61.61484, -2.870563),
        "next/events/invasion": "a62029e8c41d1e3c",
        "next/events/pick": "2ab38fe2525af201",
        "next/reward": (-776.674175, 73.967062, 26.440673),
        "next/state": (24638.066546, 479.675899, -196.168403),
        "next/step_count": "14590d8e72c9f604",
        "next/terminated": "6249da5c681dd8a5",
        "next/truncated": "78f1037002a0b2a8",
        "done": "6249da5c681dd8a5",
        "state": (24645.007311, 479.413862, -197.019838),
        "step_count": "430c55a5cea27409",
        "terminated": "6249da5c681dd8a5",
        "truncated": "6249da5c681dd8a5",
    },
    {
        "agents/action": "31d78449faeb4186",
        "agents/observation": (2400.438269, 373.729188, 85.682285),
        "agents/waypoints": (-331.492186, 441.108567, 134.554002),
        "events/collect": "17744bb6a4ed1d9d",
        "events/defense": "6cdcfd6788aaf7c5",
        "events/inst_reward": (-1412.075798, 83.675978, -28.995279),
        "events/invasion": "1c0a6d20ed9ae9e3",
        "events/pick": "45869658ea7dedfe",
        "next/agents/observation": (2409.969381, 374.242487, 147.091234),
        "next/agents/reward": (-1623.793339, 87.884964, 64.597706),
        "next/agents/waypoints": (-311.017853, 441.533827, 130.607509),
        "next/done": "8cf10cd1e78fe1f7",
        "next/events/collect": "17744bb6a4ed1d9d",
        "next/events/defense": "e71a0245f598f7ae",
        "next/events/inst_reward": (-1425.793324, 84.258799, 37.097824),
        "next/events/invasion": "409d370a7eb40928",
        "next/events/pick": "e9e08c6317f2f82b",
        "next/reward": (-1623.793331, 95.886825, 57.266961),
        "next/state": (28979.527386, 609.212677, -1176.716732),
        "next/step_count": "8b238c9c161d4ba2",
        "next/terminated": "a0ee989ed2a0a2e3",
        "next/truncated": "8cf10cd1e78fe1f7",
        "done": "a0ee989ed2a0a2e3",
        "state": (28893.618433, 608.605228, -1089.632796),
        "step_count": "6728502ec69bb852",
        "terminated": "a0ee989ed2a0a2e3",
        "truncated": "a0ee989ed2a0a2e3",
    },
)


def fingerprint(seed, num_envs, kwargs, steps=300):
    env = ResourceCollectionEnv(num_envs=num_envs, seed=seed, n_agents=3, **kwargs)
    gen = torch.Generator().manual_seed(seed)
    shape = (num_envs, 3)

    def policy(td):
        return td.set(("agents", "action"), torch.randint(0, N_ACTIONS, shape, generator=gen))

    ro = env.rollout(steps, policy=policy, break_when_any_done=False)
    out = {}
    for key in sorted(ro.keys(True, True), key=str):
        if isinstance(key, tuple) and key[-1] == "present":
            continue  # new with team sizes; checked below
        t = ro.get(key).contiguous()
        name = "/".join(key) if isinstance(key, tuple) else key
        if t.is_floating_point():
            x = t.double().flatten()
            gen64 = torch.Generator().manual_seed(7)
            proj = torch.randn(x.numel(), generator=gen64, dtype=torch.float64)
            out[name] = (x.sum().item(), x.norm().item(), (x @ proj).item())
        else:
            out[name] = hashlib.sha256(t.numpy().tobytes()).hexdigest()[:16]
    return out, ro


# float32 roundoff over a 300-step rollout, relative to each tensor's norm: a last-bit difference
# per element moves the sums by ~1e-7 of the norm; a changed dynamic moves them by far more.
FLOAT_RTOL = 1e-5


@pytest.mark.parametrize("case, expected", list(zip(FINGERPRINT_CASES, FINGERPRINTS)))
def test_fixed_team_env_keeps_the_dynamics_of_the_env_before_team_sizes(case, expected):
    got, ro = fingerprint(**case)
    assert got.keys() == expected.keys()
    for name, want in expected.items():
        if isinstance(want, str):
            assert got[name] == want, name  # discrete: exact on every CPU
        else:
            tol = FLOAT_RTOL * max(want[1], 1.0)
            assert got[name] == pytest.approx(want, rel=FLOAT_RTOL, abs=tol), name
    assert ro["agents", "present"].all() and ro["next", "agents", "present"].all()


def test_a_seeded_rollout_is_bit_identical_when_repeated_on_one_machine():
    """Same machine, same thread count: every bit repeats (what docs/task.md promises)."""
    case = FINGERPRINT_CASES[1]
    (_, first), (_, second) = fingerprint(**case, steps=60), fingerprint(**case, steps=60)
    assert (first == second).all()


def random_policy(env, seed=0):
    gen = torch.Generator().manual_seed(seed)
    shape = (env.num_envs, env.n_agents)
    return lambda td: td.set(
        ("agents", "action"), torch.randint(0, N_ACTIONS, shape, generator=gen)
    )


def other_robot_tokens(env, obs):
    """``tokens[..., n, j]``: robot j's entity token in robot n's observation (zeros for j = n)."""
    L, N = env.layout, env.n_agents
    ent = obs[..., L.own_dim :].unflatten(-1, (L.n_entities, L.entity_dim))
    out = torch.zeros(*obs.shape[:-2], N, N, L.entity_dim)
    for n in range(N):
        for j in range(N):
            if j != n:
                out[..., n, j, :] = ent[..., n, j - (j > n), :]
    return out


def robot_state_tokens(env, state):
    L = env.layout
    return state.unflatten(-1, (L.state_tokens, L.state_token_dim))[..., : env.n_agents, :]


@pytest.fixture(scope="module")
def team_rollout():
    """32 envs x 300 random steps (2 episodes and a partial reset each) of teams of 1-3 of 4."""
    env = ResourceCollectionEnv(num_envs=32, seed=3, n_agents=4, team_sizes=[1, 2, 3])
    return env, env.rollout(300, policy=random_policy(env), break_when_any_done=False)


# ---------------------------------------------------------------- drawing team sizes
def test_team_sizes_are_drawn_from_the_list_each_size_appears_robots_0_to_k_minus_1(team_rollout):
    env, ro = team_rollout
    present = ro["agents", "present"]
    assert present.dtype == torch.bool and present.shape == (32, 300, 4, 1)
    present = present[..., 0]
    sizes = present.sum(-1)
    assert set(sizes.unique().tolist()) == {1, 2, 3}
    prefix = torch.arange(4) < sizes.unsqueeze(-1)
    assert torch.equal(present, prefix)
    # fixed within an episode, redrawn at each reset
    same = present[:, 1:] == present[:, :-1]
    new_episode = ro["step_count"][:, 1:, 0] == 0
    assert same.all(-1)[~new_episode].all()
    assert not same.all(-1)[new_episode].all()  # some resets change the size
    assert torch.equal(env.present, ro["next", "agents", "present"][:, -1, :, 0])
    assert env.present.device == env.device


def test_each_listed_size_is_drawn_about_uniformly():
    env = ResourceCollectionEnv(num_envs=3000, seed=0, n_agents=5, team_sizes=[2, 5])
    sizes = env.reset()[PRESENT][..., 0].sum(-1)
    assert set(sizes.unique().tolist()) == {2, 5}
    assert 0.45 < (sizes == 2).float().mean() < 0.55


# ---------------------------------------------------------------- the absent-robot contract
def test_absent_robots_observe_nothing_earn_nothing_and_are_invisible(team_rollout):
    env, ro = team_rollout
    for td in (ro, ro["next"]):
        present = td["agents", "present"][..., 0]
        obs = td["agents", "observation"]
        assert (obs[~present] == 0).all()  # own row: all zeros
        assert (obs[present][:, :5] != 0).any(-1).all()  # a present robot's own features
        seen = other_robot_tokens(env, obs)  # [B, T, n, j, D]
        absent_j = (~present).unsqueeze(-2).expand_as(seen[..., 0])
        assert (seen[absent_j] == 0).all()
        assert seen[..., -1][~absent_j].any()  # present robots do see present ones sometimes
        tokens = robot_state_tokens(env, td["state"])
        assert (tokens[~present] == 0).all()  # the whole token, robot type flag included
        assert torch.equal(tokens[..., 4] == 1, present)  # the mask networks read
    present = ro["agents", "present"][..., 0]
    reward = ro["next", "agents", "reward"][..., 0]
    assert (reward[~present] == 0).all() and (reward[present] != 0).all()
    torch.testing.assert_close(ro["next", "reward"][..., 0], reward.sum(-1))


def scene(team_sizes=(1,), n_agents=3, **kwargs):
    """One env after reset, nothing going on: robots apart, resources on a far ring, the invader
    off for good (robots 1.. absent with the default team of 1)."""
    env = ResourceCollectionEnv(
        num_envs=1,
        seed=0,
        n_agents=n_agents,
        team_sizes=team_sizes,
        inst_reward_scale=0.0,
        **kwargs,
    )
    td = env.reset()
    env.pos[:] = torch.tensor([(0.0, -1.0), (1.0, 1.0), (-1.0, 1.0), (1.0, -1.5)][:n_agents])
    env.vel.zero_()
    angle = torch.arange(env.n_resources) * (2 * math.pi / env.n_resources)
    env.res_pos[:] = 2.8 * torch.stack([angle.cos(), angle.sin()], -1)
    env.inv_active.zero_()
    env.inv_timer.fill_(10**6)
    return env, td.exclude(("agents", "waypoints"))


def step(env, td, actions=(0, 0, 0)):
    td = env.step(td.set(("agents", "action"), torch.tensor([actions])))
    return td["next"], step_mdp(td)


@pytest.mark.parametrize("team_sizes", [(1,), None])  # None: the same scene, everyone present
def test_absent_robots_never_pick_deliver_defend_or_get_seen(team_sizes):
    env, td = scene(team_sizes)
    env.res_pos[0, 0] = env.pos[0, 1]  # on absent robot 1
    env.inv_active.fill_(True)
    env.inv_pos[0, 0] = env.pos[0, 2] + torch.tensor([0.05, 0.0])  # touching absent robot 2
    env.pos[0, 0] = env.pos[0, 1] + torch.tensor([0.4, 0.0])  # robot 0 sees robot 1
    nxt, td = step(env, td)
    events = {k: nxt["events", k].item() for k in ("pick", "defense", "collect", "invasion")}
    seen = other_robot_tokens(env, nxt["agents", "observation"])[0]
    if team_sizes is None:  # the control: the same scene scores with a full team
        assert events["pick"] == 1 and events["defense"] == 1
        assert seen[0, 1, -1] == 1
        return
    assert events == dict(pick=0, defense=0, collect=0, invasion=0)
    assert nxt["agents", "reward"][0, :, 0].tolist() == [0.0, 0.0, 0.0]
    assert bool(env.inv_active[0, 0]) and torch.equal(env.res_pos[0, 0], env.pos[0, 1])
    assert (seen[0, 1] == 0).all() and (seen[0, 2] == 0).all()
    assert not env.carry[0].any() and not env.defended[0].any()
    # a carrying absent robot at home delivers nothing
    env.carry[0, 1] = True
    env.pos[0, 1] = torch.tensor([0.1, 0.0])
    nxt, td = step(env, td)
    assert nxt["events", "collect"].item() == 0 and nxt["reward"].item() == 0.0


def test_the_invasion_penalty_goes_to_the_present_robots_only():
    env, td = scene((2,))
    env.inv_active.fill_(True)
    env.inv_pos[0, 0] = torch.tensor([0.2, 0.0])  # inside home: invades this step
    nxt, _ = step(env, td)
    assert nxt["events", "invasion"].item() == 1
    assert nxt["agents", "reward"][0, :, 0].tolist() == [-2.0, -2.0, 0.0]
    assert nxt["reward"].item() == -4.0


def test_absent_robots_actions_and_waypoints_have_no_effect():
    def run(seed_absent):
        env = ResourceCollectionEnv(
            num_envs=16, seed=5, n_agents=3, team_sizes=[1, 2], waypoint_mode="external"
        )
        same, other = torch.Generator().manual_seed(0), torch.Generator().manual_seed(seed_absent)
        wp_gen = torch.Generator().manual_seed(seed_absent)

        def policy(td):
            present = td["agents", "present"][..., 0]
            a = torch.randint(0, N_ACTIONS, (16, 3), generator=same)
            b = torch.randint(0, N_ACTIONS, (16, 3), generator=other)
            wp = td["agents", "waypoints"].clone()
            noise = (torch.rand(wp.shape, generator=wp_gen) - 0.5) * 4
            wp[~present] = noise[~present]  # absent robots' waypoints: anything
            return td.set(("agents", "action"), torch.where(present, a, b)).set(
                ("agents", "waypoints"), wp
            )

        return env.rollout(300, policy=policy, break_when_any_done=False)

    ro1, ro2 = run(1), run(2)
    present = ro1["agents", "present"][..., 0]
    assert (~present).any()
    differ = (ro1["agents", "action"] != ro2["agents", "action"])[~present]
    assert differ.float().mean() > 0.5  # the absent robots really got different actions
    skip = {("agents", "action"), ("agents", "waypoints"), ("next", "agents", "waypoints")}
    for key in ro1.keys(True, True):
        if key not in skip:
            assert torch.equal(ro1[key], ro2[key]), key


def test_check_env_specs_with_team_sizes():
    check_env_specs(ResourceCollectionEnv(num_envs=4, seed=0, n_agents=4, team_sizes=[1, 4]))


# ---------------------------------------------------------------- removing and adding robots
def test_remove_then_add_mid_episode_keeps_the_episode_and_the_counts():
    env = ResourceCollectionEnv(num_envs=4, seed=0, n_agents=3, max_steps=30)
    td = env.reset()
    policy = random_policy(env)

    def steps(td, n):
        for _ in range(n):
            parked = env.pos.clone()
            out = env.step(policy(td))
            present = env.present
            assert torch.equal(env.pos[~present], parked[~present])  # absent robots never move
            assert (out["next", "agents", "reward"][~present] == 0).all()
            assert (out["next", "agents", "reward"][present] != 0).all()
            assert (out["next", "agents", "observation"][~present] == 0).all()
            td = step_mdp(out)
        return td

    def spec_check(td):  # a 3-step rollout from the current state, without a reset
        check_env_specs(env, tensordict=td.exclude(("agents", "reward"), ("agents", "action")))

    td = steps(td, 10)
    env.remove_robot(2, 1, tensordict=td)
    assert env.present.sum(-1).tolist() == [3, 3, 2, 3]
    assert (td["agents", "observation"][2, 1] == 0).all()  # the td is rewritten at once
    assert not td[PRESENT][2, 1, 0] and td[PRESENT].sum() == 11
    assert (robot_state_tokens(env, td["state"])[2, 1] == 0).all()
    spec_check(td)
    td = steps(td, 5)
    assert env.t.tolist() == [18] * 4 and not td["done"].any()  # the episode went on

    assert env.add_robot(2, tensordict=td) == 1
    assert env.present.all() and td[PRESENT].all()
    pos = env.pos[2, 1]
    assert pos.abs().max() <= env.half - env.agent_radius and (env.vel[2, 1] == 0).all()
    assert not env.carry[2, 1]
    others = torch.cat([env.pos[2, [0, 2]], env.res_pos[2]])
    assert (others - pos).norm(dim=-1).min() >= env.agent_radius + env.resource_radius - 1e-6
    assert (env.waypoints[2, 1, 0] - pos).norm() < 4 * env.waypoint_sigma  # a walk from it
    assert torch.equal(td["agents", "observation"][2, 1, :2], pos)
    assert robot_state_tokens(env, td["state"])[2, 1, 4] == 1
    spec_check(td)
    td = steps(td, 9)
    assert env.t.tolist() == [30] * 4 and td["done"].all()  # truncated at max_steps, as always


def test_add_takes_the_lowest_absent_robot_or_the_one_named():
    env = ResourceCollectionEnv(num_envs=2, seed=0, n_agents=4)
    td = env.reset()
    for r in (0, 2, 3):
        env.remove_robot(1, r)
    assert env.present[1].tolist() == [False, True, False, False]
    assert env.add_robot(1, 3) == 3
    assert env.add_robot(1) == 0
    assert env.add_robot(1, tensordict=td) == 2
    assert env.present.all() and td[PRESENT].all()


def test_a_reset_restores_the_full_team_without_team_sizes():
    env = ResourceCollectionEnv(num_envs=3, seed=0, n_agents=3)
    td = env.reset()
    env.remove_robot(0, 2)
    env.remove_robot(1, 0)
    td.set("_reset", torch.tensor([[True], [False], [False]]))
    env.reset(td)
    assert env.present.tolist() == [[True] * 3, [False, True, True], [True] * 3]
    env.reset()
    assert env.present.all()


# ---------------------------------------------------------------- scripted policies
def test_heuristic_ignores_absent_robots():
    """A team of robot 1 alone, robot 0 absent next to the invader and the resources: robot 1
    must act as if alone (robot 0 does not intercept, nor claim a resource)."""
    env, _ = scene(None, n_agents=2)
    env.inv_active.fill_(True)
    env.inv_pos[0, 0] = torch.tensor([2.0, 2.0])
    env.pos[0, 0] = torch.tensor([1.9, 1.9])  # absent, on the invader's way
    env.remove_robot(0, 0)
    alone, _ = scene(None, n_agents=1)
    alone.inv_active.fill_(True)
    alone.inv_pos[:], alone.res_pos[:] = env.inv_pos, env.res_pos
    alone.pos[0, 0] = env.pos[0, 1]
    target, _ = HeuristicPolicy(env).targets()
    target_alone, _ = HeuristicPolicy(alone).targets()
    torch.testing.assert_close(target[0, 1], target_alone[0, 0])
    env.add_robot(0, 0)
    env.pos[0, 0] = torch.tensor([1.9, 1.9])
    assert not torch.allclose(HeuristicPolicy(env).targets()[0][0, 1], target_alone[0, 0])


@pytest.mark.parametrize("make", [HeuristicPolicy, lambda env: BlendPolicy(env, 1.75)])
def test_scripted_policies_run_with_absent_robots(make):
    env = ResourceCollectionEnv(num_envs=8, seed=0, n_agents=4, team_sizes=[1, 2])
    ro = env.rollout(150, policy=make(env), break_when_any_done=False)
    assert torch.isfinite(ro["next", "reward"]).all()
    assert ro["next", "events", "pick"].sum() > 0


def test_shaping_potential_is_zero_for_absent_robots(team_rollout):
    env, ro = team_rollout
    phi = StatePotential(env.layout, env.n_resources, ["collect", "defend"], 1.0)(ro["state"])
    present = ro["agents", "present"][..., 0]
    assert (phi[~present] == 0).all() and (phi[present] != 0).any()


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "bad, says",
    [
        ([], "must not be empty"),
        ([0, 2], "1..n_agents=3"),
        ([4], "1..n_agents=3"),
        ([2, 2.5], "1..n_agents=3"),
        ([True], "1..n_agents=3"),
        ("23", "a list"),
        (3, "a list"),
    ],
)
def test_bad_team_sizes_raise_one_line_naming_the_field(bad, says):
    with pytest.raises(ValueError) as err:
        ResourceCollectionEnv(num_envs=1, n_agents=3, team_sizes=bad)
    msg = str(err.value)
    assert msg.startswith("team_sizes") and says in msg and "\n" not in msg


@pytest.mark.parametrize(
    "call, says",
    [
        (lambda env: env.add_robot(0), "env 0 is full"),
        (lambda env: env.add_robot(1, 0), "robot 0 is already in env 1"),
        (lambda env: env.remove_robot(1, 2), "robot 2 is not in env 1"),
        (lambda env: env.remove_robot(1, 0), "robot 0 is the last robot of env 1"),
        (lambda env: env.add_robot(2), "env_index must be an integer in 0..1, got 2"),
        (lambda env: env.remove_robot(-1, 0), "env_index must be an integer in 0..1, got -1"),
        (lambda env: env.add_robot(0.0), "env_index"),
        (lambda env: env.add_robot(1, 3), "robot must be an integer in 0..2, got 3"),
        (lambda env: env.remove_robot(0, -1), "robot must be an integer in 0..2, got -1"),
    ],
)
def test_bad_team_changes_raise_one_line(call, says):
    env = ResourceCollectionEnv(num_envs=2, seed=0, n_agents=3)
    env.reset()
    env.remove_robot(1, 1)
    env.remove_robot(1, 2)  # env 0: full; env 1: robot 0 alone
    before = env.present
    with pytest.raises(ValueError) as err:
        call(env)
    assert says in str(err.value) and "\n" not in str(err.value)
    assert torch.equal(env.present, before)  # nothing changed


@pytest.mark.parametrize(
    "override, says",
    [
        ("train.team_sizes=[]", "must not be empty"),
        ("train.team_sizes=[0,2]", "in 1..n_agents=3"),
        ("train.team_sizes=[2,4]", "in 1..n_agents=3"),
    ],
)
def test_bad_train_team_sizes_fail_in_one_line_naming_the_field(override, says):
    from icco_torchrl.training.config import ConfigError, compose_config

    with pytest.raises(ConfigError) as err:
        compose_config([override])
    msg = str(err.value)
    assert msg.startswith("config field 'train.team_sizes'") and says in msg and "\n" not in msg


def test_train_team_sizes_reach_the_training_env_only():
    from icco_torchrl.training.build import build
    from icco_torchrl.training.config import EnvParams, compose_config

    assert "team_sizes" not in {f.name for f in __import__("dataclasses").fields(EnvParams)}
    cfg = compose_config(["train.team_sizes=[1,2]", "env.num_envs=4", "train.eval_envs=2"])
    run = build(cfg, for_training=True)
    assert run.env.base_env.team_sizes == (1, 2) and run.eval_env.base_env.team_sizes is None
    assert build(cfg).env.base_env.team_sizes is None
    assert compose_config([]).train.team_sizes is None
