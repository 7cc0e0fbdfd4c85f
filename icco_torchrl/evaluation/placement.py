"""Where the robots are, judged as a person watching would: arrival at the slots, the formation,
and "in place" for an instruction.

A person who says "Go right" looks at where the robots are, not at how far each is from the
nearest point of some plan (a robot that stays home satisfies that: its plan starts beside it).
The judgements here read only the robots' positions, their slots (the plan's route ends,
:mod:`icco_torchrl.instructions.serving`) and the invader, so no robot standing still can pass
one it is not meant to. Per step, batched over envs ``[B]`` and robots ``[N]``:

- **at slot**: a robot within :data:`SLOT_RADIUS` of its own slot;
- **intercepting**: the present robot nearest an active invader, when within
  :data:`INTERCEPT_RADIUS` of it: the one robot a person excuses from the formation ("go right,
  except whoever must stop the invader");
- **formation**: every present robot that is not intercepting is at its slot;
- **in place**: at least ``n - 1`` of the ``n`` present robots (2 of 3) stand where the
  instruction says (:func:`region`), judged from the instruction's words, not from any plan.

The regions (half = half the field's side, 3.25 m by default):

- a side or a corner ("Go right", "Move top", "Go to the top left corner"): beyond half/2 on
  each named axis (x > half/2 for "right");
- a place ("Gather center", "Gather at (1, -2)", "quadrant 2"): within the formation's radius
  plus :data:`PLACE_MARGIN` of it (1 m of the centre for "Gather center");
- "Spread out": at least :data:`SPREAD_GAP` from every other present robot;
- anything else (hold, task orders, a line through the centre): not judged (NaN).

    >>> import torch
    >>> judge = region("Go right", half=3.25)
    >>> pos = torch.tensor([[[2.0, 0.0], [-1.0, 0.0], [1.7, 3.0]]])  # [B = 1, N = 3, 2]
    >>> judge(pos, torch.ones(1, 3, dtype=torch.bool))
    tensor([[ True, False,  True]])
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from icco_torchrl.instructions.planner import Intent, UnknownInstruction, parse

SLOT_RADIUS = 0.5  # metres: a robot this close to its slot is at it (robot radius 0.15 m)
INTERCEPT_RADIUS = 1.75  # metres: the defend-first team's radius (experiments/calibration)
# A robot's way back after it intercepted: INTERCEPT_RADIUS at full speed (0.19 m per step), in
# steps. The judgements here (the pages' "formation", the live page) excuse only the robot
# intercepting now; the arrival check excuses its way back too with --grace (assets/go_right.py).
RETURN_TICKS = 10
PLACE_MARGIN = 1.0  # metres beyond a formation's radius that still count as "there"
SPREAD_GAP = 1.5  # metres: "spread out" means at least this far from every other robot
SIDE_DEPTH = 0.5  # a side's region starts this fraction of the half width from the centre

Judge = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def at_slot(pos: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
    """``[B, N]``: each robot within :data:`SLOT_RADIUS` of its slot."""
    return (pos - slots.to(pos)).norm(dim=-1) <= SLOT_RADIUS


def intercepting(
    pos: torch.Tensor, present: torch.Tensor, inv_pos: torch.Tensor, inv_active: torch.Tensor
) -> torch.Tensor:
    """``[B, N]``: the present robot nearest each active invader (``inv_pos`` ``[B, I, 2]``,
    ``inv_active`` ``[B, I]``), when it is within :data:`INTERCEPT_RADIUS` of it."""
    gap = (pos.unsqueeze(-2) - inv_pos.unsqueeze(-3)).norm(dim=-1)  # [B, N, I]
    gap = gap.masked_fill(~present.unsqueeze(-1), float("inf"))
    nearest = gap.argmin(-2)  # [B, I]
    near = (gap.amin(-2) <= INTERCEPT_RADIUS) & inv_active  # [B, I]
    one_hot = torch.nn.functional.one_hot(nearest, pos.shape[-2]).bool()  # [B, I, N]
    return (one_hot & near.unsqueeze(-1)).any(-2)


def formation(at: torch.Tensor, present: torch.Tensor, excused: torch.Tensor) -> torch.Tensor:
    """``[B]``: every present robot that is not ``excused`` is at its slot (``at`` ``[B, N]``)."""
    return (at | ~present | excused).all(-1)


def in_place(inside: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    """``[B]``: at least ``n - 1`` of the ``n`` present robots (at least one) are ``inside``."""
    n = present.sum(-1)
    return (inside & present).sum(-1) >= (n - 1).clamp_min(1)


def _side(direction: tuple[float, float], half: float) -> Judge:
    signs = torch.tensor(direction)
    named = signs != 0

    def judge(pos, present):
        beyond = pos * signs.to(pos) > SIDE_DEPTH * half
        return (beyond | ~named.to(pos.device)).all(-1)

    return judge


def _near(anchor: tuple[float, float], radius: float) -> Judge:
    centre = torch.tensor(anchor)

    def judge(pos, present):
        return (pos - centre.to(pos)).norm(dim=-1) <= radius + PLACE_MARGIN

    return judge


def _spread(pos: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    gap = (pos.unsqueeze(-2) - pos.unsqueeze(-3)).norm(dim=-1)  # [B, N, N]
    others = present.unsqueeze(-2) & ~torch.eye(pos.shape[-2], dtype=torch.bool, device=pos.device)
    return (gap.masked_fill(~others, float("inf")) >= SPREAD_GAP).all(-1)


def region(instruction: str, half: float) -> Judge | None:
    """``judge(pos [B, N, 2], present [B, N]) -> [B, N]``: which robots stand where
    ``instruction`` says (module docstring); None for an instruction it does not judge."""
    try:
        intent = parse(instruction, half)
    except UnknownInstruction:
        return None
    return _judge(intent, half)


def _judge(intent: Intent, half: float) -> Judge | None:
    if intent.kind == "spread":
        return _spread
    if intent.kind in ("hold", "task"):
        return None
    if intent.direction != (0.0, 0.0):
        return _side(intent.direction, half)
    if intent.anchor is None or (intent.kind == "line"):
        return None  # the team's own centroid, or a line through a point: the slots judge it
    return _near(intent.anchor, intent.radius)
