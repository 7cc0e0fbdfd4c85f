"""Pillow rendering of the resource-collection task, and GIF recording.

Frames are drawn straight from the env's state tensors with ``ImageDraw`` (a few hundred
microseconds per frame), so recording an evaluation episode costs little next to stepping
it, and nothing here needs matplotlib or imageio.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from PIL import Image, ImageDraw

from icco_torchrl.envs.resource_collection import ResourceCollectionEnv

BACKGROUND = (250, 250, 246)
FIELD_EDGE = (90, 90, 90)
HOME = (200, 214, 229)
RESOURCE = (218, 165, 32)
INVADER = (200, 30, 45)
# Robot colours (Tableau-like), chosen far from the resource gold and the invader red.
ROBOT_COLORS = (
    (31, 119, 180),
    (44, 160, 44),
    (148, 103, 189),
    (255, 127, 14),
    (23, 190, 207),
    (227, 119, 194),
    (140, 86, 75),
    (127, 127, 127),
)
MARGIN = 0.04  # fraction of the frame left around the field so edge spawns stay visible


def robot_color(i: int) -> tuple[int, int, int]:
    return ROBOT_COLORS[i % len(ROBOT_COLORS)]


def to_pixel(env: ResourceCollectionEnv, xy, size: int = 480) -> tuple[float, float]:
    """Pixel (column, row) of the field point ``xy`` (metres, +y up) in a ``size`` frame."""
    x, y = float(xy[0]), float(xy[1])
    scale = size * (1 - 2 * MARGIN) / env.field_size
    return size * MARGIN + (x + env.half) * scale, size * MARGIN + (env.half - y) * scale


def _state(env: ResourceCollectionEnv, index: int) -> list[list]:
    """Env ``index``'s pos, carry, res_pos, inv_pos, inv_active, waypoints, present, as lists."""
    keys = ("pos", "carry", "res_pos", "inv_pos", "inv_active", "waypoints", "present")
    return [getattr(env, key)[index].detach().cpu().tolist() for key in keys]


def render_frame(env: ResourceCollectionEnv, index: int = 0, size: int = 480) -> np.ndarray:
    """Draw env ``index`` of ``env`` as an ``[size, size, 3]`` uint8 RGB array.

    Shows the field, home, resources, the active invaders, and each robot of the team (robots
    absent from it are not drawn) in its own colour with its vision circle, its waypoints (dots
    joined by a line) and, when it carries a resource, a gold dot at its centre.
    """
    pos, carry, res, inv, inv_on, wps, present = _state(env, index)
    team = [i for i, here in enumerate(present) if here]  # robots absent from the team: not drawn
    scale = size * (1 - 2 * MARGIN) / env.field_size
    img = Image.new("RGB", (size, size), BACKGROUND)
    draw = ImageDraw.Draw(img)

    def circle(xy, radius_m, min_px=2.0, **style):
        cx, cy = to_pixel(env, xy, size)
        r = max(radius_m * scale, min_px)
        draw.ellipse((cx - r, cy - r, cx + r, cy + r), **style)

    corner0, corner1 = (
        to_pixel(env, (-env.half, env.half), size),
        to_pixel(env, (env.half, -env.half), size),
    )
    draw.rectangle((*corner0, *corner1), outline=FIELD_EDGE, width=2)
    circle((0.0, 0.0), env.home_radius, fill=HOME, outline=FIELD_EDGE)
    for i in team:
        circle(pos[i], env.vision_radius, outline=robot_color(i), width=1)
    for i in team:
        w = wps[i]
        points = [to_pixel(env, q, size) for q in w]
        draw.line(points, fill=robot_color(i), width=1)
        for q in w:
            circle(q, 0.0, min_px=2.5, fill=robot_color(i))
    for q in res:
        circle(q, env.resource_radius, fill=RESOURCE, outline=FIELD_EDGE)
    for q, on in zip(inv, inv_on):
        if on:
            circle(q, env.invader_radius, fill=INVADER, outline=(0, 0, 0))
    for i in team:
        p, c = pos[i], carry[i]
        circle(p, env.agent_radius, fill=robot_color(i), outline=(0, 0, 0))
        if c:
            circle(p, env.agent_radius * 0.45, fill=RESOURCE, outline=(0, 0, 0))
    draw.text((4, 2), f"t={int(env.t[index])}", fill=(0, 0, 0))
    return np.asarray(img)


def write_gif(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: float = 10) -> None:
    """Write ``frames`` (``[H, W, 3]`` uint8) as a looping animated GIF.

    Frames are palettised with the fast octree quantiser: the drawings use few flat colours,
    and Pillow's default (median cut) would take most of the recording time.
    """
    if not frames:
        raise ValueError("write_gif needs at least one frame")
    images = [
        Image.fromarray(np.asarray(f, dtype=np.uint8)).quantize(
            method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE
        )
        for f in frames
    ]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    images[0].save(
        path, save_all=True, append_images=images[1:], duration=int(round(1000 / fps)), loop=0
    )
