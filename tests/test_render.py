"""Rendering: frames show the scene where it is, and GIFs are written and readable."""

import numpy as np
import torch
from PIL import Image

from icco_torchrl.envs import ResourceCollectionEnv
from icco_torchrl.envs.render import (
    INVADER,
    RESOURCE,
    render_frame,
    robot_color,
    to_pixel,
    write_gif,
)

torch.set_num_threads(1)


def scene():
    """Two envs; in env 1 the robots stand apart on the left, far from resources and waypoints."""
    env = ResourceCollectionEnv(num_envs=2, seed=0)
    env.reset()
    env.pos[1] = torch.tensor([[-2.0, 2.0], [-2.0, 0.0], [-2.0, -2.0]])
    env.carry[1] = False
    env.res_pos[1] = torch.tensor([[2.5, y] for y in (-2.5, -1.5, -0.5, 0.5, 1.5, 2.5)])
    env.waypoints[1] = torch.tensor([2.0, 0.0])
    env.inv_active[1] = False
    return env


def pixel(frame, env, xy, size):
    col, row = to_pixel(env, xy, size)
    return tuple(frame[int(row), int(col)])


def test_frame_shape_dtype_and_content():
    env = scene()
    frame = render_frame(env, index=1, size=200)
    assert frame.shape == (200, 200, 3) and frame.dtype == np.uint8
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 5
    assert render_frame(env, index=0).shape == (480, 480, 3)


def test_robots_drawn_in_their_colours_where_they_are():
    env, size = scene(), 240
    frame = render_frame(env, index=1, size=size)
    for i in range(env.n_agents):
        assert pixel(frame, env, env.pos[1, i], size) == robot_color(i)
    assert len({robot_color(i) for i in range(env.n_agents)}) == env.n_agents


def test_frame_changes_when_a_robot_moves():
    env, size = scene(), 240
    before = render_frame(env, index=1, size=size)
    old = env.pos[1, 0].clone()
    env.pos[1, 0] = torch.tensor([0.5, 2.0])
    after = render_frame(env, index=1, size=size)
    assert not np.array_equal(before, after)
    assert pixel(after, env, env.pos[1, 0], size) == robot_color(0)
    assert pixel(after, env, old, size) != robot_color(0)
    assert np.array_equal(
        render_frame(env, index=0, size=size), render_frame(env, index=0, size=size)
    )


def test_carry_marker_resources_and_invader():
    env, size = scene(), 240
    env.carry[1, 1] = True
    env.inv_pos[1, 0] = torch.tensor([1.0, -1.0])
    frame = render_frame(env, index=1, size=size)
    assert pixel(frame, env, env.pos[1, 1], size) == RESOURCE
    assert pixel(frame, env, env.res_pos[1, 3], size) == RESOURCE
    assert pixel(frame, env, env.inv_pos[1, 0], size) != INVADER  # inactive: not drawn
    env.inv_active[1, 0] = True
    assert pixel(render_frame(env, index=1, size=size), env, env.inv_pos[1, 0], size) == INVADER


def test_write_gif(tmp_path):
    env = ResourceCollectionEnv(num_envs=2, seed=0, max_steps=6)
    td = env.reset()
    frames = [render_frame(env, index=1)]
    for _ in range(3):  # the robots drive +x: the frames differ
        td = env.step(td.set(("agents", "action"), torch.full((2, env.n_agents), 2)))["next"]
        frames.append(render_frame(env, index=1))
    assert not np.array_equal(frames[0], frames[-1])
    write_gif(frames, tmp_path / "sub" / "short.gif", fps=5)
    with Image.open(tmp_path / "sub" / "short.gif") as gif:
        assert (
            gif.is_animated
            and gif.n_frames == 4
            and gif.info["duration"] == 200
            and gif.size == (480, 480)
        )
