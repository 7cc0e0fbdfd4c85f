"""Language-instruction experiments (paper Sec. V-C/V-D: Fig. 5b, Fig. 6, Table II).

    python experiments/language/run.py               # offline rule planner, default budget
    python experiments/language/run.py --llm openai  # GPT-4o via litellm, as the paper
    python experiments/language/run.py --smoke       # seconds-long end-to-end check

``--llm openai`` reads the key from ``OPENAI_API_KEY``.

1. Agents: ICCO, QMIX and QMIX (FULL) from the four-quadrant sweep (``--sweep``; trained there
   if missing, resumable), and QMIX trained on the instruction reward alone (QMIX-TAP w/o TR:
   every task reward zeroed, as ``experiment=inst_only`` does for the default budget) in
   ``--wo-tr-sweep``.
2. Fig. 5b/6: "Go right" -> "Move top" -> "Gather center" -> "Spread out", 145 steps each, the
   planner prompted once per instruction with the paper's prompt, ICCO vs QMIX (FULL) (and the
   paper's flat QMIX (FULL)), 20 trials per checkpoint, the scripted teams (the perfect path
   follower ``pursuit`` among them) on the same episodes: ``icco instruct`` into ``<out>/fig5b``.
3. Table II: the same instructions with the task-aligned prompt driving QMIX (QMIX-TAP) and the
   instruction-reward-only QMIX (QMIX-TAP w/o TR) into ``<out>/table2_tap``; ICCO's row is its
   Fig. 5b run (ICCO gets the paper's plain prompt: its coordinator does the task alignment).
   Counts are per 145-step instruction segment.
4. ``report.py <out>`` fills ``README.md`` here.

``--methods`` narrows the agents: without ``qmix`` there is no Table II run (its QMIX-TAP rows are
then reported missing), so ``--methods icco qmix_full`` evaluates Fig. 5b on a sweep that holds only
those two, as the 5M reproduction does:

    python experiments/language/run.py --budget experiment=repro_5m --methods icco qmix_full \
        --sweep multirun/four_quadrants_5m --out multirun/language_5m \
        --readme experiments/language/5m/README.md

and ``--methods qmix`` runs Table II alone, its rows added to a page that has Fig. 5b and ICCO's
row (``report.py --table2``).

Kept policies replay any protocol without retraining. With ``--records DIR`` the four-quadrant
agents are the policies kept there (``DIR/<method>_seed<s>/policy.pt``, as the four-quadrant
script files them); a missing one is named with the command that trains and files it. With
``--wo-tr-records DIR`` the QMIX-TAP w/o TR agents are read there too, and those missing are
trained in ``--wo-tr-sweep`` and filed there (``jobs.keep_run``: no optimizer, no replay):

    python experiments/language/run.py --budget experiment=repro_5m \
        --records experiments/four_quadrants/5m/records \
        --wo-tr-records experiments/language/5m/records_wo_tr --out multirun/language_5m \
        --readme experiments/language/5m/README.md

``--kept-only`` replays what is kept and trains nothing: each method at the seeds kept (each
row of the page says its trials and seeds), a method with none reported missing, and Table II
only when QMIX-TAP w/o TR has a kept policy. Seeds retrained sitting by sitting show up as they
are filed.

The commands below train in sweeps (the checkpoints stay on the machine):

    python experiments/language/run.py --budget experiment=repro_5m --methods qmix \
        --sweep multirun/four_quadrants_5m --wo-tr-sweep multirun/inst_only_5m \
        --out multirun/language_5m_tap --readme experiments/language/5m/README.md
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from icco_torchrl.envs.reference_policies import EVAL_REFERENCES

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
import jobs  # noqa: E402  (experiments/jobs.py, the one job runner)

INSTRUCTIONS = ("Go right", "Move top", "Gather center", "Spread out")
# The four-quadrant agents this experiment reads: Fig. 5b compares ICCO with QMIX (FULL) (and the
# paper's flat QMIX (FULL)), Table II drives QMIX.
AGENTS = ("icco", "qmix", "qmix_full", "qmix_full_flat")
FIG5B = ("icco", "qmix_full", "qmix_full_flat")
# Fig. 5b's scripted rows: the evaluation's own, the perfect path follower, and the scripted team
# of highest reward that is in place on every instruction (experiments/language/frontier, once
# searched): what being in place earns in this reward (report.following_costs).
FRONTIER = HERE / "frontier" / "results.json"
IN_PLACE = json.loads(FRONTIER.read_text())["best_in_place"] if FRONTIER.is_file() else None
REFERENCES = (*EVAL_REFERENCES, "pursuit", *([IN_PLACE] if IN_PLACE else []))
NO_TASK_REWARD = (
    "env.params.pick_reward=0",
    "env.params.collect_reward=0",
    "env.params.defense_reward=0",
    "env.params.invasion_penalty=0",
    "train.shaping.potentials=[]",  # no task shaping either (as experiment=inst_only)
)


def references_override() -> str:
    """Fig. 5b's scripted rows as a Hydra override (each name quoted: a blend's has commas)."""
    return "eval.references=[" + ",".join(f'"{r}"' for r in REFERENCES) + "]"


def run(*command: str) -> None:
    print("$ " + " ".join(command), flush=True)
    subprocess.run(list(command), check=True)


def train(sweep: Path, methods, seeds, budget, smoke: bool, jobs: int = 2) -> None:
    """Resumable training through the four-quadrant script (one code path for every sweep),
    ``jobs`` runs side by side."""
    run(
        sys.executable,
        str(HERE.parent / "four_quadrants" / "run.py"),
        "--train-only",
        "--jobs",
        str(jobs),
        "--sweep",
        str(sweep),
        "--methods",
        *methods,
        "--seeds",
        *map(str, seeds),
        *(["--smoke"] if smoke else []),
        *(["--budget", *budget] if budget else []),
    )


def checkpoints(sweep: Path, method: str, seeds) -> list[str]:
    """The checkpoints of ``method``'s runs at ``seeds`` (other seeds in the sweep, finished or
    still training, are not this experiment's)."""
    found = [sweep / f"{method}_seed{s}" / "checkpoint.pt" for s in seeds]
    missing = [str(p) for p in found if not p.is_file()]
    if missing:
        raise SystemExit(f"no checkpoint {', '.join(missing)}: training failed?")
    return [str(p) for p in found]


def kept(records: Path, method: str, seeds, some: bool = False) -> list[str] | None:
    """``method``'s policies at ``seeds`` kept in ``records``; None when one is missing (with
    ``some``: those kept, None when there are none)."""
    found = [records / f"{method}_seed{s}" / jobs.POLICY for s in seeds]
    there = [str(p) for p in found if p.is_file()]
    return there if there and (some or len(there) == len(found)) else None


def from_records(records: Path, methods, seeds, budget, some=False) -> dict[str, list[str]]:
    """The four-quadrant agents from their kept policies, or one line naming what trains them.
    ``some`` (``--kept-only``): each method at the seeds kept, a method with none left out."""
    agents = {m: kept(records, m, seeds, some) for m in methods}
    missing = [m for m, paths in agents.items() if paths is None]
    if some and len(missing) < len(agents):
        return {m: paths for m, paths in agents.items() if paths is not None}
    if missing:
        raise SystemExit(
            f"no kept policy for {', '.join(missing)} at seeds {list(seeds)} in {records}: "
            f"python experiments/four_quadrants/run.py --methods {' '.join(missing)} --seeds "
            f"{' '.join(map(str, seeds))} --records {records} --budget {' '.join(budget or [])}"
        )
    return agents


def instruct(out: Path, paths, trials: int, steps: int, llm: str, extra=()) -> None:
    run(
        sys.executable,
        "-m",
        "icco_torchrl",
        "instruct",
        "; ".join(INSTRUCTIONS),
        f"eval.checkpoints=[{','.join(paths)}]",
        f"eval.trials={trials}",
        f"eval.steps={steps}",
        f"llm={llm}",
        *extra,
        f"eval.out_dir={out}",
        f"hydra.run.dir={out}",
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--sweep", type=Path, help="four-quadrant sweep (default multirun/four_quadrants[_smoke])"
    )
    parser.add_argument(
        "--wo-tr-sweep",
        type=Path,
        help="QMIX w/o task reward sweep (default multirun/inst_only[_smoke])",
    )
    parser.add_argument(
        "--out", type=Path, help="results folder (default multirun/language[_smoke])"
    )
    parser.add_argument(
        "--records", type=Path, help="the four-quadrant agents' kept policies (see above)"
    )
    parser.add_argument(
        "--wo-tr-records", type=Path, help="QMIX-TAP w/o TR's kept policies (see above)"
    )
    parser.add_argument(
        "--budget", nargs="*", help="training overrides (see four_quadrants/run.py)"
    )
    parser.add_argument(
        "--kept-only",
        action="store_true",
        help="with --records: each method at the seeds kept there, nothing trained (a page's "
        "rows say their seeds; a method or Table II with none is reported missing)",
    )
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument(
        "--methods",
        nargs="+",
        choices=AGENTS,
        help="four-quadrant agents to train and evaluate (default: all; Table II needs qmix)",
    )
    parser.add_argument(
        "--llm", default="offline", help="conf/llm group: offline | openai | ollama"
    )
    parser.add_argument(
        "--trials", type=jobs.positive, default=20, help="trials per checkpoint (paper: 20)"
    )
    parser.add_argument(
        "--steps", type=jobs.positive, default=145, help="steps per instruction (paper: 145)"
    )
    parser.add_argument(
        "--plan",
        choices=("served", "fixed"),
        default="served",
        help="how each plan reaches the robots (eval.plan; fixed: the old interface, a comparison)",
    )
    parser.add_argument(
        "--smoke", action="store_true", help="tiny budget, 4 trials, 20 steps: a pipeline check"
    )
    parser.add_argument(
        "--jobs", type=jobs.positive, default=2, help="training runs side by side (one core each)"
    )
    parser.add_argument(
        "--readme", type=Path, default=HERE / "README.md", help="where report.py writes"
    )
    args = parser.parse_args(argv)
    tag = "_smoke" * args.smoke
    sweep = (args.sweep or Path(f"multirun/four_quadrants{tag}")).resolve()
    wo_tr = (args.wo_tr_sweep or Path(f"multirun/inst_only{tag}")).resolve()
    out = (args.out or Path(f"multirun/language{tag}")).resolve()
    trials, steps = (4, 20) if args.smoke else (args.trials, args.steps)

    agents = args.methods or list(AGENTS)
    if args.kept_only and not args.records:
        raise SystemExit("--kept-only replays kept policies: give --records DIR")
    if args.records:
        policies = from_records(args.records, agents, args.seeds, args.budget, args.kept_only)
        agents = list(policies)
    else:
        train(sweep, agents, args.seeds, args.budget, args.smoke, args.jobs)
        policies = {m: checkpoints(sweep, m, args.seeds) for m in agents}
    table2 = "qmix" in agents
    wo_tr_policies = None
    if table2 and args.wo_tr_records:
        wo_tr_policies = kept(args.wo_tr_records, "qmix", args.seeds, args.kept_only)
    if table2 and wo_tr_policies is None and args.kept_only:
        table2 = False  # nothing trained behind the user's back: Table II is reported missing
    if table2 and wo_tr_policies is None:
        train(
            wo_tr,
            ["qmix"],
            args.seeds,
            [*(args.budget or ([] if args.smoke else ["experiment=default"])), *NO_TASK_REWARD],
            args.smoke,
            args.jobs,
        )
        wo_tr_policies = checkpoints(wo_tr, "qmix", args.seeds)
        if args.wo_tr_records:
            for path in wo_tr_policies:
                jobs.keep_run(Path(path).parent, args.wo_tr_records / Path(path).parent.name)
            wo_tr_policies = kept(args.wo_tr_records, "qmix", args.seeds)
    plan = [f"eval.plan={args.plan}"]
    fig5b = [m for m in FIG5B if m in agents]
    if fig5b:
        instruct(
            out / "fig5b",
            [path for m in fig5b for path in policies[m]],
            trials,
            steps,
            args.llm,
            [*plan, references_override()],
        )
    if table2:
        instruct(
            out / "table2_tap",
            policies["qmix"] + wo_tr_policies,
            trials,
            steps,
            args.llm,
            ["llm.prompt=tap", *plan],
        )
    # What the report cannot read from the checkpoints: the command line that reproduces this
    # folder (agents and folders only where they were given).
    given = {
        "methods": args.methods,
        "sweep": args.sweep,
        "wo_tr_sweep": args.wo_tr_sweep,
        "records": args.records,
        "wo_tr_records": args.wo_tr_records,
        "out": args.out,
    }
    # The folder's own remark on its agents ("note", written by hand), kept across runs.
    previous = json.loads((out / "run.json").read_text()) if (out / "run.json").is_file() else {}
    (out / "run.json").write_text(
        json.dumps(
            {
                **({"note": previous["note"]} if previous.get("note") else {}),
                "budget": args.budget or [],
                "seeds": args.seeds,
                "llm": args.llm,
                **({"kept_only": True} if args.kept_only else {}),
                **{k: v if k == "methods" else os.path.relpath(v) for k, v in given.items() if v},
            }
        )
    )
    # Without a Fig. 5b agent the folder holds Table II's runs alone: they join a page that has
    # Fig. 5b (``--readme``), beside its ICCO row.
    report = [str(out)] if fig5b else ["--table2", str(out)]
    run(sys.executable, str(HERE / "report.py"), *report, "--readme", str(args.readme))


if __name__ == "__main__":
    main()
