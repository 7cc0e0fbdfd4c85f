"""Time to skill: frames and wall-clock until the greedy team reward first passes the follower's.

    python benchmarks/time_to_skill.py                    # train the runs it needs, then report
    python benchmarks/time_to_skill.py --report-only      # report from the runs already there

For ICCO and QMIX (FULL), each at the old defaults (4-step items, one-step targets) and at
today's defaults, two seeds each: ``icco train`` at the reproduction's budget
(``experiment=repro_cpu``, one torch thread, two runs side by side) with a greedy evaluation
every ``--eval-interval`` frames. At the method's scale (``5M``): the 5M-frame reproduction's
own runs (``experiment=repro_5m``, the compiled update, an evaluation every 100k frames), seeds
0 and 1 of ``--scale-sweep``, trained here when missing. A run's skill time is the first
evaluation whose team reward passes the follower's on the same evaluation episodes
(``references.json``, written by the run itself), read from its ``eval.csv``; the wall-clock is
the run's own time (collection, learning, evaluations) up to that evaluation, from
``timing.csv``. "never" means not within the budget. A 5M run still under way is reported
once it has passed (``"finished": false``, its curve up to where it is).

Writes ``benchmarks/results/time_to_skill.json`` and ``time_to_skill.png`` (greedy team reward
against frames, mean of the seeds, the follower's level dashed).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from icco_torchrl.training.logger import clock_seconds, read_column

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))
from jobs import PRE_SEQUENCE_REPLAY, run_status, train_runs  # noqa: E402  (experiments/jobs.py)

RESULTS = ROOT / "benchmarks" / "results"
BUDGET = ["experiment=repro_cpu", "train.checkpoint_buffer=false", "logger.progress=false"]
# Old defaults: the recipe before sequence replay (what the reproduction of 2026-11-30 trained).
RECIPES = {"old defaults": PRE_SEQUENCE_REPLAY, "new defaults": [], "5M": ["experiment=repro_5m"]}
SCALE = "5M"  # its runs are the 5M reproduction's (experiments/four_quadrants, --scale-sweep)
SCALE_FRAMES = 5_000_000
METHODS = {"icco": "ICCO", "qmix_full": "QMIX (FULL)"}
SEEDS = (0, 1)


def runs(
    out: Path, methods=tuple(METHODS), scale_sweep: Path | None = None, recipes=tuple(RECIPES)
) -> dict[tuple[str, str, int], Path]:
    def folder(method, recipe, seed):
        if recipe == SCALE:
            return (scale_sweep or out) / f"{method}_seed{seed}"
        return out / f"{method}_{recipe.split()[0]}_seed{seed}"

    return {
        (method, recipe, seed): folder(method, recipe, seed)
        for method in methods
        for recipe in recipes
        for seed in SEEDS
    }


def skill_time(run: Path) -> dict | None:
    """First evaluation past the follower: frames and the run's clock up to it."""
    evals, refs = read_column(run, "eval", "reward"), run / "references.json"
    if evals is None or not refs.is_file():
        return None
    follower = json.loads(refs.read_text())["follower"]["reward"]
    curve = [(int(f), float(r)) for f, r in zip(*evals)]
    out = {"follower": follower, "curve": curve, "frames": None, "wall_s": None}
    passed = next((frames for frames, reward in curve if reward > follower), None)
    if passed is not None:
        out["frames"] = passed
        timing = csv.DictReader((run / "timing.csv").open())
        row = next((r for r in timing if int(r["frames"]) >= passed), None)
        out["wall_s"] = None if row is None else clock_seconds(row)
    out["budget_frames"] = curve[-1][0]
    return out


def report(out: Path, scale_sweep: Path | None = None) -> dict:
    rows = []
    for (method, recipe, seed), run in runs(out, scale_sweep=scale_sweep).items():
        result = skill_time(run)
        if recipe == SCALE and result is not None and run_status(run, SCALE_FRAMES) != "done":
            if result["frames"] is None:
                continue  # a 5M run still under way that has not passed yet says nothing yet
            result["finished"] = False  # its skill time is known; its curve stops early
        if result is not None:
            rows.append({"method": method, "recipe": recipe, "seed": seed, **result})
    return {"budget": BUDGET, "old_defaults": PRE_SEQUENCE_REPLAY, "runs": rows}


def plot(results: dict, path: Path) -> None:
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    for (method, label), color in zip(METHODS.items(), ("#1f77b4", "#2ca02c")):
        for recipe, style in zip(RECIPES, (":", "-", "-.")):
            curves = [
                r["curve"]
                for r in results["runs"]
                if (r["method"], r["recipe"]) == (method, recipe)
            ]
            if not curves:
                continue
            n = min(len(c) for c in curves)
            frames = np.array([c[i][0] for i in range(n) for c in curves[:1]])
            mean = np.array([[c[i][1] for i in range(n)] for c in curves]).mean(0)
            ax.plot(
                frames, mean, style, color=color, label=f"{label}, {recipe} ({len(curves)} seeds)"
            )
    followers = [r["follower"] for r in results["runs"]]
    if followers:
        ax.axhline(float(np.mean(followers)), color="k", ls="--", lw=1, label="follower (scripted)")
    ax.set_xlabel("frames")
    ax.set_ylabel("greedy team reward")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("multirun/time_to_skill"))
    parser.add_argument("--frames", type=int, default=800_000)
    parser.add_argument("--eval-interval", type=int, default=50_000)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--methods", nargs="+", choices=list(METHODS), default=list(METHODS))
    parser.add_argument("--recipes", nargs="+", choices=list(RECIPES), default=list(RECIPES))
    parser.add_argument(
        "--scale-sweep",
        type=Path,
        default=Path("multirun/four_quadrants_5m"),
        help="the 5M reproduction's sweep folder (its seed 0 and 1 runs)",
    )
    parser.add_argument("--report-only", action="store_true")
    args = parser.parse_args(argv)
    out, scale_sweep = args.out.resolve(), args.scale_sweep.resolve()

    def overrides(method, recipe, seed):
        if recipe == SCALE:  # the 5M reproduction's own command line (its budget and evaluations)
            return [f"method={method}", f"seed={seed}", *RECIPES[recipe]]
        return [
            f"method={method}",
            f"seed={seed}",
            *BUDGET,
            *RECIPES[recipe],
            f"train.total_frames={args.frames}",
            f"train.eval_interval={args.eval_interval}",
        ]

    if not args.report_only:
        train_runs(
            {
                run: (
                    overrides(method, recipe, seed),
                    5_000_000 if recipe == SCALE else args.frames,
                )
                for (method, recipe, seed), run in runs(
                    out, args.methods, scale_sweep, args.recipes
                ).items()
            },
            args.jobs,
        )
    results = report(out, scale_sweep)
    previous = RESULTS / "time_to_skill.json"
    if previous.is_file():  # rows whose runs are not on this machine keep their recorded result
        found = {(r["method"], r["recipe"], r["seed"]) for r in results["runs"]}
        kept = [
            r
            for r in json.loads(previous.read_text()).get("runs", [])
            if (r["method"], r["recipe"], r["seed"]) not in found
        ]
        results["runs"] = kept + results["runs"]
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "time_to_skill.json").write_text(json.dumps(results, indent=1) + "\n")
    plot(results, RESULTS / "time_to_skill.png")
    for r in results["runs"]:
        frames = "never" if r["frames"] is None else f"{r['frames']:,}"
        wall = "" if r["wall_s"] is None else f" ({r['wall_s'] / 60:.1f} min)"
        print(f"{METHODS[r['method']]:<12} {r['recipe']:<13} seed {r['seed']}: {frames}{wall}")


if __name__ == "__main__":
    main()
