"""How a plan reaches the robots: given once, or served as the walks they trained on.

    git show 135403d:assets/demo_icco.pt > former_demo.pt  # the page's learned team
    python experiments/language/serving/run.py --checkpoints former_demo.pt  # README.md
    python experiments/language/serving/run.py --checkpoints A.pt B.pt --label "ICCO, 5M"

The page's learned team is the demo policy as it was until commit 135403d (ICCO, 5M, seed 1,
``method.ce_coef`` 1e-4; :data:`LEARNED`): the served interface's step was chosen on it. The demo
shipped since was trained on served routes (``assets/README.md``).

The language protocol's four instructions ("Go right" -> "Move top" -> "Gather center" ->
"Spread out", 145 steps each, the offline rule planner asked once per instruction and trial),
20 trials on the env seed 20000 with the learned team's env (its calibrated reward), for:

- the scripted teams: ``follower`` (greedy on r_inst), ``pursuit`` (a perfect path follower),
  ``best_scripted`` (the yardstick), and the given checkpoints (pooled under ``--label``);
- the interfaces: ``fixed`` (the planner's waypoints written once and kept) and ``served`` at
  several step lengths (:mod:`icco_torchrl.instructions.serving`).

Columns (:mod:`icco_torchrl.evaluation.placement`, docs/metrics.md): "in place", the share of
steps in each instruction's second half with at least 2 of 3 robots where the instruction says
(x > half/2 for "Go right", y > half/2 for "Move top", within 1 m of the centre for "Gather
center", 1.5 m from every other robot for "Spread out"); "at slot", the share of robot-steps
within 0.5 m of the robot's own slot over the second half; "formation", the share of those
steps with every robot but the interceptor at its slot; "time to slot", steps until the
formation first holds (145 when it never does); the episode's team reward; planner requests.
Writes ``results.json`` and ``README.md`` here (or ``--out``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from icco_torchrl.envs.reference_policies import make_reference_policy
from icco_torchrl.envs.routes import DEFAULT_STEP
from icco_torchrl.evaluation.metrics import EPISODE, summarize, write_json
from icco_torchrl.evaluation.protocols import run_schedule, schedule_env
from icco_torchrl.instructions import LLMPlanner
from icco_torchrl.instructions.sources import language_schedule

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
sys.path.insert(0, str(HERE.parents[1]))
import jobs  # noqa: E402  (experiments/jobs.py)

INSTRUCTIONS = ("Go right", "Move top", "Gather center", "Spread out")
STEPS, TRIALS, ENV_SEED = 145, 20, 20000
LEARNED = "former demo ICCO (135403d)"  # the page's learned rows: see the docstring
REFERENCES = ("follower", "pursuit", "best_scripted")
INTERFACES = ("fixed", "served@0.19", "served@0.25", "served@0.35", "served@0.5")
COLUMNS = ("in_place", "at_slot", "formation", "time_to_slot", "reward")


def play(
    team: str, checkpoint: Path, interface: str, trials: int, seed: int = ENV_SEED, **env_params
) -> dict:
    """One team under one interface: its summary per instruction and for the episode.
    ``env_params``: env parameters other than the checkpoint's (``inst_hold``)."""
    plan, _, step = interface.partition("@")
    total = STEPS * len(INSTRUCTIONS)
    restored = schedule_env(checkpoint, total, trials, seed=seed, **env_params)
    env = restored["env"]
    policy = restored["policy"] if team == "policy" else make_reference_policy(team, env)
    schedule = language_schedule(
        LLMPlanner(),
        list(INSTRUCTIONS),
        STEPS,
        plan=plan,
        **({"step": float(step)} if step else {}),
    )
    run = run_schedule(env, policy, schedule, trials, method=team)
    out = {s["segment"]: {k: s[k] for k in COLUMNS} for s in summarize(run.rows)}
    out["requests"] = sum(source["plans"] for source in run.sources)
    return out


def pooled(parts: list[dict]) -> dict:
    """The mean over checkpoints (seeds) of each per-segment value (equal trials each), its std
    over them (``<column>_seed_std``) and the checkpoints' own rows (``seeds``)."""
    out = {"requests": sum(p["requests"] for p in parts)}
    for segment in parts[0]:
        if segment == "requests":
            continue
        values = {k: np.array([p[segment][k] for p in parts], float) for k in COLUMNS}
        out[segment] = {k: float(v.mean()) for k, v in values.items()}
        out[segment].update({f"{k}_seed_std": float(v.std()) for k, v in values.items()})
    if len(parts) > 1:
        out["seeds"] = parts
    return out


def _cell(entry: dict, key: str, scale: float, digits: int, unit: str = "") -> str:
    text = f"{scale * entry[key]:.{digits}f}"
    spread = entry.get(f"{key}_seed_std")
    return text + (f" ± {scale * spread:.{digits}f}" if spread else "") + unit


def render(results: dict) -> str:
    lines = [
        "# How a plan reaches the robots: given once, or served",
        "",
        "Generated by `python experiments/language/serving/run.py` from `results.json`; the "
        "protocol, the teams and the columns are in the script's docstring. "
        f"{results['trials']} trials per team, env seed {ENV_SEED}, the offline rule planner; "
        f"{results['machine']}.",
        "",
        "In place: the share of steps in each instruction's second half with at least 2 of 3 "
        "robots where the instruction says (a person's judgement). Reward: the team's episode "
        "total (4 instructions x 145 steps). A row of several checkpoints (seeds) shows the mean "
        "over them ± the std over them; `results.json` keeps each seed's row.",
        "",
    ]
    head = (
        "| team | plan | "
        + " | ".join(INSTRUCTIONS)
        + " | at slot | formation | time to slot | reward | requests |"
    )
    lines += [head, "|" + "---|" * (len(INSTRUCTIONS) + 7)]
    for key, row in results["rows"].items():
        team, interface = key.split(" | ")
        ep = row[EPISODE]
        cells = [_cell(row[i], "in_place", 100, 0, " %") for i in INSTRUCTIONS]
        cells += [_cell(ep, "at_slot", 1, 2), _cell(ep, "formation", 1, 2)]
        cells += [_cell(ep, "time_to_slot", 1, 0), _cell(ep, "reward", 1, 1), str(row["requests"])]
        lines.append(f"| {team} | {interface} | " + " | ".join(cells) + " |")
    return "\n".join(lines[:6] + findings(results) + lines[6:]) + "\n"


def findings(results: dict) -> list[str]:
    """What the table says, every figure read from ``results`` (missing rows are left out)."""
    rows = results["rows"]
    demo, served = LEARNED, f"served@{DEFAULT_STEP:g}"

    def place(team, plan):
        return "/".join(
            f"{100 * rows[f'{team} | {plan}'][i]['in_place']:.0f}" for i in INSTRUCTIONS
        )

    def reward(team, plan):
        return rows[f"{team} | {plan}"][EPISODE]["reward"]

    keys = [f"{t} | {p}" for t in ("follower", "pursuit", "best_scripted", demo)
            for p in ("fixed", served)]  # fmt: skip
    if not all(k in rows for k in keys):
        return []
    share = {p: reward(demo, p) / reward("best_scripted", p) for p in ("fixed", served)}
    out = [
        "## What it shows",
        "",
        f"- **Given once**, the teams that earn the instruction reward are rarely in place on the "
        f"sides (in place, {', '.join(INSTRUCTIONS)}, %: follower {place('follower', 'fixed')}, "
        f"best scripted {place('best_scripted', 'fixed')}, demo {place(demo, 'fixed')}), while a "
        f"path follower that ignores the reward is always there ({place('pursuit', 'fixed')}): "
        "the plan leads there, but past its middle the reward's direction (nearest waypoint to its "
        "nearest neighbour) points back, and the team never trained on a fixed path.",
        f"- **Served** (K waypoints from each robot along its route, {DEFAULT_STEP:g} m apart, at "
        f"every refresh), the same teams are in place far more often: demo "
        f"{place(demo, served)}, follower {place('follower', served)}, best scripted "
        f"{place('best_scripted', served)}; the path "
        f"follower stays at {place('pursuit', served)}. The planner is asked once per instruction "
        f"and episode either way ({rows[f'{demo} | {served}']['requests']} requests for "
        f"{len(INSTRUCTIONS)} instructions x {results['trials']} trials).",
        f"- **Reward falls** under served plans for every team (demo {reward(demo, 'fixed'):.1f} "
        f"-> {reward(demo, served):.1f}, best scripted {reward('best_scripted', 'fixed'):.1f} -> "
        f"{reward('best_scripted', served):.1f}, follower {reward('follower', 'fixed'):.1f} -> "
        f"{reward('follower', served):.1f}): a robot at its slot is served K copies of it and "
        "earns no direction reward (the cosine of a zero path is 0), where a fixed path pays a "
        "robot that moves back and forth along it. The demo's share of the best scripted team "
        "falls from "
        f"{100 * share['fixed']:.0f} % to {100 * share[served]:.0f} %.",
        "- **The greedy follower stalls** even when served: `r_inst`'s cosine does not see speed, "
        "so on a diagonal route coasting to a halt along it scores more than any axis move. That "
        "is the reward's doing, not the interface's: the path follower arrives in about "
        f"{rows[f'pursuit | {served}'][EPISODE]['time_to_slot']:.0f} steps.",
        *_learned(rows, served, reward("best_scripted", served)),
        "- **The step length** trades following against reward: longer steps lift the follower's "
        "in-place share and lower every team's reward (the rows above). "
        f"{DEFAULT_STEP:g} m, the training walk's mean increment, is the default.",
        "",
    ]
    return out


def _learned(rows: dict, served: str, best: float) -> list[str]:
    """The bullet on the 5M ICCO runs (seeds pooled), when the page has their rows."""
    key = "ICCO, 5M (seeds 0, 1, 2)"
    if f"{key} | {served}" not in rows or f"{key} | fixed" not in rows:
        return []
    on, once = rows[f"{key} | {served}"], rows[f"{key} | fixed"]

    def place(row):
        return "/".join(
            f"{100 * row[i]['in_place']:.0f} ± {100 * row[i]['in_place_seed_std']:.0f}"
            for i in INSTRUCTIONS
        )

    return [
        f"- **ICCO at 5M, 3 seeds** (the reproduction's policies, kept beside its records in "
        "experiments/four_quadrants/5m/records): in place "
        f"{place(once)} % given once, {place(on)} % served (mean ± std over seeds); reward "
        f"{once[EPISODE]['reward']:.1f} -> {on[EPISODE]['reward']:.1f}, "
        f"{100 * on[EPISODE]['reward'] / best:.0f} % of the best scripted team served.",
    ]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--checkpoints", nargs="+", type=Path, required=True)
    parser.add_argument("--label", default=LEARNED)
    parser.add_argument("--interfaces", nargs="+", default=list(INTERFACES))
    parser.add_argument("--references", nargs="*", default=list(REFERENCES))
    parser.add_argument("--trials", type=int, default=TRIALS)
    parser.add_argument("--out", type=Path, default=HERE)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    path = args.out / "results.json"
    results = json.loads(path.read_text()) if path.is_file() else {"rows": {}}
    results.update(trials=args.trials, machine=f"{jobs.cpu_name()}, 1 thread")
    for interface in args.interfaces:
        for team in [*args.references, args.label]:
            start = time.time()
            if team == args.label:
                row = pooled([play("policy", c, interface, args.trials) for c in args.checkpoints])
            else:
                row = play(team, args.checkpoints[0], interface, args.trials)
            results["rows"][f"{team} | {interface}"] = row
            shown = " ".join(f"{100 * row[i]['in_place']:.0f}%" for i in INSTRUCTIONS)
            reward = row[EPISODE]["reward"]
            print(f"{team} | {interface}: in place {shown}, reward {reward:.1f} "
                  f"({time.time() - start:.0f} s)", flush=True)  # fmt: skip
            write_json(results, path)
    (args.out / "README.md").write_text(render(results))


if __name__ == "__main__":
    sys.exit(main())
