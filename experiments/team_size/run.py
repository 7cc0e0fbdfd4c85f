"""Team-size experiment (issue 26, COPA's dynamic teams): train on 2-4 robots, run 1-6 zero-shot,
and sweep the coordinator's broadcast threshold beta.

    python experiments/team_size/run.py                          # experiment=repro_cpu, 3 seeds
    python experiments/team_size/run.py --budget experiment=paper device=cuda
    python experiments/team_size/run.py --smoke                  # minutes: a pipeline check

1. Training: ICCO and QMIX (FULL) with the networks that read any team (``method.mixer=attention
   method.posterior_input=tokens``), each on 2-4 robots (``env.params.n_agents=4
   train.team_sizes=[2,3,4]``, a team drawn per env at every reset) and on 3 robots only, one
   ``icco train`` per run into ``--sweep`` (``<method>_<group>_seed<seed>``), seed by seed,
   ``--jobs`` (2) side by side. Run the script again after an interruption: finished runs are
   kept, interrupted ones continue from their checkpoint (``experiments/jobs.py``).
2. Team sizes: ``icco eval eval.protocol=quadrants eval.team_size=K`` for K in ``--team-sizes``
   (1-6) on each group's checkpoints (seeds pooled per method) into ``<sweep>/eval_<group>_n<K>``,
   the scripted references (follower, heuristic, blend) beside the 2-4 group on the same episodes.
3. Beta sweep: ICCO (2-4) at ``--beta-team-size`` (3) robots with ``eval.broadcast_threshold=b``
   for b in ``--betas`` (no retraining) into ``<sweep>/eval_beta<b>``.
4. ``results.json`` (the budget's frames, the commands, the machine) in ``--out`` (default: this
   folder; with ``--smoke``: ``<sweep>/report``, never this folder), then ``report.py`` renders
   the README and figures there.

``--beta-screen CHECKPOINT... --beta-label LABEL`` runs step 3 alone on other ICCO checkpoints
(no training, no team sizes) into ``beta_screen.json`` in ``--out``: a first read of the
broadcast target from policies trained elsewhere, rendered in its own section.

``--train-beta B`` trains ICCO (2-4) with the threshold itself (``method.broadcast_threshold=B``,
so the agents learn with the z they would hold) at ``--seeds`` into
``<sweep>/icco_mixed_beta<B>_seed<seed>``, then runs step 3 alone on those checkpoints into
``beta_trained.json``, rendered in its own section beside the beta = 0 policy's sweep.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

from omegaconf import OmegaConf

from icco_torchrl import methods
from icco_torchrl.evaluation.metrics import write_json
from icco_torchrl.training.build import compose_config

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE.parent))
import jobs  # noqa: E402  (experiments/jobs.py, a sibling script)
from jobs import train_runs  # noqa: E402

FOUR_QUADRANTS = jobs.script(HERE.parent / "four_quadrants" / "run.py", "four_quadrants_run")
icco, machine = FOUR_QUADRANTS.icco, FOUR_QUADRANTS.machine

METHODS = ("icco", "qmix_full")
SEEDS = (0, 1, 2)
# The networks whose every shape is independent of the team size (docs/method.md).
ANY_TEAM = ("method.mixer=attention", "method.posterior_input=tokens")
# Training groups: what each trains on, and its label suffix in tables and figures.
GROUPS = {
    "mixed": dict(
        overrides=("env.params.n_agents=4", "train.team_sizes=[2,3,4]"), sizes=[2, 3, 4], tag="2-4"
    ),
    "fixed3": dict(overrides=("env.params.n_agents=3",), sizes=[3], tag="3"),
}
REFERENCES = ("follower", "heuristic", "blend")
TEAM_SIZES = (1, 2, 3, 4, 5, 6)
BETAS = (0.0, 0.25, 0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0)  # down to COPA's 13 % and below


def repo_relative(text: str) -> str:
    """``text`` (a path or a command) with this checkout's location dropped: what results.json
    records reads from the repository root on any machine."""
    return text.replace(f"{ROOT}{os.sep}", "")


def run_overrides(method: str, group: str, seed: int, budget, beta: float = 0.0) -> list[str]:
    """The ``icco train`` overrides of one run (``beta``: trained with that broadcast threshold)."""
    trained_beta = [f"method.broadcast_threshold={beta:g}"] if beta else []
    return [
        f"method={method}",
        f"seed={seed}",
        *ANY_TEAM,
        *GROUPS[group]["overrides"],
        *trained_beta,
        *budget,
    ]


def run_dir(sweep: Path, method: str, group: str, seed: int, beta: float = 0.0) -> Path:
    return sweep / f"{method}_{group}{f'_beta{beta:g}' * bool(beta)}_seed{seed}"


def train(sweep: Path, seeds, budget, jobs: int = 2) -> int:
    """Bring every ``method x group x seed`` run to its budget; returns ``train.total_frames``."""
    runs = {}
    for s in seeds:  # seed by seed: a sweep cut short has every run at the same seeds
        for group in GROUPS:
            for m in METHODS:
                overrides = run_overrides(m, group, s, budget)
                total = compose_config(overrides).train.total_frames
                runs[run_dir(sweep, m, group, s)] = (overrides, total)
    train_runs(runs, jobs)
    return total


def evaluate(sweep: Path, name: str, checkpoints, *overrides: str, commands: list) -> dict:
    """One ``icco eval`` (quadrants) into ``<sweep>/<name>``; returns its JSON.

    An evaluation already in that folder is kept when it ran with the same overrides (Hydra's
    ``.hydra/overrides.yaml``) after every checkpoint was last written, so a rerun (more
    ``--betas``, an interrupted evaluation) evaluates only what is new.
    """
    out = sweep / name
    args = [
        "eval",
        f"eval.checkpoints=[{','.join(map(str, checkpoints))}]",
        "eval.protocol=quadrants",
        *overrides,
        f"eval.out_dir={out}",
        f"hydra.run.dir={out}",
    ]
    commands.append(repo_relative("icco " + " ".join(args)))
    if not is_current(out, args[1:-1], checkpoints):
        icco(*args)
    else:
        print(f"kept {out} (same overrides, newer than its checkpoints)", flush=True)
    return json.loads((out / "quadrants.json").read_text())


def is_current(out: Path, overrides: list[str], checkpoints) -> bool:
    """Whether ``out`` holds an evaluation run with ``overrides`` after ``checkpoints``."""
    result, recorded = out / "quadrants.json", out / ".hydra" / "overrides.yaml"
    if not (result.is_file() and recorded.is_file()):
        return False
    if OmegaConf.to_container(OmegaConf.load(recorded)) != list(overrides):
        return False
    return all(result.stat().st_mtime > Path(c).stat().st_mtime for c in checkpoints)


def episode_rows(payload: dict) -> dict[str, dict]:
    """``{table label: whole-episode summary row}`` of an eval JSON (null back to NaN)."""
    return {
        r["method"]: {k: (math.nan if v is None else v) for k, v in r.items()}
        for r in payload["summary"]
        if r["segment"] == "episode"
    }


def point(row: dict, team: int, **labels) -> dict:
    """A results.json entry: team reward, reward per robot, broadcast rate (mean and std), and
    the share of steps spent in the instructed quadrant."""
    return dict(
        **labels,
        team_size=team,
        trials=row["n"],
        seeds=row["seeds"],
        reward=row["reward"],
        reward_std=row["reward_std"],
        reward_per_robot=row["reward"] / team,
        reward_per_robot_std=row["reward_std"] / team,
        broadcast_rate=row["broadcast_rate"],
        broadcast_rate_std=row["broadcast_rate_std"],
        in_quadrant=row["in_quadrant"],
    )


def beta_sweep(
    sweep: Path, checkpoints, betas, team: int, label: str, quick, commands, prefix: str = "eval"
) -> list:
    """ICCO ``checkpoints`` (seeds pooled) at ``team`` robots with ``eval.broadcast_threshold=b``
    for each b into ``<sweep>/<prefix>_beta<b>``: one results.json point per beta, labelled
    ``label``."""
    points = []
    for beta in betas:
        payload = evaluate(
            sweep,
            f"{prefix}_beta{beta:g}",
            checkpoints,
            *quick,
            f"eval.team_size={team}",
            f"eval.broadcast_threshold={beta}",
            "eval.references=[]",
            commands=commands,
        )
        row = episode_rows(payload)[methods.label("icco")]
        points.append(point(row, team, method=label, beta=beta))
    return points


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sweep", type=Path, help="default multirun/team_size[_smoke]")
    parser.add_argument(
        "--budget",
        nargs="*",
        help="training overrides (default experiment=repro_cpu); with --smoke, added to the "
        "smoke budget",
    )
    parser.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    parser.add_argument("--team-sizes", nargs="+", type=int, default=list(TEAM_SIZES))
    parser.add_argument("--betas", nargs="+", type=float, default=list(BETAS))
    parser.add_argument("--beta-team-size", type=int, default=3)
    parser.add_argument("--trials", type=jobs.positive, default=20, help="trials per checkpoint")
    parser.add_argument("--steps", type=jobs.positive, default=145, help="steps per quadrant")
    parser.add_argument(
        "--smoke", action="store_true", help="tiny budget, 2 trials, 10 steps: a pipeline check"
    )
    parser.add_argument("--jobs", type=jobs.positive, default=2, help="training runs side by side")
    parser.add_argument("--out", type=Path, help="results.json, README.md and figures/")
    parser.add_argument(
        "--beta-screen", nargs="+", type=Path, help="ICCO checkpoints: run only the beta sweep"
    )
    parser.add_argument("--beta-label", default="ICCO", help="their label in the screen")
    parser.add_argument(
        "--train-beta",
        type=float,
        help="train ICCO (2-4) with this broadcast threshold, then run only the beta sweep on it",
    )
    args = parser.parse_args(argv)
    if any(k < 1 for k in [*args.team_sizes, args.beta_team_size]):
        parser.error("team sizes must be >= 1")
    if any(b < 0 for b in args.betas):
        parser.error("--betas must be >= 0")
    if args.train_beta is not None and not args.train_beta > 0:
        parser.error("--train-beta must be > 0 (beta = 0 is the experiment's own ICCO (2-4))")
    budget = jobs.budget(args.smoke, args.budget, ["experiment=repro_cpu"])
    trials, steps = (2, 10) if args.smoke else (args.trials, args.steps)
    sweep = (args.sweep or Path("multirun/team_size" + "_smoke" * args.smoke)).resolve()
    out = args.out or (sweep / "report" if args.smoke else HERE)
    sweep.mkdir(parents=True, exist_ok=True)
    quick = [f"eval.trials={trials}", f"eval.steps={steps}"]
    if args.beta_screen:
        missing = [str(p) for p in args.beta_screen if not p.is_file()]
        if missing:
            raise SystemExit(f"--beta-screen: no checkpoint at {', '.join(missing)}")
        screen(args, sweep, out / "beta_screen.json", args.beta_screen, args.beta_label, quick)
        return
    if args.train_beta is not None:
        trained_beta(args, sweep, out, budget, quick)
        return

    start = time.time()
    frames = train(sweep, args.seeds, budget, args.jobs)
    train_wall = time.time() - start
    checkpoints = {
        (m, g): [
            p for s in args.seeds if (p := run_dir(sweep, m, g, s) / "checkpoint.pt").is_file()
        ]
        for g in GROUPS
        for m in METHODS
    }
    commands = [
        "icco train " + " ".join(run_overrides(m, g, "S", budget)) + " hydra.run.dir=..."
        for g in GROUPS
        for m in METHODS
    ]
    start = time.time()
    sizes, trained_frames = [], []
    for team in args.team_sizes:
        for group, spec in GROUPS.items():
            paths = [p for m in METHODS for p in checkpoints[(m, group)]]
            refs = list(REFERENCES) if group == "mixed" else []
            payload = evaluate(
                sweep,
                f"eval_{group}_n{team}",
                paths,
                *quick,
                f"eval.team_size={team}",
                f"eval.references=[{','.join(refs)}]",
                commands=commands,
            )
            trained_frames += [c["frames"] for c in payload["checkpoints"]]
            for label, row in episode_rows(payload).items():
                reference = label not in {methods.label(m) for m in METHODS}
                sizes.append(
                    point(
                        row,
                        team,
                        method=label if reference else f"{label} ({spec['tag']})",
                        kind="reference" if reference else "trained",
                        trained_on=None if reference else spec["sizes"],
                    )
                )
    label = f"{methods.label('icco')} (2-4)"
    points = beta_sweep(
        sweep,
        checkpoints[("icco", "mixed")],
        args.betas,
        args.beta_team_size,
        label,
        quick,
        commands,
    )
    eval_wall = time.time() - start

    cfg = compose_config(run_overrides("icco", "mixed", 0, budget))
    results = dict(
        experiment="team_size",
        smoke=args.smoke,
        frames=frames,
        checkpoint_frames=min(trained_frames, default=None),
        budget=budget,
        seeds=args.seeds,
        trials=trials,
        steps=steps,
        episode_steps=4 * steps,
        period=int(cfg.method.period),
        groups={
            g: dict(overrides=list(s["overrides"]), sizes=s["sizes"]) for g, s in GROUPS.items()
        },
        networks=list(ANY_TEAM),
        team_sizes=args.team_sizes,
        sizes=sizes,
        beta_sweep=dict(team_size=args.beta_team_size, policy=label, points=points),
        commands=commands,
        machine=machine(),
        wall_s=dict(train=train_wall, eval=eval_wall),
        sweep=repo_relative(str(sweep)),
    )
    write_json(results, out / "results.json")
    report = jobs.script(HERE / "report.py", "team_size_report")
    report.main([str(out / "results.json"), "--readme", str(out / "README.md")])


def screen(args, sweep: Path, path: Path, checkpoints, label: str, quick, **extra) -> None:
    """The beta sweep alone on ICCO ``checkpoints`` into ``path`` (``beta_screen.json``,
    ``beta_trained.json``), then the README re-rendered."""
    start, commands = time.time(), []
    prefix = "eval" if path.stem == "beta_screen" else f"eval_{path.stem}"
    points = beta_sweep(
        sweep, checkpoints, args.betas, args.beta_team_size, label, quick, commands, prefix
    )
    cfg = compose_config(["method=icco"])
    write_json(
        dict(
            **extra,
            period=int(cfg.method.period),
            checkpoints=[repo_relative(str(Path(p).resolve())) for p in checkpoints],
            eval_overrides=quick,
            episode_steps=4 * (10 if args.smoke else args.steps),
            beta_sweep=dict(team_size=args.beta_team_size, policy=label, points=points),
            commands=commands,
            machine=machine(),
            wall_s=time.time() - start,
        ),
        path,
    )
    report = jobs.script(HERE / "report.py", "team_size_report")
    out = path.parent
    report.main([str(out / "results.json"), "--readme", str(out / "README.md")])


def trained_beta(args, sweep: Path, out: Path, budget, quick) -> None:
    """``--train-beta B``: ICCO (2-4) trained with the threshold B at ``--seeds``, then the beta
    sweep on those checkpoints into ``beta_trained.json``."""
    beta = args.train_beta
    runs = {}
    for s in args.seeds:
        overrides = run_overrides("icco", "mixed", s, budget, beta)
        runs[run_dir(sweep, "icco", "mixed", s, beta)] = (
            overrides,
            compose_config(overrides).train.total_frames,
        )
    start = time.time()
    train_runs(runs, args.jobs)
    train_wall = time.time() - start
    checkpoints = [run / "checkpoint.pt" for run in runs]
    label = f"{methods.label('icco')} (2-4, trained at beta = {beta:g})"
    overrides = " ".join(run_overrides("icco", "mixed", "S", budget, beta))
    screen(
        args,
        sweep,
        out / "beta_trained.json",
        checkpoints,
        label,
        quick,
        train_beta=beta,
        seeds=args.seeds,
        frames=min(load_frames(c) for c in checkpoints),
        train_command=f"icco train {overrides} hydra.run.dir=...",
        train_wall_s=train_wall,
    )


def load_frames(checkpoint: Path) -> int:
    return int(jobs.load_checkpoint(checkpoint).get("frames", 0))


if __name__ == "__main__":
    main()
