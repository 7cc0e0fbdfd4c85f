"""Behaviour of the batched resource-collection env (the task section of the README).

Long random rollouts check the invariants the task promises at every step; hand-built
scenes (internal tensors set after reset) check each event, vision and the instruction
reward against the numbers given there.
"""

import math

import pytest
import torch
from torchrl.envs.utils import check_env_specs, step_mdp

from icco_torchrl.envs import N_ACTIONS, ResourceCollectionEnv

torch.set_num_threads(1)

NOOP, LEFT, RIGHT, DOWN, UP = range(N_ACTIONS)
STATE_TENSORS = (
    "pos",
    "vel",
    "carry",
    "defended",
    "res_pos",
    "inv_pos",
    "inv_vel",
    "inv_active",
    "inv_timer",
    "waypoints",
    "t",
)


def random_policy(env, seed=0):
    gen = torch.Generator().manual_seed(seed)
    shape = (env.num_envs, env.n_agents)
    return lambda td: td.set(
        ("agents", "action"), torch.randint(0, N_ACTIONS, shape, generator=gen)
    )


def split_state(env, state):
    """Global state [..., state_dim] -> robot, resource and invader tokens."""
    L = env.layout
    tok = state.unflatten(-1, (L.state_tokens, L.state_token_dim))
    N, R = env.n_agents, env.n_resources
    return tok[..., :N, :], tok[..., N : N + R, :], tok[..., N + R :, :]


@pytest.fixture(scope="module")
def long_rollout():
    """64 envs x 600 random steps with auto-reset (4 episodes each), default rewards."""
    env = ResourceCollectionEnv(num_envs=64, seed=0)
    return env, env.rollout(600, policy=random_policy(env), break_when_any_done=False)


def test_robots_stay_inside_the_field(long_rollout):
    env, ro = long_rollout
    xy = ro["next", "agents", "observation"][..., 0:2]
    assert xy.abs().max() <= env.half - env.agent_radius + 1e-5


def test_resources_always_on_the_field_and_apart(long_rollout):
    env, ro = long_rollout
    _, res, _ = split_state(env, ro["next", "state"])
    xy = res[..., 0:2]
    assert res.shape[-2] == env.n_resources
    assert torch.isfinite(xy).all()
    assert xy.abs().max() <= env.half + 1e-5
    # spawn="uniform" (default): anywhere but on home
    assert xy.norm(dim=-1).min() >= env.home_radius + env.resource_radius - 1e-5
    gap = torch.cdist(xy, xy) + torch.eye(env.n_resources) * 1e3
    assert gap.min() > 0


def test_copa_spawn_keeps_resources_on_the_ring_and_invaders_on_the_edge():
    env = ResourceCollectionEnv(num_envs=64, seed=0, spawn="copa")
    ro = env.rollout(300, policy=random_policy(env), break_when_any_done=False)
    _, res, inv = split_state(env, ro["next", "state"])
    assert res[..., 0:2].norm(dim=-1).min() >= env.resource_min_radius - 1e-5
    assert (
        not ro["state"][:, 0].unflatten(-1, (env.layout.state_tokens, -1))[:, -1, 7].any()
    )  # starts inactive
    # An invader is first seen (active) on the edge: the step after it appears.
    active = inv[..., 7] > 0
    appeared = active[:, 1:] & ~active[:, :-1]
    first_xy = inv[:, 1:][appeared][..., 0:2]
    assert (
        first_xy.numel() > 0
        and first_xy.abs().amax(-1).min() >= env.half - env.invader_speed - 1e-4
    )


def test_uniform_spawn_fills_the_field():
    """Initial robots, resources and the invader are uniform in the field (coverage over resets)."""
    env = ResourceCollectionEnv(num_envs=4096, seed=3)
    env.reset()
    h = env.half
    for name, xy, clear in (
        ("robots", env.pos, 0.0),
        ("resources", env.res_pos, env.home_radius),
        ("invader", env.inv_pos, env.invader_min_radius),
    ):
        xy = xy.reshape(-1, 2)
        assert xy.abs().max() <= h + 1e-5, name
        assert xy.norm(dim=-1).min() >= clear - 1e-5, name
        # 4 x 4 grid over the field: every cell is hit, and about as often as its area says.
        cell = ((xy + h) / (2 * h) * 4).clamp(0, 3.999).long()
        counts = torch.bincount(cell[:, 0] * 4 + cell[:, 1], minlength=16).float()
        if name == "invader":  # the 4 central cells are 85 % inside the 1.5 m exclusion disc
            inner = torch.tensor([5, 6, 9, 10])
            assert counts[inner].max() < 0.6 * counts.mean() and counts[inner].min() > 0, counts
            counts[inner] = counts.mean()
        assert counts.min() > 0.8 * counts.mean(), (name, counts)
        assert (xy[:, 0] > 0).float().mean().sub(0.5).abs() < 0.05, name  # no side preferred
    assert env.inv_active.all(), "spawn=uniform puts the invader on the field at reset"


def test_uniform_respawns_keep_the_invader_clear_of_home():
    env = ResourceCollectionEnv(num_envs=256, seed=4)
    ro = env.rollout(400, policy=random_policy(env), break_when_any_done=False)
    _, _, inv = split_state(env, ro["next", "state"])
    active = inv[..., 7] > 0
    appeared = active[:, 1:] & ~active[:, :-1]
    xy = inv[:, 1:][appeared][..., 0:2]
    assert xy.shape[0] > 50
    # seen one step after it appears: at most one invader step closer than its clearance
    assert xy.norm(dim=-1).min() >= env.invader_min_radius - env.invader_speed - 1e-4
    assert xy.norm(dim=-1).max() > env.half  # and out to the corners


def test_unknown_spawn_mode_is_refused():
    with pytest.raises(ValueError, match="spawn must be one of"):
        ResourceCollectionEnv(spawn="edge")


def test_carry_changes_only_through_picks_and_collects(long_rollout):
    env, ro = long_rollout
    before = ro["agents", "observation"][..., 4]
    after = ro["next", "agents", "observation"][..., 4]
    assert set(before.unique().tolist()) <= {0.0, 1.0}
    picked = (before == 0) & (after == 1)
    delivered = (before == 1) & (after == 0)
    assert torch.equal(picked.sum(-1), ro["next", "events", "pick"])
    assert torch.equal(delivered.sum(-1), ro["next", "events", "collect"])
    # A delivery needs the robot at home.
    home_dist = ro["next", "agents", "observation"][..., 0:2].norm(dim=-1)
    assert (home_dist[delivered] < env.home_radius + env.agent_radius).all()


def test_random_play_has_picks_and_invasions(long_rollout):
    _, ro = long_rollout
    assert ro["next", "events", "pick"].sum() > 0
    assert ro["next", "events", "invasion"].sum() > 0


def event_reward(events):
    return (
        5 * events["pick"] + events["collect"] + 4 * events["defense"] - 4 * events["invasion"]
    ).float()


def test_team_reward_is_events_plus_instruction_reward(long_rollout):
    _, ro = long_rollout
    nxt = ro["next"]
    team = nxt["reward"].squeeze(-1)
    expected = event_reward(nxt["events"]) + nxt["events", "inst_reward"]
    torch.testing.assert_close(team, expected, atol=1e-3, rtol=0)
    torch.testing.assert_close(team, nxt["agents", "reward"].sum((-2, -1)), atol=1e-4, rtol=0)
    assert nxt["events", "inst_reward"].abs().sum() > 0


def test_team_reward_without_instruction_reward_is_the_task_reward():
    env = ResourceCollectionEnv(num_envs=32, seed=1, inst_reward_scale=0.0)
    ro = env.rollout(300, policy=random_policy(env, 1), break_when_any_done=False)
    nxt = ro["next"]
    torch.testing.assert_close(
        nxt["reward"].squeeze(-1), event_reward(nxt["events"]), atol=1e-4, rtol=0
    )
    assert (nxt["events", "inst_reward"] == 0).all()


def test_truncation_exactly_at_max_steps(long_rollout):
    env, ro = long_rollout
    nxt = ro["next"]
    at_end = nxt["step_count"] == env.max_steps
    assert torch.equal(nxt["truncated"], at_end)
    assert torch.equal(nxt["done"], at_end)
    assert not nxt["terminated"].any()
    assert at_end.sum() == 64 * (600 // env.max_steps)
    assert nxt["step_count"].max() == env.max_steps


def test_check_env_specs():
    check_env_specs(ResourceCollectionEnv(num_envs=4, seed=0))
    check_env_specs(
        ResourceCollectionEnv(
            num_envs=2, seed=0, n_agents=5, n_resources=3, waypoint_mode="external"
        )
    )


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_rollout():
    env = ResourceCollectionEnv(num_envs=8, device="cuda", seed=0)
    check_env_specs(env)
    ro = env.rollout(50, break_when_any_done=False)
    assert ro["next", "reward"].device.type == "cuda"
    assert ro["next", "agents", "observation"][..., 0:2].abs().max() <= env.half


# ---------------------------------------------------------------- seeding and resets
def test_same_seed_same_rollout_and_different_seed_differs():
    def run(seed):
        env = ResourceCollectionEnv(num_envs=8, seed=seed)
        return env.rollout(200, policy=random_policy(env), break_when_any_done=False)

    a, b, c = run(3), run(3), run(4)
    assert (a == b).all()
    assert not torch.equal(a["next", "agents", "observation"], c["next", "agents", "observation"])


def test_set_seed_makes_resets_reproducible():
    env = ResourceCollectionEnv(num_envs=4)
    env.set_seed(11)
    first = env.reset()
    env.rollout(10)
    env.set_seed(11)
    assert (env.reset() == first).all()


def test_partial_reset_touches_only_reset_envs():
    env = ResourceCollectionEnv(num_envs=6, seed=0)
    td = env.reset()
    policy = random_policy(env)
    for _ in range(7):
        td = step_mdp(env.step(policy(td)))
    before = {name: getattr(env, name).clone() for name in STATE_TENSORS}
    mask = torch.tensor([False, True, False, False, True, False])
    td.set("_reset", mask.unsqueeze(-1))
    out = env.reset(td)
    for name, old in before.items():
        new = getattr(env, name)
        assert torch.equal(new[~mask], old[~mask]), name
    assert (env.t[mask] == 0).all() and (env.t[~mask] == 7).all()
    assert not env.pos[mask].equal(before["pos"][mask])
    assert (env.vel[mask] == 0).all() and not env.carry[mask].any()
    assert torch.equal(out["step_count"].squeeze(-1), env.t)
    assert torch.equal(out["agents", "observation"][~mask], td["agents", "observation"][~mask])


# ---------------------------------------------------------------- hand-built scenes
ROBOTS = ((0.0, -1.0), (1.0, 1.0), (-1.0, 1.0))


def quiet_scene(num_envs=1, **kwargs):
    """Env after reset with nothing happening: robots still and apart, resources on a far ring,
    the invader inactive for good. Tests then place what they need."""
    kwargs.setdefault("inst_reward_scale", 0.0)
    env = ResourceCollectionEnv(num_envs=num_envs, seed=0, **kwargs)
    td = env.reset()
    env.pos[:] = torch.tensor(ROBOTS[: env.n_agents])
    env.vel.zero_()
    env.carry.zero_()
    angle = torch.arange(env.n_resources) * (2 * math.pi / env.n_resources)
    env.res_pos[:] = 2.8 * torch.stack([angle.cos(), angle.sin()], -1)
    env.inv_active.zero_()
    env.inv_timer.fill_(10**6)
    # Without this key the env keeps its own waypoints (tests may set env.waypoints).
    return env, td.exclude(("agents", "waypoints"))


def step(env, td, actions=None):
    """One step with per-robot ``actions`` (default: all no-op) -> (the "next" td, next root td)."""
    a = torch.zeros(env.num_envs, env.n_agents, dtype=torch.int64)
    if actions is not None:
        a[:] = torch.as_tensor(actions)
    td = env.step(td.set(("agents", "action"), a))
    return td["next"], step_mdp(td)


def rewards(nxt):
    return nxt["agents", "reward"][0, :, 0].tolist()


def test_quiet_scene_is_quiet():
    env, td = quiet_scene()
    for _ in range(5):
        nxt, td = step(env, td)
        assert rewards(nxt) == [0.0, 0.0, 0.0]


def test_pick_scores_sets_carry_and_respawns_resource():
    env, td = quiet_scene(spawn="copa")
    env.res_pos[0, 2] = torch.tensor([0.2, -1.0])  # touching robot 0
    nxt, td = step(env, td)
    assert rewards(nxt) == [5.0, 0.0, 0.0]
    assert nxt["events", "pick"].item() == 1
    assert env.carry[0].tolist() == [True, False, False]
    new = env.res_pos[0, 2]
    assert not torch.allclose(new, torch.tensor([0.2, -1.0]))
    assert new.norm() >= env.resource_min_radius and new.abs().max() <= env.half
    others = torch.cat([env.res_pos[0, :2], env.res_pos[0, 3:]])
    assert (others - new).norm(dim=-1).min() >= 2 * env.resource_radius

    # While carrying, touching another resource picks nothing.
    env.res_pos[0, 0] = torch.tensor([-0.2, -1.0])
    nxt, _ = step(env, td)
    assert rewards(nxt) == [0.0, 0.0, 0.0]
    assert torch.allclose(env.res_pos[0, 0], torch.tensor([-0.2, -1.0]))


def test_delivery_scores_only_when_carrying_at_home():
    env, td = quiet_scene()
    env.pos[0, 0] = torch.tensor([0.3, 0.0])
    env.pos[0, 1] = torch.tensor([-0.3, 0.0])
    env.carry[0, 0] = True  # robot 1 is at home too, but empty-handed
    nxt, _ = step(env, td)
    assert rewards(nxt) == [1.0, 0.0, 0.0]
    assert nxt["events", "collect"].item() == 1
    assert not env.carry.any()


def test_defense_scores_and_removes_invader():
    env, td = quiet_scene()
    env.inv_active[0, 0] = True
    env.inv_pos[0, 0] = torch.tensor([0.0, -1.3])  # walks 0.19 toward home, onto robot 0
    nxt, _ = step(env, td)
    assert rewards(nxt) == [4.0, 0.0, 0.0]
    assert nxt["events", "defense"].item() == 1 and nxt["events", "invasion"].item() == 0
    assert not env.inv_active[0, 0]
    assert 1 <= env.inv_timer[0, 0] <= env.invader_respawn_max


def test_invasion_costs_the_team_four_and_invader_respawns_at_the_edge():
    env, td = quiet_scene(spawn="copa")
    env.inv_active[0, 0] = True
    env.inv_pos[0, 0] = torch.tensor([0.3, 0.0])
    nxt, td = step(env, td)
    assert nxt["reward"].item() == pytest.approx(-4.0)
    assert rewards(nxt) == pytest.approx([-4 / 3] * 3)
    assert nxt["events", "invasion"].item() == 1
    assert not env.inv_active[0, 0]
    env.inv_timer[0, 0] = env.invader_respawn_max  # the longest wait
    waited = 0
    while not env.inv_active[0, 0] and waited <= env.invader_respawn_max:
        waited += 1
        nxt, td = step(env, td)
        assert nxt["reward"].item() == 0.0
    assert env.inv_active[0, 0], "invader never respawned"
    assert waited <= env.invader_respawn_max
    assert env.inv_pos[0, 0].abs().max().item() == pytest.approx(env.half)


def test_ties_go_to_the_lower_robot_index():
    env, td = quiet_scene()
    env.pos[0, 1] = torch.tensor([0.15, -1.0])
    env.res_pos[0, 0] = torch.tensor([0.25, -1.0])  # touches both robots, robot 1 closer
    nxt, _ = step(env, td)
    assert rewards(nxt) == [5.0, 0.0, 0.0]
    assert env.carry[0].tolist() == [True, False, False]

    env, td = quiet_scene()
    env.pos[0, 1] = torch.tensor([0.1, -1.2])
    env.inv_active[0, 0] = True
    env.inv_pos[0, 0] = torch.tensor([0.0, -1.3])  # lands between robots 0 and 1
    nxt, _ = step(env, td)
    assert rewards(nxt) == [4.0, 0.0, 0.0]


def test_one_event_per_robot_per_step_defense_first():
    env, td = quiet_scene()
    env.res_pos[0, 0] = torch.tensor([0.2, -1.0])
    env.inv_active[0, 0] = True
    env.inv_pos[0, 0] = torch.tensor([0.0, -1.3])
    nxt, _ = step(env, td)
    assert rewards(nxt) == [4.0, 0.0, 0.0]
    assert not env.carry[0, 0]
    assert torch.allclose(env.res_pos[0, 0], torch.tensor([0.2, -1.0]))


def test_simultaneous_respawns_do_not_overlap():
    env, td = quiet_scene(num_envs=2048)
    env.res_pos[:, :3] = env.pos  # every robot picks one resource in the same step
    step(env, td)
    assert env.carry.all()
    gap = torch.cdist(env.res_pos, env.res_pos) + torch.eye(env.n_resources) * 1e3
    assert gap.min() >= 2 * env.resource_radius


def test_vision_is_a_radius_around_the_robot():
    env, td = quiet_scene()
    L, r = env.layout, env.vision_radius
    diag = torch.tensor([1.0, 1.0]) / math.sqrt(2)
    robot = env.pos[0, 0].clone()
    env.res_pos[0, 0] = robot + (r - 1e-3) * diag  # inside, on the diagonal
    env.res_pos[0, 1] = robot + (r + 1e-3) * torch.tensor([-1.0, 0.0])  # just outside
    env.pos[0, 2] = robot + torch.tensor([-0.4, 0.3])  # another robot, inside
    obs = step(env, td)[0]["agents", "observation"][0, 0]
    tokens = obs[L.own_dim :].view(L.n_entities, L.entity_dim)
    other_robot_2 = 1  # order: other robots (1, 2), resources, invaders, home
    res0, res1 = env.n_agents - 1, env.n_agents
    invader, home = L.n_entities - 2, L.n_entities - 1

    assert tokens[res0, -1] == 1
    torch.testing.assert_close(tokens[res0, 0:2], (r - 1e-3) * diag)
    assert tokens[res0, 4:8].tolist() == [0, 1, 0, 0]
    assert (tokens[res1] == 0).all()
    assert tokens[other_robot_2, -1] == 1
    torch.testing.assert_close(tokens[other_robot_2, 0:2], torch.tensor([-0.4, 0.3]))
    assert (tokens[0] == 0).all()  # robot 1 is far
    assert (tokens[invader] == 0).all()  # inactive
    assert (tokens[home] == 0).all()  # home is 1 m away


def test_inactive_invader_is_invisible_even_when_close():
    env, td = quiet_scene()
    env.inv_pos[0, 0] = env.pos[0, 0] + torch.tensor([0.5, 0.0])
    L = env.layout
    obs = step(env, td)[0]["agents", "observation"][0, 0]
    assert (obs[L.own_dim :].view(L.n_entities, L.entity_dim)[L.n_entities - 2] == 0).all()


def test_instruction_reward_follows_nearest_to_second_nearest_waypoint():
    # Five copies of one scene; env a takes action a for robot 0.
    env, td = quiet_scene(num_envs=N_ACTIONS, inst_reward_scale=1.3, inst_dist_coef=0.1)
    x0, y0 = ROBOTS[0]
    # Nearest (x0+.2), then x0+.5: the path points +x although the list starts at x0+.8.
    env.waypoints[:, 0] = torch.tensor(
        [[x0 + 0.8, y0], [x0 + 0.2, y0], [x0 + 1.1, y0], [x0 + 0.5, y0]]
    )
    actions = torch.zeros(N_ACTIONS, env.n_agents, dtype=torch.int64)
    actions[:, 0] = torch.arange(N_ACTIONS)
    r0 = step(env, td, actions)[0]["agents", "reward"][:, 0, 0]

    move = env.dt * env.dt * env.accel  # displacement of one step from rest
    dirs = torch.tensor([[0.0, 0.0], [-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]])
    new = torch.tensor([x0, y0]) + move * dirs
    cos = torch.tensor([0.0, -1.0, 1.0, 0.0, 0.0])
    e_dist = -(new - torch.tensor([x0 + 0.2, y0])).norm(dim=-1)
    torch.testing.assert_close(r0, 1.3 * (cos + 0.1 * e_dist))
    assert r0.argmax() == RIGHT and r0.argmin() == LEFT


# ---------------------------------------------------------------- waypoints
def test_random_walk_waypoints_refresh_every_interval_near_each_robot():
    env = ResourceCollectionEnv(num_envs=32, seed=2)
    td = env.reset()
    policy, sigma, K = random_policy(env, 2), env.waypoint_sigma, env.n_waypoints
    increments = []

    def check_fresh():
        w = env.waypoints
        first = (w[:, :, 0] - env.pos).norm(dim=-1)
        steps = (w[:, :, 1:] - w[:, :, :-1]).norm(dim=-1)
        assert first.max() < 6 * sigma and steps.max() < 6 * sigma
        assert w.abs().max() <= env.half
        increments.extend([first.flatten(), steps.flatten()])

    check_fresh()
    for t in range(1, 30):
        previous = env.waypoints.clone()
        td = step_mdp(env.step(policy(td)))
        if t % env.waypoint_interval == 0:
            assert not torch.equal(env.waypoints, previous)
            check_fresh()
        else:
            assert torch.equal(env.waypoints, previous)
        assert torch.equal(td["agents", "waypoints"], env.waypoints)
        own = td["agents", "observation"][..., 5 : 5 + 2 * K]
        torch.testing.assert_close(own, (env.waypoints - env.pos.unsqueeze(2)).flatten(2))
    # Gaussian increments: mean norm sigma*sqrt(pi/2) (a bit less where clipped at the edge).
    mean = torch.cat(increments).mean().item()
    assert 0.8 * sigma * math.sqrt(math.pi / 2) < mean < 1.05 * sigma * math.sqrt(math.pi / 2)


def test_path_walks_stay_where_they_were_laid_while_robot_walks_follow_the_robot():
    # sigma 0: a path is its starting point forever, whatever the robots do; a robot's own walk
    # restarts on the robot at every refresh.
    env = ResourceCollectionEnv(num_envs=64, seed=4, waypoint_sigma=0.0, waypoint_path_prob=0.5)
    td = env.reset()
    on_path = env._on_path[:, 0].t()  # [B, N]
    assert 0.3 < on_path.float().mean().item() < 0.7  # about half of the robots
    laid = env.waypoints.clone()
    assert (laid[:, :, 0] - env.pos).norm(dim=-1)[
        on_path
    ].mean() > 1.0  # uniform in the field, not on the robot
    policy = random_policy(env, 1)
    for t in range(1, 13):
        td = step_mdp(env.step(policy(td)))
        if t % env.waypoint_interval == 0:
            w = env.waypoints
            assert torch.equal(w[on_path], laid[on_path])
            torch.testing.assert_close(
                w[~on_path], env.pos[~on_path].unsqueeze(1).expand(-1, env.n_waypoints, 2)
            )
    # with noise, a path's next walk starts one increment from its last waypoint
    env = ResourceCollectionEnv(num_envs=64, seed=4, waypoint_path_prob=1.0)
    td = env.reset()
    last = env.waypoints[:, :, -1].clone()
    for _ in range(env.waypoint_interval):
        td = step_mdp(env.step(policy(td)))
    gap = (env.waypoints[:, :, 0] - last).norm(dim=-1)
    assert gap.max() < 6 * env.waypoint_sigma


@pytest.mark.parametrize("option", ["waypoint_path_prob", "waypoint_route_prob"])
def test_paths_and_routes_are_drawn_after_the_scene_so_first_scenes_are_paired(option):
    # their draws come last in a reset: the same seed gives the same first scene with or without
    # them (paired comparisons of training instructions)
    a, b = (
        ResourceCollectionEnv(num_envs=8, seed=3),
        ResourceCollectionEnv(num_envs=8, seed=3, **{option: 0.5}),
    )
    a.reset(), b.reset()
    for name in ("pos", "res_pos", "inv_pos", "inv_timer"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert not a._on_path.any() and not a._on_route.any()  # 0: nobody on a path or a route
    with pytest.raises(ValueError, match=option):
        ResourceCollectionEnv(**{option: 1.5})


def test_the_cosine_ignores_speed_and_hold_pays_for_staying_at_the_slot():
    from icco_torchrl.envs._kernels import instruction_reward

    # One robot at the origin, its path along +x (nearest waypoint on it, the next 0.25 m on);
    # four moves: full speed along, half speed along, full speed back, full speed across. The
    # cosine pays coasting at half speed what it pays driving (why the greedy follower stalls).
    full = ResourceCollectionEnv().params  # max_speed 1.9 m/s, dt 0.1 s: 0.19 m a step
    step = full.max_speed * full.dt
    wp = torch.tensor([[0.0, 0.0], [0.25, 0.0]]).view(1, 2, 2, 1).expand(1, 2, 2, 4)
    moves = torch.tensor([[step, 0.0], [step / 2, 0.0], [-step, 0.0], [0.0, step]]).t()
    old, new = torch.zeros(1, 2, 4), moves.unsqueeze(0)
    cosine = instruction_reward(wp, old, new, 1.0, 0.0)
    torch.testing.assert_close(cosine, torch.tensor([[1.0, 1.0, -1.0, 0.0]]))
    # at a route's end (the two nearest waypoints coincide) holding still earns what following
    # earned: 1 standing, 0.5 at half speed, nothing at full speed or faster; without it, nothing
    slot = torch.zeros(1, 2, 2, 4)
    moves = torch.tensor([[0.0, 0.0], [step / 2, 0.0], [0.0, -step], [2 * step, 0.0]]).t()
    held = instruction_reward(slot, old, moves.unsqueeze(0), 1.0, 0.0, 1.0 / step)
    torch.testing.assert_close(held, torch.tensor([[1.0, 0.5, 0.0, 0.0]]))
    not_held = instruction_reward(slot, old, moves.unsqueeze(0), 1.0, 0.0)
    torch.testing.assert_close(not_held, torch.zeros(1, 4))
    # the env passes the hold scale from its parameters; off by default (the paper's r_inst)
    assert ResourceCollectionEnv(inst_hold=True)._params().inst_hold == 1.0 / step
    assert ResourceCollectionEnv()._params().inst_hold == 0.0


def test_route_robots_are_served_their_route_to_a_slot_at_every_refresh():
    from icco_torchrl.envs.routes import serve_routes

    env = ResourceCollectionEnv(num_envs=64, seed=5, waypoint_route_prob=0.5)
    td = env.reset()
    on_route = env._on_route[:, 0].t()  # [B, N]
    assert 0.3 < on_route.float().mean().item() < 0.7  # about half of the robots
    slots = env._slot.permute(2, 0, 1).clone()  # [B, N, 2]
    assert slots.abs().max() <= env.half - env.agent_radius
    policy = random_policy(env, 2)
    for t in range(0, 13):
        if t % env.waypoint_interval == 0:  # the reference rule on a straight route [pos, slot]
            route = torch.stack([env.pos, slots], dim=-2)
            served = serve_routes(env.pos, route, env.n_waypoints, env.waypoint_route_step)
            torch.testing.assert_close(env.waypoints[on_route], served[on_route])
            walk = env.waypoints[~on_route]  # the others keep their random walks
            assert not torch.allclose(walk, served[~on_route])
        td = step_mdp(env.step(policy(td)))
    assert torch.equal(env._slot.permute(2, 0, 1), slots)  # a slot holds for the episode
    # a robot within one step of its slot is given K copies of it
    near = ResourceCollectionEnv(num_envs=4, seed=1, waypoint_route_prob=1.0)
    near.reset()
    near._put(_slot=near._pos + 0.1)
    near._refresh_waypoints(torch.arange(4))
    torch.testing.assert_close(
        near.waypoints, near._slot.permute(2, 0, 1).unsqueeze(2).expand(-1, -1, 4, -1)
    )


def test_waypoints_supplied_through_the_tensordict_drive_that_step():
    env, td = quiet_scene(inst_reward_scale=1.3)
    p = env.pos[0]
    offsets = torch.tensor(
        [[0.0, 0.3], [0.0, 0.6], [0.0, 0.9], [0.0, 9.0]]
    )  # path +y; last one off-field
    supplied = (p[:, None, :] + offsets).unsqueeze(0)
    td.set(("agents", "waypoints"), supplied)
    nxt, _ = step(env, td, [UP] * 3)
    move = env.dt * env.dt * env.accel
    expected = 1.3 * (1 - 0.1 * (0.3 - move))
    torch.testing.assert_close(nxt["agents", "reward"][0, :, 0], torch.full((3,), expected))
    torch.testing.assert_close(nxt["agents", "waypoints"], supplied.clamp(-env.half, env.half))
    assert nxt["agents", "waypoints"].abs().max() == env.half


def test_external_waypoints_are_kept_clipped_and_observed():
    env = ResourceCollectionEnv(num_envs=3, seed=0, waypoint_mode="external")
    td = env.reset()
    W = torch.empty(3, env.n_agents, env.n_waypoints, 2).uniform_(-5, 5)  # partly off-field
    clipped = W.clamp(-env.half, env.half)
    td = env.write_waypoints(td, W)
    K = env.n_waypoints
    robots, _, _ = split_state(env, td["state"])
    torch.testing.assert_close(robots[..., 9:], clipped.flatten(2))
    policy = random_policy(env)
    for _ in range(2 * env.waypoint_interval + 1):
        torch.testing.assert_close(td["agents", "waypoints"], clipped)
        own = td["agents", "observation"][..., 5 : 5 + 2 * K]
        torch.testing.assert_close(own, (clipped - env.pos.unsqueeze(2)).flatten(2))
        td = step_mdp(env.step(policy(td)))
    torch.testing.assert_close(env.waypoints, clipped)


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "name,value",
    [
        ("n_agents", 0),
        ("n_resources", -1),
        ("num_envs", 0),
        ("field_size", -1.0),
        ("field_size", 0),
        ("vision_radius", 0.0),
        ("vision_radius", -0.5),
        ("max_steps", 0),
        ("n_waypoints", 1),
    ],
)
def test_bad_parameters_raise_naming_the_parameter(name, value):
    with pytest.raises(ValueError, match=name):
        ResourceCollectionEnv(**{name: value})


@pytest.mark.parametrize(
    "name,value,says",
    [
        ("damping", 1.0, "must be in [0, 1)"),
        ("waypoint_sigma", -0.1, "must be >= 0"),
        ("inst_reward_scale", -1.0, "must be >= 0"),
        ("resource_min_radius", 4.0, "must be in (0, field_size/2)"),
        ("invader_min_radius", -1.0, "must be in [0, field_size/2)"),
        ("waypoint_path_prob", 1.5, "must be in [0, 1]"),
        ("waypoint_route_prob", -0.1, "must be in [0, 1]"),
        ("waypoint_route_step", 0, "must be a positive finite number"),
        ("waypoint_mode", "scripted", "must be one of"),
        ("spawn", "edge", "must be one of"),
        ("pick_reward", "five", "must be a number"),
        ("invader_respawn_max", 2.5, "must be a positive integer"),
    ],
)
def test_each_bad_parameter_is_one_line_starting_with_its_name(name, value, says):
    with pytest.raises(ValueError) as err:
        ResourceCollectionEnv(**{name: value})
    msg = str(err.value)
    assert msg.startswith(f"{name} ") and says in msg and "\n" not in msg


def test_the_parameters_are_one_frozen_table_that_makes_the_signature_and_the_schema():
    import dataclasses
    import inspect

    from icco_torchrl.envs.params import ResourceCollectionParams
    from icco_torchrl.training.config import EnvParams

    table = {f.name: f for f in dataclasses.fields(ResourceCollectionParams)}
    signature = inspect.signature(ResourceCollectionEnv.__init__).parameters
    keywords = {k: p for k, p in signature.items() if p.kind is p.KEYWORD_ONLY}
    assert list(keywords) == [*table, "team_sizes"]
    assert all(keywords[k].default == f.default for k, f in table.items())
    schema = {f.name: (f.type, f.default) for f in dataclasses.fields(EnvParams)}
    assert schema == {k: (f.type, f.default) for k, f in table.items()}
    env = ResourceCollectionEnv(num_envs=1, pick_reward=3, n_agents=2)
    assert env.params == ResourceCollectionParams(pick_reward=3.0, n_agents=2)
    assert env.pick_reward == 3.0 and type(env.pick_reward) is float and env.n_agents == 2
    assert env.event_rewards["pick"] == 3.0 and env.half == env.field_size / 2
    with pytest.raises(AttributeError):
        env.dt = 0.2  # fixed at construction: the step's constants are derived once
    with pytest.raises(dataclasses.FrozenInstanceError):
        env.params.dt = 0.2
    with pytest.raises(TypeError, match="bogus"):
        ResourceCollectionEnv(bogus=1)
    # every field documented once, in the table, and shown in the env's docstring
    assert all(
        f.metadata["doc"] and f"{k} (" in ResourceCollectionEnv.__doc__ for k, f in table.items()
    )


@pytest.mark.parametrize("bad", [torch.zeros(2, 3, 5, 2), torch.zeros(2, 3, 4, 3)])
def test_waypoints_of_the_wrong_shape_raise(bad):
    env = ResourceCollectionEnv(num_envs=2, seed=0)
    td = env.reset()
    with pytest.raises(ValueError, match="waypoints"):
        env.write_waypoints(td, bad)
    td.set(("agents", "waypoints"), bad)
    with pytest.raises(ValueError, match="waypoints"):
        step(env, td)


def test_non_finite_waypoints_raise():
    env = ResourceCollectionEnv(num_envs=2, seed=0)
    td = env.reset()
    W = env.waypoints.clone()
    W[1, 2, 3, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        env.write_waypoints(td, W)
    W[1, 2, 3, 0] = float("inf")
    td.set(("agents", "waypoints"), W)
    with pytest.raises(ValueError, match="non-finite"):
        step(env, td)


@pytest.mark.parametrize("bad_action", [N_ACTIONS, -1])
def test_out_of_range_actions_raise_at_that_step(bad_action):
    env = ResourceCollectionEnv(num_envs=2, seed=0)
    td = env.reset()
    td = step_mdp(env.step(td.set(("agents", "action"), torch.ones(2, 3, dtype=torch.int64))))
    action = torch.ones(2, 3, dtype=torch.int64)
    action[1, 0] = bad_action
    with pytest.raises(ValueError, match="action"):
        env.step(td.set(("agents", "action"), action))
