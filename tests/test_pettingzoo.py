"""The PettingZoo view: API compliance, seeding, and the same dynamics as the batched env."""

import numpy as np
import pytest
import torch
from pettingzoo.test import parallel_api_test, parallel_seed_test
from torchrl.envs.utils import step_mdp

from icco_torchrl.envs import N_ACTIONS, ResourceCollectionEnv, parallel_env

torch.set_num_threads(1)


def random_actions(env, rng):
    return {a: int(rng.integers(N_ACTIONS)) for a in env.agents}


def play(env, seed, n_steps):
    """Trajectory of (obs, rewards, truncations, infos, state) under seeded random actions."""
    rng = np.random.default_rng(123)
    obs, _ = env.reset(seed=seed)
    traj = [(obs, None, None, None, env.state())]
    for _ in range(n_steps):
        obs, rew, _, trunc, info = env.step(random_actions(env, rng))
        traj.append((obs, rew, trunc, info, env.state()))
    return traj


def test_parallel_api():
    parallel_api_test(parallel_env(seed=0), num_cycles=1000)


def test_parallel_seed():
    parallel_seed_test(lambda: parallel_env(seed=0))


def test_episode_protocol_and_spaces():
    env = parallel_env(seed=0, max_steps=5)
    assert env.possible_agents == ["agent_0", "agent_1", "agent_2"]
    obs, infos = env.reset(seed=1)
    assert set(obs) == set(infos) == set(env.agents)
    rng = np.random.default_rng(0)
    for t in range(1, 6):
        obs, rew, term, trunc, info = env.step(random_actions(env, rng))
        for a in env.possible_agents:
            assert obs[a].dtype == np.float32 and obs[a] in env.observation_space(a)
            assert isinstance(rew[a], float)
            assert term[a] is False
            assert trunc[a] is (t == 5)
            assert set(info[a]["events"]) == {
                "pick",
                "collect",
                "defense",
                "invasion",
                "inst_reward",
            }
        state = env.state()
        assert state.shape == env.state_space.shape and state in env.state_space
    assert env.agents == []
    with pytest.raises(RuntimeError):
        env.step({})
    env.reset()
    assert env.agents == env.possible_agents


def test_max_cycles_sets_the_episode_length():
    env = parallel_env(seed=0)
    assert env.max_cycles == 145
    env.max_cycles = 200
    env.reset()
    rng = np.random.default_rng(0)
    steps = 0
    while env.agents:
        env.step(random_actions(env, rng))
        steps += 1
    assert steps == 200


def test_actions_must_cover_the_live_agents():
    env = parallel_env(seed=0)
    env.reset()
    with pytest.raises(ValueError, match="agent"):
        env.step({"agent_0": 1, "agent_1": 2})
    with pytest.raises(ValueError, match="action"):
        env.step({"agent_0": 1, "agent_1": 2, "agent_2": N_ACTIONS})


def test_same_seed_same_trajectory_different_seed_differs():
    a, b = play(parallel_env(), 5, 60), play(parallel_env(), 5, 60)
    for (oa, ra, ta, ia, sa), (ob, rb, tb, ib, sb) in zip(a, b):
        assert all(np.array_equal(oa[k], ob[k]) for k in oa)
        assert ra == rb and ta == tb and ia == ib and np.array_equal(sa, sb)
    c = play(parallel_env(), 6, 1)
    assert not np.array_equal(a[0][0]["agent_0"], c[0][0]["agent_0"])


def test_same_dynamics_as_the_batched_env():
    seed, n_agents = 9, 3
    view = parallel_env()
    obs, _ = view.reset(seed=seed)
    batched = ResourceCollectionEnv(num_envs=1, seed=seed)
    td = batched.reset()
    rng = np.random.default_rng(0)
    for _ in range(batched.max_steps):
        expected = td["agents", "observation"][0].numpy()
        np.testing.assert_array_equal(
            np.stack([obs[f"agent_{i}"] for i in range(n_agents)]), expected
        )
        np.testing.assert_array_equal(view.state(), td["state"][0].numpy())
        actions = random_actions(view, rng)
        obs, rew, _, trunc, info = view.step(actions)
        assert all(obs[a] in view.observation_space(a) for a in obs)
        td.set(
            ("agents", "action"), torch.tensor([[actions[f"agent_{i}"] for i in range(n_agents)]])
        )
        td = batched.step(td)
        nxt = td["next"]
        assert [rew[f"agent_{i}"] for i in range(n_agents)] == nxt["agents", "reward"][
            0, :, 0
        ].tolist()
        assert info["agent_0"]["events"]["pick"] == nxt["events", "pick"].item()
        assert trunc["agent_0"] == nxt["truncated"].item()
        td = step_mdp(td)
    assert view.agents == []


def test_render():
    env = parallel_env(seed=0, render_mode="rgb_array", render_size=96)
    env.reset()
    frame = env.render()
    assert frame.shape == (96, 96, 3) and frame.dtype == np.uint8
    with pytest.raises(ValueError, match="render_mode"):
        parallel_env(render_mode="human")


@pytest.mark.parametrize(
    "bad",
    [
        2.9,
        2.0,
        "2",
        True,
        None,
        -1,
        N_ACTIONS,
        np.float32(1.0),
        [1],
        np.array(2.0),
        torch.tensor(2.5),
    ],
)
@pytest.mark.fault
def test_an_action_that_is_not_an_integer_in_range_is_one_clear_line(bad):
    env = parallel_env(seed=0)
    env.reset()
    with pytest.raises(
        ValueError, match=r"action for agent_1 must be an integer in 0\.\.4"
    ) as info:
        env.step({"agent_0": 1, "agent_1": bad, "agent_2": 0})
    assert "\n" not in str(info.value) and repr(bad) in str(info.value)


def test_numpy_integer_actions_are_accepted():
    env = parallel_env(seed=0)
    env.reset()
    env.step({"agent_0": np.int64(4), "agent_1": np.uint8(2), "agent_2": np.array(3)})
    env.step({"agent_0": torch.tensor(1), "agent_1": 0, "agent_2": np.int32(4)})
    assert env.agents == env.possible_agents


def test_step_before_reset_is_a_clear_error():
    env = parallel_env(seed=0)
    with pytest.raises(RuntimeError, match=r"before reset\(\)"):
        env.step({a: 0 for a in env.possible_agents})


EXTREME = [  # valid parameters far from the defaults
    dict(
        invader_speed=2.0, vision_radius=1e12, invader_respawn_max=3
    ),  # inactive invaders in sight
    dict(
        field_size=1.0,
        agent_radius=0.8,
        resource_radius=0.9,
        home_radius=0.7,
        vision_radius=1e12,
        spawn="copa",
        resource_min_radius=0.1,
        invader_min_radius=0.0,
    ),  # bodies larger than the field
    dict(
        dt=0.05,
        accel=400.0,
        max_speed=20.0,
        damping=0.0,
        field_size=20.0,
        vision_radius=5.0,
        invader_speed=5.0,
        waypoint_sigma=5.0,
    ),  # fast robots and invaders
]


@pytest.mark.parametrize("params", EXTREME)
@pytest.mark.fault
def test_observations_and_states_stay_in_the_declared_boxes_at_extreme_parameters(params):
    env = parallel_env(seed=0, max_steps=100, **params)
    rng = np.random.default_rng(0)
    inactive_steps = 0
    for episode in range(3):  # 300 steps in all
        obs, _ = env.reset(seed=episode)
        while True:
            for a in env.possible_agents:
                space = env.observation_space(a)
                outside = np.nonzero((obs[a] < space.low) | (obs[a] > space.high))[0]
                assert not outside.size, f"{a}: features {outside[:5]} = {obs[a][outside[:5]]}"
                assert (
                    np.abs(obs[a]).max() < 1e6
                )  # never the 1e9 placeholder of an inactive invader
            state = env.state()
            outside = np.nonzero((state < env.state_space.low) | (state > env.state_space.high))[0]
            assert not outside.size, f"state features {outside[:5]} = {state[outside[:5]]}"
            inactive_steps += int((~env._env.inv_active).sum())
            if not env.agents:
                break
            obs, *_ = env.step(random_actions(env, rng))
    if params.get("vision_radius") == 1e12 and params.get("invader_speed") == 2.0:
        assert inactive_steps > 10, "the run never had an inactive invader in sight"


def test_parallel_api_at_extreme_parameters():
    parallel_api_test(parallel_env(seed=0, **EXTREME[0]), num_cycles=200)


# ---------------------------------------------------------------- team sizes
def test_parallel_api_with_team_sizes():
    parallel_api_test(parallel_env(seed=0, n_agents=4, team_sizes=[1, 2, 3]), num_cycles=300)


def test_agents_are_the_present_robots_and_follow_team_changes():
    env = parallel_env(seed=0, n_agents=4, team_sizes=[2, 3], max_steps=6)
    assert env.possible_agents == [f"agent_{i}" for i in range(4)]
    seen = set()
    for seed in range(12):
        obs, infos = env.reset(seed=seed)
        k = len(env.agents)
        seen.add(k)
        assert env.agents == env.possible_agents[:k] and set(obs) == set(infos) == set(env.agents)
    assert seen == {2, 3}
    env.reset(seed=1)
    team = list(env.agents)
    env.remove_robot(team[0])
    assert env.agents == team[1:]
    with pytest.raises(ValueError, match="actions must have exactly one entry"):
        env.step({a: 0 for a in team})
    obs, rew, term, trunc, info = env.step({a: 0 for a in env.agents})
    assert set(obs) == set(rew) == set(term) == set(trunc) == set(info) == set(team[1:])
    state = env.state().reshape(env._env.layout.state_tokens, -1)
    assert (state[0] == 0).all()  # the removed robot's state token
    assert env.add_robot() == "agent_0" and env.agents == team
    obs, *_ = env.step({a: 0 for a in env.agents})
    assert set(obs) == set(team) and obs["agent_0"][:2].any()
    with pytest.raises(ValueError, match="unknown agent"):
        env.remove_robot("agent_9")
