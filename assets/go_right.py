"""The demo policy's check on the live page's "Go right" (the offline planner's plan), in 8 scenes
(``LiveLoop`` seeds 0-7), over one episode:

- **lines up**: the tick when every robot is first in the right half of the field;
- **delivers what it carries**: every load picked up at least ``--deliver-within`` ticks before
  the episode ends is brought home (a robot still carrying one it took earlier fails the scene).

A scene passes when both hold. ``python assets/go_right.py`` checks the shipped demo policy;
``python assets/go_right.py runs/icco/.../checkpoint.pt [more]`` checks others. "never" means not
within the episode.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from icco_torchrl.instructions import LLMPlanner
from icco_torchrl.live.loop import LiveLoop
from icco_torchrl.training.config import LLMConfig

DEMO = Path(__file__).resolve().parent / "demo_icco.pt"


@dataclass
class Scene:
    lined_up: int | None  # tick when every robot was first in the right half
    picks: int
    deliveries: int
    undelivered: int  # loads held since before the last `deliver_within` ticks at the end

    @property
    def passed(self) -> bool:
        return self.lined_up is not None and self.undelivered == 0


def run_scene(path: Path, seed: int, deliver_within: int) -> Scene:
    planner = LLMPlanner.from_config(vars(LLMConfig()))
    loop = LiveLoop.from_checkpoint(path, planner=planner, seed=seed)
    loop.instruct("Go right")
    loop.wait_for_plan(timeout=60)
    lined_up, held_since = None, None
    state = None
    for tick in range(1, 10_000):
        state = loop.tick()
        if held_since is None:
            held_since = np.full(len(state.carry), -1)
        carrying = np.asarray(state.carry) > 0
        held_since = np.where(carrying, np.where(held_since < 0, tick, held_since), -1)
        if lined_up is None and (state.positions[:, 0] > 0).all():
            lined_up = tick
        if state.step >= state.episode_steps:  # the episode's last step
            break
    late = tick - deliver_within
    totals = state.totals
    return Scene(
        lined_up=lined_up,
        picks=int(totals.get("pick", 0)),
        deliveries=int(totals.get("collect", 0)),
        undelivered=int(((held_since >= 0) & (held_since <= late)).sum()),
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="*", type=Path, default=[DEMO])
    parser.add_argument("--deliver-within", type=int, default=60, help="ticks a trip may take")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    for path in args.checkpoints:
        scenes = [run_scene(path, seed, args.deliver_within) for seed in range(8)]
        lined = " / ".join("never" if s.lined_up is None else str(s.lined_up) for s in scenes)
        trips = " / ".join(f"{s.deliveries}/{s.picks}" for s in scenes)
        passed = sum(s.passed for s in scenes)
        print(f"{path}: lines up at tick {lined}; delivered/picked {trips}; passes {passed} of 8")


if __name__ == "__main__":
    main()
