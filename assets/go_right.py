"""The arrival check: does the team go where a person tells it, and stay there?

For each instruction (the language protocol's four and "Go to the top left corner") and each
of 8 scenes (``LiveLoop`` seeds 0-7), a team is driven as ``icco live`` drives it: the offline
planner is asked once, its plan is served (``icco_torchrl/instructions/serving.py``), and the
team plays one episode. What a person watching checks:

- **arrives**: by tick ``--within``, every robot that is not intercepting the invader is at its
  slot (within 0.5 m: ``icco_torchrl/evaluation/placement.py``; the intercepting robot is the
  one nearest an active invader within 1.75 m, whom a person excuses; ``--grace N`` excuses it
  for N ticks after too, its way back: ``--grace 10`` is ``placement.RETURN_TICKS``, 1.75 m at
  full speed);
- **stays**: from then to the episode's end, that holds on at least ``--stay`` of the ticks.

A scene passes when both hold; the plan starts beside each robot, so a robot that stays home
passes nothing. Defenses and invasions are printed beside it (the task still counts), and so is
who breaks the formation: the share of ticks after arrival out of formation with exactly one
robot off its slot, standing at home (within 0.5 m of it) with no invader within reach, a
*keeper* (a team that guards home instead of going where told).

    .venv/bin/python assets/go_right.py                                   # the shipped demo
    .venv/bin/python assets/go_right.py runs/icco/.../checkpoint.pt       # other checkpoints
    .venv/bin/python assets/go_right.py --reference pursuit best_scripted # scripted teams

Exit status 1 when some team fails a scene (0 when every scene passes). Figures:
``assets/README.md``.
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from icco_torchrl.envs.reference_policies import make_reference_policy
from icco_torchrl.evaluation.placement import RETURN_TICKS, SLOT_RADIUS
from icco_torchrl.instructions import LLMPlanner
from icco_torchrl.live.loop import LiveLoop
from icco_torchrl.training.config import LLMConfig

DEMO = Path(__file__).resolve().parent / "demo_icco.pt"
INSTRUCTIONS = ("Go right", "Move top", "Gather center", "Spread out", "Go to the top left corner")
SCENES = range(8)
GRACE = 0  # ticks a robot is excused after intercepting (the check as the issue words it)


@dataclass
class Scene:
    arrived: int | None  # first tick in formation (every robot not intercepting at its slot)
    held: float  # the share of ticks in formation from then on
    defenses: int
    invasions: int
    keeper: float = 0.0  # the share of ticks from arrival on broken by one robot kept at home
    returning: float = 0.0  # the share of ticks from arrival on held only by the way back

    def passed(self, within: int, stay: float) -> bool:
        return self.arrived is not None and self.arrived <= within and self.held >= stay


def _loop(source: str | Path, seed: int) -> LiveLoop:
    planner = LLMPlanner.from_config(vars(LLMConfig()))
    if isinstance(source, Path):
        return LiveLoop.from_checkpoint(source, planner=planner, seed=seed)
    loop = LiveLoop.from_checkpoint(DEMO, planner=planner, seed=seed)  # its one-team env
    loop.policy = make_reference_policy(source, loop.env, seed=seed)
    return loop


def run_scene(source: str | Path, instruction: str, seed: int, grace: int = GRACE) -> Scene:
    loop = _loop(source, seed)
    loop.instruct(instruction)
    if loop.wait_for_plan(timeout=60).state != "used":
        raise SystemExit(f"the planner did not plan {instruction!r}: {loop.status.error}")
    formation, kept, back = [], [], []
    since = None  # ticks since each robot last intercepted
    while True:
        state = loop.tick()
        since = ticks_since(since, state.intercepting)
        excused = since <= grace
        formation.append(in_formation(state, excused))
        back.append(formation[-1] and not state.formation)
        kept.append(kept_home(state, excused))
        if state.step >= state.episode_steps:  # the episode's last step
            break
    arrived = next((t + 1 for t, held in enumerate(formation) if held), None)
    after = formation[arrived - 1 :] if arrived else []

    def share(ticks):
        return sum(ticks[arrived - 1 :]) / len(after) if after else 0.0

    totals = state.totals
    defenses, invasions = int(totals.get("defense", 0)), int(totals.get("invasion", 0))
    return Scene(arrived, share(formation), defenses, invasions, share(kept), share(back))


def ticks_since(since: np.ndarray | None, intercepting: np.ndarray | None) -> np.ndarray:
    """Ticks since each robot last intercepted (0 while it does; large before it ever has)."""
    now = np.zeros(0, bool) if intercepting is None else np.asarray(intercepting, bool)
    since = np.full(now.shape, 10**6) if since is None or since.shape != now.shape else since + 1
    return np.where(now, 0, since)


def in_formation(state, excused: np.ndarray) -> bool:
    """Every present robot at its slot but those ``excused`` (intercepting or on the way back)."""
    if state.slot_distance is None:
        return bool(state.formation)
    ok = (state.slot_distance <= SLOT_RADIUS) | excused
    if state.present is not None:
        ok |= ~state.present
    return bool(ok.all())


def kept_home(state, excused: np.ndarray | None = None) -> bool:
    """Out of formation only because one robot, not excused (by default: not intercepting),
    stands at home (0, 0)."""
    excused = state.intercepting if excused is None else excused
    if state.slot_distance is None or in_formation(state, excused):
        return False
    off = (state.slot_distance > SLOT_RADIUS) & ~excused
    if state.present is not None:
        off &= state.present
    home = np.linalg.norm(state.positions, axis=-1) <= SLOT_RADIUS
    return bool(off.sum() == 1 and (off & home).any())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="*", type=Path)
    parser.add_argument("--reference", nargs="+", default=[], help="scripted teams to check")
    parser.add_argument("--instructions", nargs="+", default=list(INSTRUCTIONS))
    parser.add_argument("--within", type=int, default=60, help="ticks to arrive (145 a episode)")
    parser.add_argument("--stay", type=float, default=0.8, help="share of ticks held after")
    parser.add_argument(
        "--grace",
        type=int,
        default=GRACE,
        help=f"ticks excused after intercepting, its way back ({RETURN_TICKS}: 1.75 m)",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    failed = False
    for source in [*args.checkpoints, *args.reference] or [DEMO]:
        name = os.path.relpath(source) if isinstance(source, Path) else source
        total = 0
        for instruction in args.instructions:
            scenes = [run_scene(source, instruction, seed, args.grace) for seed in SCENES]
            passed = sum(s.passed(args.within, args.stay) for s in scenes)
            total += passed
            shown = " / ".join(
                "never" if s.arrived is None else f"{s.arrived}:{100 * s.held:.0f}%" for s in scenes
            )
            fights = " / ".join(f"{s.defenses}:{s.invasions}" for s in scenes)
            keeper = " / ".join(f"{100 * s.keeper:.0f}%" for s in scenes)
            back = " / ".join(f"{100 * s.returning:.0f}%" for s in scenes)
            print(
                f"{name} | {instruction}: passes {passed} of {len(scenes)} "
                f"(arrival tick:held {shown}; defenses:invasions {fights}; keeper {keeper}; "
                f"way back {back})",
                flush=True,
            )
        scenes_run = len(args.instructions) * len(SCENES)
        print(f"{name}: passes {total} of {scenes_run} scenes", flush=True)
        failed |= total < scenes_run
    return int(failed)


if __name__ == "__main__":
    sys.exit(main())
