"""Best-team screens: which learning lever closes the gap to the best scripted team.

    python experiments/best_team/run.py                       # every screen, resumable
    python experiments/best_team/run.py --only icco icco_layernorm --seeds 0
    python experiments/best_team/run.py --train-only          # stop after training

A screen is one method at :data:`BUDGET` plus the lever's overrides, two seeds (a screen, not a
result). Training runs go to ``--out/<screen>/<method>_seed<k>``, two side by side, one thread
each, seed by seed across screens (so a sitting cut short leaves paired seeds); a run cut short
continues from its checkpoint when the script runs again. Each screen is then evaluated by the
four-quadrant experiment (``experiments/four_quadrants/run.py``: ``icco eval
eval.protocol=quadrants``, 20 trials per seed, seeds pooled, the scripted references on the same
episodes) into ``screens/<screen>/``. Levers measured and not kept left the library with their
screens; their pages keep the numbers and the command, at the last commit that trains them
(``README.md``).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from icco_torchrl.training.build import compose_config

HERE = Path(__file__).resolve().parent
EXPERIMENTS = HERE.parent
sys.path.insert(0, str(EXPERIMENTS))
from jobs import positive, train_runs  # noqa: E402  (experiments/jobs.py, the one job runner)

# At least 2M frames (the screen budget), the 5M reproduction's recipe otherwise.
BUDGET = ["experiment=repro_5m", "train.total_frames=2000000"]
SEEDS = (0, 1)
# The controls are the agent without LayerNorm, as they were trained before it became the default.
CONTROL = ["method.layer_norm=false"]
SCREENS = {  # name: (lever, method, overrides)
    "icco": ("control", "icco", CONTROL),
    "icco_layernorm": (
        "LayerNorm in the agent's trunk (the GRU's input) and Q head",
        "icco",
        ["method.layer_norm=true"],
    ),
    "icco_process": (
        "speed recipe, not a lever: the env and acting in a collector process "
        "(train.collector=process, one batch of policy lag); learning must stay the control's",
        "icco",
        ["train.collector=process", *CONTROL],
    ),
    # A speed recipe (benchmarks/README.md): half the updates, each twice as large, at the same
    # replay ratio (8); learning is compared with icco_layernorm, today's default agent.
    "icco_fewer_updates": (
        "4 updates of 64 sequences per batch instead of 8 of 32 (replay ratio 8 kept)",
        "icco",
        ["method.layer_norm=true", "train.updates_per_batch=4", "train.batch_segments=64"],
    ),
    "qmix_full": ("control", "qmix_full", CONTROL),
}


def train(out: Path, names, seeds, jobs: int) -> None:
    runs = {}
    for seed in seeds:
        for name in names:
            lever, method, overrides = SCREENS[name]
            cfg = compose_config([f"method={method}", *BUDGET, *overrides])
            runs[out / name / f"{method}_seed{seed}"] = (
                [f"method={method}", f"seed={seed}", *BUDGET, *overrides],
                cfg.train.total_frames,
            )
    train_runs(runs, jobs)


def evaluate(out: Path, name: str, seeds) -> None:
    lever, method, overrides = SCREENS[name]
    folder = HERE / "screens" / name
    folder.mkdir(parents=True, exist_ok=True)
    command = [
        sys.executable,
        str(EXPERIMENTS / "four_quadrants" / "run.py"),
        "--methods",
        method,
        "--seeds",
        *map(str, seeds),
        "--sweep",
        str(out / name),
        "--readme",
        str(folder / "README.md"),
        "--budget",
        *BUDGET,
        *overrides,
    ]
    print("$ " + " ".join(command), flush=True)
    subprocess.run(command, check=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=Path("multirun/best_team"))
    parser.add_argument("--only", nargs="+", choices=list(SCREENS))
    parser.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    parser.add_argument("--jobs", type=positive, default=2, help="training runs side by side")
    parser.add_argument("--train-only", action="store_true")
    args = parser.parse_args(argv)
    out, names = args.out.resolve(), args.only or list(SCREENS)
    train(out, names, args.seeds, args.jobs)
    if not args.train_only:
        for name in names:
            evaluate(out, name, args.seeds)


if __name__ == "__main__":
    main()
