"""A team's check on the live page's "Go right" (the offline planner's plan), in 8 scenes
(``LiveLoop`` seeds 0-7), over one episode each. What the instruction and the reward ask for:

- **follows**: by tick ``--within``, every robot that is not intercepting has come within
  ``--near`` metres of its nearest waypoint of the plan. A robot is intercepting while an active
  invader is within ``--intercept`` metres of it (the defend-first team's radius), so the team may
  send one robot to defend and still follow.
- **defends**: the team's defenses are at least its invasions over the episode.

A scene passes when both hold. The defaults (30 ticks, 0.75 m, 1.75 m) let every scripted team
follow in every scene, so the defending part decides; measured figures: ``assets/README.md``.

    python assets/go_right.py                                   # the shipped demo policy
    python assets/go_right.py runs/icco/.../checkpoint.pt       # other checkpoints
    python assets/go_right.py --reference 'blend(defend=1.75)' follower   # scripted teams

"never" means not within the episode.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from icco_torchrl.envs.reference_policies import make_reference_policy
from icco_torchrl.instructions import LLMPlanner
from icco_torchrl.live.loop import LiveLoop
from icco_torchrl.training.config import LLMConfig

DEMO = Path(__file__).resolve().parent / "demo_icco.pt"


@dataclass
class Scene:
    followed: int | None  # first tick when every robot not intercepting was near its plan
    defenses: int
    invasions: int

    def passed(self, within: int) -> bool:
        return self.followed is not None and self.followed <= within and self.defends

    @property
    def defends(self) -> bool:
        return self.defenses >= self.invasions


def _loop(source: str | Path, seed: int) -> LiveLoop:
    planner = LLMPlanner.from_config(vars(LLMConfig()))
    if isinstance(source, Path):
        return LiveLoop.from_checkpoint(source, planner=planner, seed=seed)
    loop = LiveLoop.from_checkpoint(DEMO, planner=planner, seed=seed)  # its one-team env
    loop.policy = make_reference_policy(source, loop.env, seed=seed)
    return loop


def run_scene(source: str | Path, seed: int, near: float, intercept: float) -> Scene:
    loop = _loop(source, seed)
    loop.instruct("Go right")
    loop.wait_for_plan(timeout=60)
    followed, state = None, None
    for tick in range(1, 10_000):
        state = loop.tick()
        if followed is None:
            gap = state.invader[None] - state.positions[:, None]  # [N, I, 2]
            close = (np.linalg.norm(gap, axis=-1) < intercept) & state.invader_active[None]
            to_plan = np.linalg.norm(state.waypoints - state.positions[:, None], axis=-1).min(-1)
            if ((to_plan <= near) | close.any(-1)).all():
                followed = tick
        if state.step >= state.episode_steps:  # the episode's last step
            break
    totals = state.totals
    return Scene(followed, int(totals.get("defense", 0)), int(totals.get("invasion", 0)))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="*", type=Path)
    parser.add_argument("--reference", nargs="+", default=[], help="scripted teams to check")
    parser.add_argument("--within", type=int, default=30, help="ticks to reach the plan")
    parser.add_argument("--near", type=float, default=0.75, help="metres from a waypoint")
    parser.add_argument("--intercept", type=float, default=1.75, help="metres to an invader")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    sources = [*args.checkpoints, *args.reference] or [DEMO]
    for source in sources:
        scenes = [run_scene(source, seed, args.near, args.intercept) for seed in range(8)]
        ticks = " / ".join("never" if s.followed is None else str(s.followed) for s in scenes)
        fights = " / ".join(f"{s.defenses}:{s.invasions}" for s in scenes)
        follows = sum(s.followed is not None and s.followed <= args.within for s in scenes)
        defends = sum(s.defends for s in scenes)
        passed = sum(s.passed(args.within) for s in scenes)
        print(
            f"{source}: follows at tick {ticks} (within {args.within}: {follows} of 8); "
            f"defenses:invasions {fights} ({defends} of 8 defend); passes {passed} of 8"
        )


if __name__ == "__main__":
    main()
