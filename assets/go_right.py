"""The demo policy's check: on the live page's "Go right" (the offline planner's plan), how many
ticks until every robot is in the right half of the field, in 8 scenes (``LiveLoop`` seeds 0-7).

    python assets/go_right.py                           # the shipped demo policy
    python assets/go_right.py runs/icco/.../checkpoint.pt [more checkpoints]

"never" means not within ``--ticks`` (200).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from icco_torchrl.instructions import LLMPlanner
from icco_torchrl.live.loop import LiveLoop
from icco_torchrl.training.config import LLMConfig

DEMO = Path(__file__).resolve().parent / "demo_icco.pt"


def ticks_to_right_half(path: Path, seed: int, limit: int) -> int | None:
    planner = LLMPlanner.from_config(vars(LLMConfig()))
    loop = LiveLoop.from_checkpoint(path, planner=planner, seed=seed)
    loop.instruct("Go right")
    loop.wait_for_plan(timeout=60)
    for tick in range(1, limit + 1):
        if (loop.tick().positions[:, 0] > 0).all():
            return tick
    return None


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="*", type=Path, default=[DEMO])
    parser.add_argument("--ticks", type=int, default=200)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    for path in args.checkpoints:
        ticks = [ticks_to_right_half(path, seed, args.ticks) for seed in range(8)]
        shown = " / ".join("never" if t is None else str(t) for t in ticks)
        print(f"{path}: {shown} (never in {ticks.count(None)} of 8)")


if __name__ == "__main__":
    main()
