"""Training for served plans: routes to a slot, holding it, and a reward that sees speed.

    python experiments/language/routes/run.py                 # train what is missing, evaluate
    python experiments/language/routes/run.py --only hold_routes --seeds 0
    python experiments/language/routes/run.py --report-only   # README.md from results.json
    python experiments/language/routes/run.py --smoke --seeds 0 --out DIR   # a pipeline check

Under served plans (``experiments/language/serving``) the greedy follower of the paper's
``r_inst`` stalls: the cosine does not see speed, so coasting to a halt along a route scores as
much as driving along it. A learned team has the same incentive, and it never trained on a route
to a slot either. Each screen is ICCO at ``make train``'s recipe on one core (the consistency
screen's ``BUDGET``, 2M frames), 2 seeds, with:

- ``control``: nothing changed. Its runs are the consistency screen's ``ce1e-4`` records (the
  same recipe), so it is not retrained;
- ``hold_routes``: ``env.params.waypoint_route_prob=0.5`` (half the robots get a route to a
  uniform slot per episode, served as evaluation serves a plan) and ``env.params.inst_hold=true``:
  at a route's end (its slot, where the served waypoints coincide) r_inst pays for holding still
  what it paid for following, where otherwise arriving ends the instruction reward;
- ``hold_routes_0.2``: that with routes 0.2, to see whether fewer robots on a route keep the task;
- ``hold_routes_soft``: ``hold_routes`` with soft target updates (``make train``'s recipe since
  the time-to-skill screen), to see whether the recipe that learns the task faster keeps it;
- ``hold_routes_all_soft``: that with every robot on a route (``waypoint_route_prob=1.0``), as
  evaluation serves a slot to every robot: ``hold_routes_soft`` keeps one robot home as a
  goalkeeper under served plans (the one robot a route-free half of training never told to leave).

And at the reproduction's scale (:data:`BUDGET_5M`: ``experiment=repro_5m``, 5M frames, ICCO at
today's consistency default, as the four-quadrant 5M page trains it):

- ``control_5m``: the four-quadrant 5M page's ICCO runs (their kept policies; not retrained);
- ``hold_routes_5m``: ``hold_routes``'s two levers on that recipe, to see whether the 2M
  screen's in-place team keeps the task with the reproduction's budget.

    python experiments/language/routes/run.py --only control_5m hold_routes_5m --seeds 0 1

Measured and not kept (:data:`RETIRED`: their numbers stay in ``results.json``, the option and
its records left the library): ``progress``, r_inst's direction term as a step's length along the
path over the longest step (1 at full speed) instead of its cosine, and ``progress_routes``, that
with routes 0.5. Teams trained on it stopped following.

Every team is evaluated in the paper's env (``inst_hold`` off), so rewards are in one unit
and the scripted teams face the same episodes:

- four quadrants (``icco eval eval.protocol=quadrants``, 20 trials, seeds pooled): the team
  reward and its share of the best scripted team's (the task must not be paid for);
- the language protocol under served plans (``experiments/language/serving``'s ``play``: "Go
  right" -> "Move top" -> "Gather center" -> "Spread out", 145 steps each, 20 trials on env seed
  20000): in place per instruction (at least 2 of 3 robots where the instruction says, over each
  instruction's second half), at slot, formation, time to slot and the episode reward, with the
  scripted follower (greedy on r_inst), the pursuit follower and the best scripted team.

Records (``records/<screen>/seed<k>/``): ``config.yaml``, ``eval.csv``, ``timing.csv`` and the
policy weights (``policy.pt``), so any protocol can be rerun without retraining. ``results.json``
and ``README.md`` here are written from the evaluations.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from icco_torchrl.evaluation.metrics import EPISODE, write_json
from icco_torchrl.training.build import compose_config

HERE = Path(__file__).resolve().parent
EXPERIMENTS = HERE.parents[1]
sys.path.insert(0, str(EXPERIMENTS))
import jobs  # noqa: E402  (experiments/jobs.py, the one job runner)
import verdict  # noqa: E402  (experiments/verdict.py: means over trials)

consistency = jobs.script(EXPERIMENTS / "consistency" / "run.py", "consistency_run")
serving = jobs.script(EXPERIMENTS / "language" / "serving" / "run.py", "serving_run")
go_right = jobs.script(EXPERIMENTS.parent / "assets" / "go_right.py", "go_right")

# make train's ICCO when the routes screens ran: the consistency term's weight then (1e-4,
# unclamped) is pinned, so a screen trained after the default moved changes only its own lever.
CONTROL_WEIGHT = "ce1e-4"
BUDGET = [
    *consistency.BUDGET,
    "method=icco",
    *consistency.SCREENS[CONTROL_WEIGHT].overrides,
    "logger.progress=false",
]
CONTROL_RECORDS = EXPERIMENTS / "consistency" / "records" / CONTROL_WEIGHT
# The reproduction's scale: ICCO as the four-quadrant 5M page trains it (today's consistency
# default), whose kept runs are the control at that scale (not retrained).
BUDGET_5M = ["experiment=repro_5m", "method=icco", "logger.progress=false"]
CONTROLS = {  # screen: (records folder, glob of its runs' policies)
    "control": (CONTROL_RECORDS, "*/policy.pt"),
    "control_5m": (EXPERIMENTS / "four_quadrants" / "5m" / "records", "icco_seed*/policy.pt"),
}
SCALE = {"control_5m": BUDGET_5M, "hold_routes_5m": BUDGET_5M}  # screens not at BUDGET
HOLD_ROUTES = ["env.params.inst_hold=true", "env.params.waypoint_route_prob=0.5"]
SCREENS = {
    "control": [],
    "control_5m": [],
    "hold_routes": HOLD_ROUTES,
    "hold_routes_0.2": ["env.params.inst_hold=true", "env.params.waypoint_route_prob=0.2"],
    "hold_routes_soft": [
        "env.params.inst_hold=true",
        "env.params.waypoint_route_prob=0.5",
        "train.target_update=soft",
    ],
    "hold_routes_all_soft": [
        "env.params.inst_hold=true",
        "env.params.waypoint_route_prob=1.0",
        "train.target_update=soft",
    ],
    "hold_routes_5m": HOLD_ROUTES,  # on SCALE's budget
}
LABELS = {
    "control": "ICCO (make train)",
    "progress": "ICCO, progress r_inst",
    "progress_routes": "ICCO, progress r_inst, routes 0.5",
    "hold_routes": "ICCO, hold at the slot, routes 0.5",
    "hold_routes_0.2": "ICCO, hold at the slot, routes 0.2",
    "hold_routes_soft": "ICCO, hold at the slot, routes 0.5, soft target updates",
    "hold_routes_all_soft": "ICCO, hold at the slot, routes 1.0, soft target updates",
    "control_5m": "ICCO at 5M (the four-quadrant 5M page's runs)",
    "hold_routes_5m": "ICCO at 5M, hold at the slot, routes 0.5",
}
SEEDS = (0, 1)
INTERFACE = f"served@{serving.DEFAULT_STEP:g}"
# Screens measured and not kept: their rows stay in results.json, their lever left the library.
RETIRED = ("progress", "progress_routes")
REFERENCES = {  # label: team
    "follower (cosine r_inst)": "follower",
    "pursuit": "pursuit",
    "best scripted": "best_scripted",
}
# References of a retired lever: kept from results.json, scored in its own env (other units).
RETIRED_REFERENCES = ("follower (progress r_inst)",)
# The paper's r_inst, whatever a policy trained with: rewards in one unit, the same references.
PAPER_ENV = {"inst_hold": False}
TARGET_IN_PLACE = 0.8  # issue 47's bar for a learned team, on each instruction
WITHIN, STAY = 60, 0.8  # the arrival check's defaults (assets/go_right.py)
SCENES = len(go_right.INSTRUCTIONS) * len(go_right.SCENES)


def records_of(records: Path, screen: str) -> list[Path]:
    """A screen's run records (folders with a ``policy.pt``)."""
    folder, pattern = CONTROLS.get(screen, (records / screen, "*/policy.pt"))
    return sorted(p.parent for p in folder.glob(pattern))


def train(out: Path, records: Path, names, seeds, budget, n_jobs: int, smoke: bool = False) -> None:
    runs = {}
    for seed in seeds:  # seed by seed: a sitting cut short leaves paired seeds
        for name in names:
            if name in CONTROLS:
                continue
            scale = budget if smoke else SCALE.get(name, budget)
            overrides = [*scale, *SCREENS[name], f"seed={seed}"]
            runs[out / name / f"seed{seed}"] = (
                overrides,
                compose_config(overrides).train.total_frames,
            )
    jobs.train_runs(runs, n_jobs)
    for run in runs:  # keep the records: what any protocol needs, no optimizer or replay
        jobs.keep_run(run, records / run.parent.name / run.name)


def evaluate(screens: dict[str, list[Path]], out: Path, trials: int, seeds) -> dict:
    policies = [p / "policy.pt" for runs in screens.values() for p in runs]
    paper = (f"env.params.{k}={str(v).lower()}" for k, v in PAPER_ENV.items())
    rows = verdict.read_rows(jobs.score_quadrants(policies, out / "quadrants", trials, *paper))
    best_q = verdict.best_scripted(rows)
    results = {
        "trials": trials,
        "machine": f"{jobs.cpu_name()}, 1 thread",
        "budget": BUDGET,
        "seeds": list(seeds),
        "screens": {},
        "references": {},
    }
    for name, runs in screens.items():
        own = [r for r in rows if r["checkpoint"] in {str(p / "policy.pt") for p in runs}]
        parts = [
            serving.play("policy", p / "policy.pt", INTERFACE, trials, **PAPER_ENV) for p in runs
        ]
        results["screens"][name] = {
            "runs": [_shown(p) for p in runs],
            "quadrants": verdict.share_entry(verdict.episode_mean(own), best_q),
            "language": serving.pooled(parts),
            "arrival": [arrival(p / "policy.pt") for p in runs],
        }
        print(name, _in_place(results["screens"][name]["language"]), flush=True)
    results["quadrants_best_scripted"] = verdict.share_entry(best_q, best_q)
    first = policies[0]
    for label, team in REFERENCES.items():
        results["references"][label] = serving.play(team, first, INTERFACE, trials, **PAPER_ENV)
    return results


def arrival(policy: Path) -> int:
    """Scenes of the arrival check (``assets/go_right.py``: 5 instructions x 8 scenes, driven as
    ``icco live`` drives a team) that the policy passes."""
    scenes = [
        go_right.run_scene(policy, instruction, seed)
        for instruction in go_right.INSTRUCTIONS
        for seed in go_right.SCENES
    ]
    return sum(s.passed(WITHIN, STAY) for s in scenes)


def _shown(path: Path) -> str:
    """A run's folder relative to the repository (as given where it lies elsewhere)."""
    try:
        return str(path.resolve().relative_to(EXPERIMENTS.parent))
    except ValueError:
        return path.name


def _in_place(row: dict) -> str:
    return " ".join(f"{100 * row[i]['in_place']:.0f}%" for i in serving.INSTRUCTIONS)


def _pm(entry: dict, key: str, scale: float = 100, digits: int = 0) -> str:
    text = f"{scale * entry[key]:.{digits}f}"
    spread = entry.get(f"{key}_seed_std")
    return text + (f" ± {scale * spread:.{digits}f}" if spread is not None else "")


def render(results: dict) -> str:
    best_l = results["references"]["best scripted"][EPISODE]["reward"]
    lines = [
        "# Training for served plans: routes to a slot, and holding it",
        "",
        "Generated by `python experiments/language/routes/run.py` from `results.json`; the "
        "screens, the protocols and the columns are in the script's docstring. ICCO at `make "
        f"train`'s recipe on one core (2M frames), seeds {', '.join(map(str, SEEDS))}; the rows "
        "marked 5M at the reproduction's (`experiment=repro_5m`, 5M frames, the four-quadrant 5M "
        "page's ICCO), "
        f"their seeds in the arrival column; {results['trials']} trials per seed and protocol; "
        f"{results['machine']}. Every team is scored in the paper's env (cosine r_inst), plans "
        f"served ({INTERFACE}). A row: mean ± std over its seeds.",
        "",
        "In place: the share of steps in each instruction's second half with at least 2 of 3 "
        "robots where the instruction says (x > half/2, y > half/2, within 1 m of the centre, "
        "every pair 1.5 m apart). Language reward: the episode's team reward (4 instructions x "
        "145 steps), share of the best scripted team's under the same interface. Four quadrants: "
        "share of the best scripted team's on the same episodes. Arrival: scenes passed per seed "
        f"of the arrival check (`assets/go_right.py`: {len(go_right.INSTRUCTIONS)} instructions x "
        f"{len(go_right.SCENES)} scenes; every robot not intercepting at its slot by tick "
        f"{WITHIN}, and held on {STAY:.0%} of the ticks after). The last rows are scripted; "
        "the follower of the progress r_inst (measured and not kept) played in that env, so its "
        "reward is in other units. Screens marked *not kept*: their lever left the library; their "
        "numbers stay here.",
        "",
        "| team | "
        + " | ".join(serving.INSTRUCTIONS)
        + " | time to slot | language reward (share) | four quadrants (share) | arrival |",
        "|" + "---|" * (len(serving.INSTRUCTIONS) + 5),
    ]
    for name, s in results["screens"].items():
        lang, q = s["language"], s["quadrants"]
        cells = [_pm(lang[i], "in_place") + " %" for i in serving.INSTRUCTIONS]
        ep = lang[EPISODE]
        cells += [
            _pm(ep, "time_to_slot", 1),
            f"{_pm(ep, 'reward', 1, 1)} ({ep['reward'] / best_l:.0%})",
            f"{q['mean']:.1f} ± {q['std']:.1f} ({q['share_of_best_scripted']:.0%})",
            " / ".join(str(a) for a in s.get("arrival", [])) + f" of {SCENES}",
        ]
        kept = "" if name in SCREENS else " (*not kept*)"
        lines.append(f"| {LABELS[name]}{kept} | " + " | ".join(cells) + " |")
    best_q = results["quadrants_best_scripted"]
    for label, row in results["references"].items():
        ep = row[EPISODE]
        cells = [f"{100 * row[i]['in_place']:.0f} %" for i in serving.INSTRUCTIONS]
        quad = f"{best_q['mean']:.1f} (100%)" if label == "best scripted" else ""
        own_units = label in RETIRED_REFERENCES  # scored in its own r_inst's env
        reward = "other units" if own_units else f"{ep['reward']:.1f} ({ep['reward'] / best_l:.0%})"
        cells += [f"{ep['time_to_slot']:.0f}", reward, quad, ""]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", *reading(results), ""]
    return "\n".join(lines)


def reading(results: dict) -> list[str]:
    """What the table says, every figure read from ``results``."""
    out = ["## Reading", ""]
    best_l = results["references"]["best scripted"][EPISODE]["reward"]
    for name, s in results["screens"].items():
        lang = s["language"]
        low = [i for i in serving.INSTRUCTIONS if lang[i]["in_place"] < TARGET_IN_PLACE]
        verdict_text = (
            f"in place at least {TARGET_IN_PLACE:.0%} on every instruction"
            if not low
            else f"below {TARGET_IN_PLACE:.0%} on {', '.join(low)}"
        )
        out.append(
            f"- {LABELS[name]}: {verdict_text}; language reward "
            f"{lang[EPISODE]['reward'] / best_l:.0%} of the best scripted team's, four quadrants "
            f"{s['quadrants']['share_of_best_scripted']:.0%}"
            + (
                f"; arrival check passed in {' and '.join(map(str, s['arrival']))} of {SCENES} "
                "scenes (per seed)."
                if s.get("arrival")
                else "."
            )
        )
    follower = results["references"]
    for label in ("follower (cosine r_inst)", *RETIRED_REFERENCES):
        if label in follower:
            out.append(f"- The greedy {label}: in place {_in_place(follower[label])}.")
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--only", nargs="+", choices=list(SCREENS), default=list(SCREENS))
    parser.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    parser.add_argument(
        "--jobs", type=jobs.positive, default=2, help="runs side by side (one core each)"
    )
    parser.add_argument("--trials", type=jobs.positive, default=serving.TRIALS)
    parser.add_argument("--out", type=Path, default=Path("multirun/language_routes"))
    parser.add_argument("--records", type=Path, help="default: records/ here (--smoke: --out)")
    parser.add_argument("--smoke", action="store_true", help="seconds-long runs, 2 trials")
    parser.add_argument("--train-only", action="store_true")
    parser.add_argument("--report-only", action="store_true", help="README.md from results.json")
    args = parser.parse_args(argv)
    results_path = (args.out if args.smoke else HERE) / "results.json"
    args.records = args.records or (args.out / "records" if args.smoke else HERE / "records")
    if not args.report_only:
        budget = jobs.budget(args.smoke, None, BUDGET)
        if args.smoke:
            budget = [*budget, "method=icco", "logger.progress=false"]
        train(
            args.out.resolve(), args.records, args.only, args.seeds, budget, args.jobs, args.smoke
        )
        if args.train_only:
            return
        screens = {name: records_of(args.records, name) for name in args.only}
        screens = {name: runs for name, runs in screens.items() if runs}
        trials = 2 if args.smoke else args.trials
        new = evaluate(screens, args.out.resolve(), trials, args.seeds)
        if results_path.is_file():  # screens evaluated before stay (the same episodes, trials)
            old = json.loads(results_path.read_text())
            if old.get("trials") == trials:
                new["screens"] = {**old["screens"], **new["screens"]}
                retired = {k: v for k, v in old["references"].items() if k in RETIRED_REFERENCES}
                new["references"] = {**new["references"], **retired}
        order = [*SCREENS, *RETIRED]
        new["screens"] = {name: new["screens"][name] for name in order if name in new["screens"]}
        write_json(new, results_path)
    results = json.loads(results_path.read_text())
    (results_path.parent / "README.md").write_text(render(results))
    print(f"wrote {results_path.parent / 'README.md'}")


if __name__ == "__main__":
    sys.exit(main())
