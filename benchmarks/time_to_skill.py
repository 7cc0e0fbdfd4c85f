"""Time to skill: wall-clock minutes until a recipe's greedy team reaches 90 % of the best scripted
team in four quadrants, learning and speed judged together.

    python benchmarks/time_to_skill.py                  # train what is missing, score, report
    python benchmarks/time_to_skill.py --recipes "hard target copies" "replay ratio 4"
    python benchmarks/time_to_skill.py --report-only    # the figure from the JSON
    python benchmarks/time_to_skill.py --smoke --seeds 0   # a pipeline check

Each recipe is the base the screen started from, ``make train``'s recipe then
(``experiment=make_train``: ICCO, 2M frames, a hard target copy every 50 updates), with its own
overrides (:data:`RECIPES`); "soft target updates" won and is ``make train``'s now. Trained at
:data:`BUDGET`: the env in the learner's process, one torch
thread, two runs side by side on a 2-core machine (``--jobs``), and ``train.policy_snapshots`` so
that the weights of every evaluation mark (``train.eval_interval``, 100k frames) are kept. A
stopped sitting resumes: finished runs are kept, interrupted ones continue from their checkpoint.

Then, timed apart from training, every snapshot plays the four-quadrant protocol (``icco eval
eval.protocol=quadrants``, its 20 trials, the scripted references on the same episodes,
coordination measures off). A mark's share is the snapshot's mean episode reward over the best
scripted team's; its minutes are the run's own collection and update clock up to that mark
(``timing.csv``: evaluations, process start and compile-cache loading excluded, the first compile
included). ``minutes_to_90_percent`` is the first mark at or above 90 % (null: not within the
budget).

Writes ``benchmarks/results/time_to_skill.json`` (per recipe and seed: the curve, the marks'
shares and minutes, the CPU model and thread count) and ``time_to_skill.png`` (share against
minutes, one line per recipe, the mean of its seeds); ``python benchmarks/report.py`` renders the
table into ``benchmarks/README.md``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import platform
import sys
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from icco_torchrl.evaluation.metrics import EPISODE
from icco_torchrl.training.build import compose_config
from icco_torchrl.training.logger import clock_seconds
from icco_torchrl.training.run_folder import SNAPSHOTS

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))
import jobs  # noqa: E402  (experiments/jobs.py, the one job runner)
import verdict  # noqa: E402  (experiments/verdict.py: means over trials)

# the language protocol under served plans
serving = jobs.script(ROOT / "experiments" / "language" / "serving" / "run.py", "serving_run")

RESULTS = ROOT / "benchmarks" / "results"
BUDGET = [
    "experiment=make_train",
    "train.target_update=hard",  # the base every recipe is one lever on (make train's until it won)
    "train.collector=inline",
    "train.threads=1",
    "train.checkpoint_buffer=false",
]
# Always: the method, the snapshots the scores are read from, no progress bar in the job logs.
FIXED = ["method=icco", "train.policy_snapshots=true", "logger.progress=false"]
# make train's batch: 32 envs x 16 steps = 512 frames, 8 updates of 32 sequences x 16 steps = 8
# replayed transitions per collected one. Each recipe changes what its name says.
RECIPES = {
    "hard target copies": [],  # make train's recipe before this screen
    "fewer, larger updates": ["train.updates_per_batch=2", "train.batch_segments=128"],
    "replay ratio 4": ["train.updates_per_batch=4"],
    "replay ratio 2": ["train.updates_per_batch=2"],
    "64 envs per batch": ["env.num_envs=64", "train.batch_segments=64"],
    "lr 3e-3, target every 100": ["train.lr=3e-3", "train.target_update_interval=100"],
    "epsilon over 150k frames": ["train.eps_decay_frames=150000"],
    # make train's policy swings by up to 15 points between marks 100k frames apart: a target
    # that follows slowly (Polyak 0.005, a 200-update horizon) in place of a copy every 50.
    "soft target updates": ["train.target_update=soft"],  # make train's now (tau 0.005)
}
# The levers again on the winner's base: whether one of them makes make train faster still.
SOFT = RECIPES["soft target updates"]
RECIPES |= {
    "soft, replay ratio 4": [*SOFT, *RECIPES["replay ratio 4"]],
    "soft, 64 envs per batch": [*SOFT, *RECIPES["64 envs per batch"]],
    "soft, epsilon over 150k frames": [*SOFT, *RECIPES["epsilon over 150k frames"]],
}
SEEDS = (0, 1)
INTERFACE = f"served@{serving.DEFAULT_STEP:g}"  # plans as icco live serves them
TARGET = 0.9  # share of the best scripted team
TRIALS = 20  # the four-quadrant protocol's trials per snapshot


def folder(out: Path, recipe: str, seed: int) -> Path:
    slug = "".join(c if c.isalnum() else "_" for c in recipe).strip("_")
    return out / f"{slug}_seed{seed}"


# ---------------------------------------------------------------------------- scoring
def _episode_means(trials: Path) -> tuple[dict[str, float], float | None]:
    """From an ``icco eval`` trials file: each checkpoint's mean episode reward, and the best
    scripted team's on the same episodes."""
    rows = verdict.read_rows(trials)
    by_checkpoint: dict[str, list[dict]] = {}
    for row in rows:
        if row["checkpoint"]:
            by_checkpoint.setdefault(row["checkpoint"], []).append(row)
    means = {k: verdict.episode_mean(v) for k, v in by_checkpoint.items()}
    best = verdict.best_scripted(rows)
    kept = {k: m.mean for k, m in means.items() if m is not None}
    return kept, None if best is None else best.mean


def score(run: Path, trials: int = TRIALS) -> Path:
    """Four quadrants for every snapshot of ``run`` (one ``icco eval`` call, so the references
    play once), into ``run/time_to_skill/``; kept while no snapshot is newer."""
    snapshots = sorted((run / SNAPSHOTS).glob("*.pt"))
    if not snapshots:
        raise SystemExit(f"{run}: no policy snapshots (train it with train.policy_snapshots=true)")
    out = run / "time_to_skill"
    scored = out / "quadrants_trials.csv"
    if scored.is_file() and scored.stat().st_mtime > max(p.stat().st_mtime for p in snapshots):
        means, _ = _episode_means(scored)
        if set(means) == {str(p) for p in snapshots}:
            return scored
    return jobs.score_quadrants(snapshots, out, trials)


def language(run: Path) -> dict:
    """The run's last snapshot under the language protocol with plans served (the serving page's
    ``play``: its instructions, trials and env seed): in place per instruction and the episode's
    team reward."""
    last = sorted((run / SNAPSHOTS).glob("*.pt"))[-1]
    return _language_row(serving.play("policy", last, INTERFACE, serving.TRIALS))


def _language_row(played: dict) -> dict:
    return {
        "in_place": {i: played[i]["in_place"] for i in serving.INSTRUCTIONS},
        "reward": played[EPISODE]["reward"],
    }


def minutes_at(run: Path) -> dict[int, float]:
    """The run's collection and update clock (minutes) at each ``timing.csv`` row's frames."""
    with (run / "timing.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    return {
        int(r["frames"]): (clock_seconds(r) - float(r.get("time_eval") or 0)) / 60 for r in rows
    }


def curve(run: Path, scored: Path) -> dict:
    """The run's marks: frames, minutes of training, reward and share of the best scripted
    team's; and the first mark at :data:`TARGET`."""
    means, best = _episode_means(scored)
    clock = minutes_at(run)
    marks = []
    for path, reward in sorted(means.items(), key=lambda kv: int(Path(kv[0]).stem)):
        frames = int(Path(path).stem)
        at = min((f for f in clock if f >= frames), default=None)
        share = reward / best if best and best > 0 else math.nan
        marks.append({"frames": frames, "minutes": clock.get(at), "reward": reward, "share": share})
    first = next((m for m in marks if m["share"] >= TARGET), None)
    return {
        "best_scripted": best,
        "marks": marks,
        "final_share": marks[-1]["share"] if marks else None,
        "minutes_to_90_percent": None if first is None else first["minutes"],
        "frames_to_90_percent": None if first is None else first["frames"],
    }


def merged(previous: dict, rows: list[dict]) -> list[dict]:
    """``previous``'s runs, less those ``rows`` measure again (the same recipe, seed and CPU),
    then ``rows``: a run on another CPU is another measurement and stays. A file from before
    rows named their CPU names it once, at the top."""
    key = lambda r: (r["recipe"], r["seed"], r["cpu"])  # noqa: E731
    fresh = {key(r) for r in rows}
    old = [{"cpu": previous.get("cpu"), **r} for r in previous.get("runs", [])]
    return [r for r in old if key(r) not in fresh] + rows


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


# ---------------------------------------------------------------------------- report
def plot(results: dict, path: Path) -> None:
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    cpus = sorted({r["cpu"] for r in results["runs"]})
    for recipe in RECIPES:
        for cpu, style in zip(cpus, ("-", "--", ":")):  # minutes compare within one CPU only
            runs = [r for r in results["runs"] if (r["recipe"], r["cpu"]) == (recipe, cpu)]
            runs = [r for r in runs if r["marks"]]
            if not runs:
                continue
            n = min(len(r["marks"]) for r in runs)
            minutes = np.mean([[m["minutes"] for m in r["marks"][:n]] for r in runs], axis=0)
            share = np.mean([[m["share"] for m in r["marks"][:n]] for r in runs], axis=0)
            label = f"{recipe}, {cpu.split(' Processor')[0]} ({len(runs)} seeds)"
            ax.plot(minutes, 100 * share, style, marker=".", label=label)
    ax.axhline(100 * TARGET, color="k", ls="--", lw=1, label="90 % of the best scripted team")
    ax.set_xlabel("minutes of training (one core; evaluations excluded)")
    ax.set_ylabel("four quadrants: % of the best scripted team")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--out", type=Path, help="runs folder (default multirun/time_to_skill[_smoke])"
    )
    parser.add_argument("--recipes", nargs="+", choices=list(RECIPES), default=list(RECIPES))
    parser.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    parser.add_argument("--jobs", type=int, default=2, help="runs side by side (one core each)")
    parser.add_argument("--trials", type=int, default=TRIALS)
    parser.add_argument("--budget", nargs="*", help="training overrides instead of BUDGET")
    parser.add_argument(
        "--smoke", action="store_true", help="seconds-long runs and 2 trials: a pipeline check"
    )
    parser.add_argument(
        "--results",
        type=Path,
        help="default benchmarks/results/time_to_skill.json (--smoke: --out)",
    )
    parser.add_argument(
        "--host",
        help="a label added to the CPU model: one model name can run at different speeds on two "
        "hosts, and minutes compare only within one host",
    )
    parser.add_argument("--report-only", action="store_true", help="the figure from --results")
    parser.add_argument(
        "--no-language",
        action="store_true",
        help="skip the language protocol of each run's last snapshot (and the follower's)",
    )
    args = parser.parse_args(argv)
    out = (args.out or Path("multirun/time_to_skill" + "_smoke" * args.smoke)).resolve()
    budget = [*FIXED, *jobs.budget(args.smoke, args.budget, BUDGET)]
    trials = 2 if args.smoke else args.trials
    default = out / "time_to_skill.json" if args.smoke else RESULTS / "time_to_skill.json"
    args.results = args.results or default
    wanted = {
        (recipe, seed): folder(out, recipe, seed) for recipe in args.recipes for seed in args.seeds
    }
    if not args.report_only:
        runs = {}
        for (recipe, seed), run in wanted.items():
            overrides = [*budget, *RECIPES[recipe], f"seed={seed}"]
            runs[run] = (overrides, compose_config(overrides).train.total_frames)
        jobs.train_runs(runs, args.jobs)
        previous = json.loads(args.results.read_text()) if args.results.is_file() else {}
        cpu = cpu_model() + (f" ({args.host})" if args.host else "")
        rows = []
        for (recipe, seed), run in wanted.items():
            row = {"recipe": recipe, "seed": seed, "overrides": RECIPES[recipe], "cpu": cpu}
            row.update(curve(run, score(run, trials)))
            if not args.no_language:
                row["language"] = language(run)
            rows.append(row)
        # Minutes are comparable only between rows of one CPU model: each row names its own.
        results = {
            "budget": budget,
            "target": TARGET,
            "trials": trials,
            "threads": 1,
            "side_by_side": args.jobs,
            "runs": merged(previous, rows),
        }
        if not args.no_language:  # the yardstick: the scripted follower on the same episodes
            first = sorted((next(iter(wanted.values())) / SNAPSHOTS).glob("*.pt"))[-1]
            follower = serving.play("follower", first, INTERFACE, serving.TRIALS)
            results["language_follower"] = _language_row(follower)
        elif "language_follower" in previous:
            results["language_follower"] = previous["language_follower"]
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text(json.dumps(results, indent=1) + "\n")
    results = json.loads(args.results.read_text())
    plot(results, args.results.with_suffix(".png"))
    for r in results["runs"]:
        m = r["minutes_to_90_percent"]
        reached = "not reached" if m is None else f"{m:.1f} min ({r['frames_to_90_percent']:,})"
        print(f"{r['recipe']:<28} seed {r['seed']}: 90 % {reached}; final {r['final_share']:.0%}")


if __name__ == "__main__":
    main()
