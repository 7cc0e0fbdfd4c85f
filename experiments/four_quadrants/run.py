"""Four-quadrant experiment (paper Sec. V-B, Fig. 4 and 5a): train, evaluate, report.

    python experiments/four_quadrants/run.py           # default budget, every method x 3 seeds
    python experiments/four_quadrants/run.py --budget experiment=paper device=cuda
    python experiments/four_quadrants/run.py --smoke               # seconds-long end-to-end check

1. Training: one ``icco train method=M seed=S <budget>`` process per run into ``--sweep`` (one
   folder ``<method>_seed<seed>`` per run), ``--jobs`` (2) side by side. Run the script again
   after an interruption: finished runs are kept, interrupted ones continue from their
   checkpoint with ``resume=``, missing ones are started.
2. Evaluation: ``icco eval`` with the quadrant protocol on the checkpoints of ``--methods`` x
   ``--seeds`` (seeds pooled per method) into ``<sweep>/eval_quadrants``.
3. Report: ``report.py <sweep>`` fills ``README.md`` here from ``README.template.md``.

With ``--records DIR`` each evaluated run also leaves its record in ``DIR/<run>/`` (its config,
greedy-eval curve, timing, references and its own quadrant trials), and the report pools every
record there. Checkpoints stay on the machine that trained them, so seeds trained on different
machines meet in one report: the 5M reproduction keeps its records in ``5m/records/`` here
and its page in ``5m/README.md``.

``--train-only`` stops after step 1 (the language experiment uses it to train its agents).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import torch

from icco_torchrl import methods
from icco_torchrl.training.build import compose_config

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import jobs  # noqa: E402  (experiments/jobs.py, a sibling script)
from jobs import train_runs  # noqa: E402

HERE = Path(__file__).resolve().parent
SEEDS = (0, 1, 2)


def icco(*args: str) -> None:
    """Run ``icco ARGS`` in a child process; a failure stops the script."""
    command = [sys.executable, "-m", "icco_torchrl", *args]
    print("$ icco " + " ".join(args), flush=True)
    subprocess.run(command, check=True)


def train(sweep: Path, methods, seeds, budget, jobs: int = 2) -> None:
    """Bring every ``method x seed`` run in ``sweep`` to its budget (see
    ``experiments/jobs.py``)."""
    totals = {m: compose_config([f"method={m}", *budget]).train.total_frames for m in methods}
    train_runs(
        {
            sweep / f"{m}_seed{s}": ([f"method={m}", f"seed={s}", *budget], totals[m])
            # Seed by seed: a sweep cut short has every method at the same seeds.
            for s in seeds
            for m in methods
        },
        jobs,
    )


def machine() -> dict:
    """What the numbers were measured on (for the README)."""
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return dict(
        host=platform.node(),
        cpu=jobs.cpu_name(),
        cores=os.cpu_count(),
        python=platform.python_version(),
        torch=torch.__version__,
        gpu=gpu,
        platform=platform.platform(),
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--sweep", type=Path, help="sweep folder (default multirun/four_quadrants[_smoke])"
    )
    parser.add_argument(
        "--budget",
        nargs="*",
        help="training overrides (default experiment=default), "
        "e.g. experiment=paper device=cuda; with --smoke, added to the smoke budget",
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        default=list(methods.names()),
        choices=methods.names(),
        help="default: every method (conf/method/)",
    )
    parser.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    parser.add_argument(
        "--trials",
        type=jobs.positive,
        default=20,
        help="evaluation trials per checkpoint (paper: 20)",
    )
    parser.add_argument(
        "--steps", type=jobs.positive, default=145, help="steps per quadrant (paper: 145)"
    )
    parser.add_argument("--gif", action="store_true", help="also write a GIF per method")
    parser.add_argument(
        "--smoke", action="store_true", help="tiny budget, 4 trials, 20 steps: a pipeline check"
    )
    parser.add_argument("--train-only", action="store_true", help="stop after training")
    parser.add_argument(
        "--jobs", type=jobs.positive, default=2, help="training runs side by side (one core each)"
    )
    parser.add_argument(
        "--readme", type=Path, default=HERE / "README.md", help="where report.py writes"
    )
    parser.add_argument(
        "--records",
        type=Path,
        help="keep each evaluated run's record here and report on every record there",
    )
    args = parser.parse_args(argv)
    budget = jobs.budget(args.smoke, args.budget, ["experiment=default"])
    trials, steps = (4, 20) if args.smoke else (args.trials, args.steps)
    sweep = (args.sweep or Path("multirun/four_quadrants" + "_smoke" * args.smoke)).resolve()
    sweep.mkdir(parents=True, exist_ok=True)

    start = time.time()
    train(sweep, args.methods, args.seeds, budget, args.jobs)
    info_path = sweep / "sweep.json"
    info = json.loads(info_path.read_text()) if info_path.exists() else {"train_wall_s": 0.0}
    info.update(
        budget=budget, methods=args.methods, seeds=args.seeds, machine=machine(), smoke=args.smoke
    )
    info["train_wall_s"] += time.time() - start  # summed over the script's invocations
    info_path.write_text(json.dumps(info, indent=2))
    if args.train_only:
        return

    # The runs asked for, not every run in the sweep: another seed may still be training there.
    checkpoints = [
        str(p)
        for m in args.methods
        for p in (sweep / f"{m}_seed{s}" / "checkpoint.pt" for s in args.seeds)
        if p.is_file()
    ]
    out = sweep / "eval_quadrants"
    start = time.time()
    icco(
        "eval",
        f"eval.checkpoints=[{','.join(checkpoints)}]",
        "eval.protocol=quadrants",
        f"eval.trials={trials}",
        f"eval.steps={steps}",
        f"eval.gif={str(args.gif).lower()}",
        f"eval.out_dir={out}",
        f"hydra.run.dir={out}",
    )
    info.update(eval_wall_s=time.time() - start, eval_trials=trials, eval_steps=steps)
    info_path.write_text(json.dumps(info, indent=2))
    records = []
    if args.records:
        jobs.keep_records(out / "quadrants.json", out / "quadrants_trials.csv", args.records)
        records = ["--records", str(args.records)]
    subprocess.run(
        [
            sys.executable,
            str(HERE / "report.py"),
            str(sweep),
            "--readme",
            str(args.readme),
            *records,
        ],
        check=True,
    )


if __name__ == "__main__":
    main()
