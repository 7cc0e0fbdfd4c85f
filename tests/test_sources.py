"""Instruction sources: quadrant references stay inside their quadrant and are smooth, the
random-walk source reproduces the env's training convention, fixed waypoints are written once."""

import pytest
import torch

from icco_torchrl.envs import FixedSource, QuadrantSource, RandomWalkSource, ResourceCollectionEnv
from icco_torchrl.envs.waypoints import QUADRANT_SIGNS


def drive(env, source, steps, seed=0):
    """Step ``env`` with random actions under ``source``; the waypoints in force at each step
    ``[T, B, N, K, 2]``, the positions they were made from ``[T, B, N, 2]`` and the steps
    where the source wrote new ones."""
    gen = torch.Generator().manual_seed(seed)
    td = env.reset()
    source.reset(env, td)
    waypoints, positions, written = [], [], []
    for step in range(steps):
        new = source(env, td, step)
        if new is not None:
            env.write_waypoints(td, new)
            written.append(step)
        waypoints.append(env.waypoints.clone())
        positions.append(env.pos.clone())
        td.set(
            ("agents", "action"), torch.randint(0, 5, (env.num_envs, env.n_agents), generator=gen)
        )
        td = env.step(td)["next"]
    return torch.stack(waypoints), torch.stack(positions), written


@pytest.mark.parametrize("quadrant", [1, 2, 3, 4])
def test_quadrant_waypoints_stay_strictly_inside_and_move_in_bounded_steps(quadrant):
    env = ResourceCollectionEnv(num_envs=32, seed=quadrant, waypoint_mode="external", max_steps=40)
    source = QuadrantSource(quadrant, seed=quadrant)
    wps, pos, written = drive(env, source, 40)
    sx, sy = QUADRANT_SIGNS[quadrant]
    assert (wps[..., 0] * sx > 0).all() and (wps[..., 1] * sy > 0).all()
    assert (wps.abs() <= env.half - source.margin + 1e-6).all() and (
        wps.abs() >= source.margin - 1e-6
    ).all()
    limit = 3 * env.waypoint_sigma + 1e-5
    assert ((wps[:, :, :, 1:] - wps[:, :, :, :-1]).abs() <= limit).all()
    # The walk starts where the robot is, projected into the quadrant.
    low, high = source.bounds(env)
    assert written == [0, 4, 8, 12, 16, 20, 24, 28, 32, 36]
    start = pos[written].clamp(low, high)
    assert ((wps[written][:, :, :, 0] - start).abs() <= limit).all()
    # A zero-mean walk, not a fixed point: the waypoints spread.
    assert (wps[:, :, :, -1] - wps[:, :, :, 0]).norm(dim=-1).mean() > env.waypoint_sigma


def test_quadrant_refreshes_at_segment_start_and_on_the_env_clock():
    env = ResourceCollectionEnv(num_envs=2, seed=0, waypoint_mode="external", max_steps=20)
    td = env.reset()
    for _ in range(5):  # a segment that starts at t = 5: refresh now, then at t = 8, 12
        td.set(("agents", "action"), torch.zeros(2, 3, dtype=torch.int64))
        td = env.step(td)["next"]
    source = QuadrantSource(2)
    source.reset(env, td)
    due = []
    for step in range(8):
        if source(env, td, step) is not None:
            due.append(int(env.t[0]))
        td.set(("agents", "action"), torch.zeros(2, 3, dtype=torch.int64))
        td = env.step(td)["next"]
    assert due == [5, 8, 12]


def test_bad_quadrant_arguments_fail_fast():
    for kwargs in (
        dict(quadrant=0),
        dict(quadrant=5),
        dict(quadrant=1, margin=0),
        dict(quadrant=1, sigma=-1),
    ):
        with pytest.raises(ValueError):
            QuadrantSource(**kwargs)
    env = ResourceCollectionEnv(num_envs=1, waypoint_mode="external")
    with pytest.raises(ValueError, match="margin"):
        QuadrantSource(1, margin=2.0).bounds(env)


def test_random_walk_source_follows_the_env_training_convention():
    n = 256
    internal = ResourceCollectionEnv(num_envs=n, seed=0, max_steps=16)  # the env's own random walk
    external = ResourceCollectionEnv(num_envs=n, seed=0, max_steps=16, waypoint_mode="external")
    source = RandomWalkSource(seed=1)
    assert (
        source.settings(external)
        == (internal.waypoint_sigma, internal.waypoint_interval)
        == (0.19, 4)
    )

    def increments(env, src):
        wps, pos, _ = drive(env, src, 16)
        changed = [t for t in range(1, 16) if not torch.equal(wps[t], wps[t - 1])]
        fresh = [0, *changed]  # each walk starts at the position of the step it is first used on
        wps, pos = wps[fresh], pos[fresh]
        steps = torch.cat([wps[..., :1, :] - pos.unsqueeze(-2), wps.diff(dim=-2)], -2)
        inside = (wps.abs() < env.half - 1e-3).all(-1).all(-1)  # walks not clipped at the edge
        return changed, steps[inside]

    changed_env, steps_env = increments(internal, _Keep())

    changed_src, steps_src = increments(external, source)
    assert changed_env == changed_src == [4, 8, 12]
    for steps in (steps_env, steps_src):
        assert steps.mean().abs() < 0.01
        assert abs(steps.std().item() - 0.19) < 0.01


class _Keep(RandomWalkSource):
    """No waypoints from outside: the env's own random walk stays in force."""

    def __call__(self, env, td, step):
        return None


def test_fixed_source_is_written_once_and_checks_its_shape():
    env = ResourceCollectionEnv(num_envs=3, waypoint_mode="external")
    target = torch.tensor([1.0, -1.0]).expand(3, 4, 2)
    wps, _, written = drive(env, FixedSource(target), 6)
    assert written == [0]
    assert torch.allclose(wps, target.expand_as(wps))
    with pytest.raises(ValueError, match="do not fit"):
        FixedSource(torch.zeros(2, 4, 2))(env, None, 0)
    with pytest.raises(ValueError):
        FixedSource(torch.zeros(4, 2))
