"""Consistency-term screen (issue 48): the weight of L_CE, with COPA's clamps on and off.

    python experiments/consistency/run.py                 # every screen x 2 seeds, resumable
    python experiments/consistency/run.py --only ce1e-3 ce1e-3_clamp --seeds 0
    python experiments/consistency/run.py --train-only    # stop after training
    python experiments/consistency/run.py --report-only   # results.json, README from the records
    python experiments/consistency/run.py --smoke --only wo_ce ce1 --seeds 0   # pipeline check

The paper trains on ``L_RL + L_CE`` at unit weight, COPA at ``1e-3`` (``-log q``) and ``1e-4``
(``-H``) with clamps, this project at ``1e-3`` for both with clamps (:data:`CONTROL`, the
screen's choice; 1e-4 unclamped before it). A screen is ICCO at
:data:`BUDGET` (``make train``'s recipe, 2M frames, one core: the env and the update in one
process, one thread) with ``method.ce_coef = method.entropy_coef = w`` (the paper's 1 : 1 ratio,
the project's default one) for ``w`` in :data:`WEIGHTS`, each with ``train.ce_clamp`` off and on;
``wo_ce`` is ``w = 0`` (ICCO w/o CE: no term, so nothing to clamp) and ``copa`` is COPA as written
(1e-3 and 1e-4, clamps on). Two seeds each (a screen, not a result).

1. Training: ``--out/<screen>/<method>_seed<k>``, two runs side by side, one thread each, seed by
   seed across screens (``experiments/jobs.py``); run the script again after an interruption:
   finished runs are kept, interrupted ones continue from their checkpoint.
2. Evaluation of each screen, seeds pooled (redone only when a checkpoint is newer):
   ``icco eval eval.protocol=quadrants`` (20 trials per seed, the scripted references on the same
   episodes: team reward and its share of the best scripted team's; and the coordination
   measures of ``docs/consistency.md``: the mutual-information lower bound with a posterior
   fitted after training, its floor, swap consistency) into ``<screen>/eval_quadrants``, and the
   language protocol (``icco instruct`` "Go right; Move top; Gather center; Spread out", offline
   planner, 20 trials per seed) into ``<screen>/language``.
3. Records: each run's ``config.yaml``, ``eval.csv``, ``timing.csv``, ``references.json``, its
   quadrant and language trials, its checkpoint entry (coordination measures included), the means
   of its last training rows (``training.json``: ``loss_td``, ``loss_ce``, ``log_q``, ``entropy``)
   and its exported policy weights (``policy.pt``: ``icco eval checkpoint=.../policy.pt``) in
   ``--records/<screen>/<run>/``; ``results.json`` and ``README.md`` here are written from the
   records alone (``--report-only``), so seeds trained on different machines pool.
"""

# No ``from __future__ import annotations``: the dataclass below then needs no module lookup,
# so the tests may load this file by path (as experiments/verdict.py explains).
import argparse
import csv
import json
import math
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from icco_torchrl.evaluation.consistency import COLUMNS
from icco_torchrl.evaluation.metrics import share_text, write_csv, write_json
from icco_torchrl.training.build import compose_config

HERE = Path(__file__).resolve().parent
EXPERIMENTS = HERE.parent
sys.path.insert(0, str(EXPERIMENTS))
import jobs  # noqa: E402  (experiments/jobs.py, the one job runner)
from verdict import (  # noqa: E402
    AHEAD,
    BEHIND,
    RULE,
    WITHIN,
    Mean,
    best_scripted,
    compare,
    digits,
    episode_mean,
    read_rows,
    share_entry,
)

# `make train`'s recipe (experiment=make_train: 2M frames, compiled update) on one core: the env
# in the learner's process (two runs side by side use a 2-core machine), and no replay dump in the
# checkpoints (24 runs x ~450 MB; a resumed run refills its buffer). The weights of every
# evaluation are kept, so benchmarks/time_to_skill.py can score the control's learning curve.
# Hard target copies: make train's recipe when the screen began (it has soft updates since), so
# every screen stays comparable with its control.
BUDGET = [
    "experiment=make_train",
    "train.target_update=hard",
    "train.collector=inline",
    "train.threads=1",
    "train.checkpoint_buffer=false",
    "train.policy_snapshots=true",
]
SEEDS = (0, 1)
WEIGHTS = {"1e-4": 1e-4, "1e-3": 1e-3, "1e-2": 1e-2, "1e-1": 1e-1, "1": 1.0}
INSTRUCTIONS = ("Go right", "Move top", "Gather center", "Spread out")
TRAINING_COLUMNS = ("loss_td", "loss_ce", "log_q", "entropy", "ce_nll", "ce_neg_entropy")
TAIL = 0.1  # training.json: the mean over the last 10 % of train.csv's rows


@dataclass(frozen=True)
class Screen:
    """One screen: the lever in words, the method preset and its overrides, and the weights."""

    lever: str
    method: str
    ce_coef: float
    entropy_coef: float
    clamp: bool

    @property
    def overrides(self) -> list[str]:  # ICCO w/o CE: its preset's zeros, unclamped as it trained
        return [
            f"method.ce_coef={self.ce_coef}",
            f"method.entropy_coef={self.entropy_coef}",
            f"train.ce_clamp={str(self.clamp).lower()}",
        ]


def _screens() -> dict[str, Screen]:
    screens = {"wo_ce": Screen("no consistency term (ICCO w/o CE)", "icco_wo_ce", 0.0, 0.0, False)}
    for name, w in WEIGHTS.items():
        for clamp in (False, True):
            lever = f"L_CE weighted {name} (-log q and -H)" + (", COPA's clamps" if clamp else "")
            screens[f"ce{name}" + "_clamp" * clamp] = Screen(lever, "icco", w, w, clamp)
    screens["copa"] = Screen(
        "COPA as written: 1e-3 x -log q, 1e-4 x -H, clamps", "icco", 1e-3, 1e-4, True
    )
    return screens


SCREENS = _screens()
# The project's default ICCO (method.ce_coef, method.entropy_coef, train.ce_clamp): this screen's
# choice (the page's rule); the default was ce1e-4 before it.
CONTROL = "ce1e-3_clamp"


# ---------------------------------------------------------------------------- 1. training
def train(out: Path, names, seeds, budget, n_jobs: int) -> None:
    runs = {}
    for seed in seeds:  # seed by seed: a sitting cut short leaves paired seeds
        for name in names:
            s = SCREENS[name]
            overrides = [f"method={s.method}", *budget, *s.overrides]
            runs[out / name / f"{s.method}_seed{seed}"] = (
                [*overrides, f"seed={seed}"],
                compose_config(overrides).train.total_frames,
            )
    jobs.train_runs(runs, n_jobs)


# ---------------------------------------------------------------------------- 2. evaluation
def icco(*args: str) -> None:
    command = [sys.executable, "-m", "icco_torchrl", *args]
    print("$ icco " + " ".join(args), flush=True)
    subprocess.run(command, check=True)


def up_to_date(report: Path, checkpoints: list[Path]) -> bool:
    """Whether ``report`` (an evaluation's JSON) scored exactly ``checkpoints``, after their last
    write."""
    if not report.is_file():
        return False
    scored = [c["path"] for c in json.loads(report.read_text()).get("checkpoints", [])]
    newest = max(p.stat().st_mtime for p in checkpoints)
    return scored == [str(p) for p in checkpoints] and report.stat().st_mtime > newest


def evaluate(folder: Path, checkpoints: list[Path], trials: int, steps: int, smoke: bool) -> None:
    """The quadrant protocol (with the coordination measures) and the language protocol of one
    screen's checkpoints, each unless up to date."""
    paths = f"eval.checkpoints=[{','.join(map(str, checkpoints))}]"
    common = [paths, f"eval.trials={trials}", f"eval.steps={steps}"]
    budget = ["eval.coordination.episodes=4", "eval.coordination.fit_steps=5"] if smoke else []
    quadrants = folder / "eval_quadrants"
    if not up_to_date(quadrants / "quadrants.json", checkpoints):
        icco(
            "eval",
            *common,
            "eval.protocol=quadrants",
            *budget,
            f"eval.out_dir={quadrants}",
            f"hydra.run.dir={quadrants}",
        )
    language = folder / "language"
    if not up_to_date(language / "instruct.json", checkpoints):
        icco(
            "instruct",
            "; ".join(INSTRUCTIONS),
            *common,
            "llm=offline",
            f"eval.out_dir={language}",
            f"hydra.run.dir={language}",
        )


# ---------------------------------------------------------------------------- 3. records
def training_tail(run: Path) -> dict:
    """The mean of each of :data:`TRAINING_COLUMNS` over the last :data:`TAIL` of ``train.csv``'s
    rows (NaN where the column is absent or empty: ICCO w/o CE has no ``loss_ce``)."""
    path = run / "train.csv"
    if not path.is_file():
        return {}
    with path.open() as handle:
        rows = list(csv.DictReader(handle))
    tail = rows[-max(1, int(len(rows) * TAIL)) :]
    out = {"frames": float(tail[-1]["frames"]) if tail else math.nan}
    for column in TRAINING_COLUMNS:
        values = [float(r[column]) for r in tail if r.get(column) not in (None, "", "nan")]
        out[column] = float(np.mean(values)) if values else math.nan
    return out


def keep(folder: Path, records: Path) -> None:
    """File the screen's runs as records (:func:`jobs.keep_records`: their files and policy
    weights), with their language trials and training tail."""
    quadrants, language = folder / "eval_quadrants", folder / "language"
    kept = jobs.keep_records(
        quadrants / "quadrants.json", quadrants / "quadrants_trials.csv", records
    )
    with (language / "instruct_trials.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    for entry in json.loads((language / "instruct.json").read_text())["checkpoints"]:
        run = Path(entry["path"]).parent
        own = [{**r, "checkpoint": run.name} for r in rows if r["checkpoint"] == entry["path"]]
        write_csv(own, records / run.name / "language_trials.csv")
    references = [r for r in rows if not r["checkpoint"]]
    if references:
        write_csv(references, records / "language_references_trials.csv")
    for record in kept:
        write_json(training_tail(folder / record.name), record / "training.json")


# ---------------------------------------------------------------------------- results, README
def _spread(values: list[float]) -> dict | None:
    values = [v for v in values if v is not None and math.isfinite(v)]
    if not values:
        return None
    return {"mean": float(np.mean(values)), "std": float(np.std(values)), "seeds": len(values)}


def screen_results(folder: Path) -> dict | None:
    """One screen's numbers from its records ``folder``: rewards per protocol (mean, std and
    trials, seeds pooled; share of the best scripted team's on the same episodes), coordination
    measures and training tails (mean and std over seeds)."""
    runs = sorted(p for p in folder.iterdir() if (p / "checkpoint.json").is_file())
    if not runs:
        return None
    quadrant_rows = [r for run in runs for r in read_rows(run / "trials.csv")]
    language_rows = [r for run in runs for r in read_rows(run / "language_trials.csv")]
    entries = [json.loads((run / "checkpoint.json").read_text()) for run in runs]
    tails = [
        json.loads((run / "training.json").read_text())
        for run in runs
        if (run / "training.json").is_file()
    ]
    best_q = best_scripted(read_rows(folder / jobs.REFERENCES_TRIALS))
    best_l = best_scripted(read_rows(folder / "language_references_trials.csv"))
    coordination = [e.get("coordination") or {} for e in entries]
    return {
        "runs": [run.name for run in runs],
        "seeds": sorted(e["seed"] for e in entries),
        "frames": min(int(e.get("frames") or 0) for e in entries),
        "quadrants": {
            "reward": share_entry(episode_mean(quadrant_rows), best_q),
            "task_reward": share_entry(episode_mean(quadrant_rows, "task_reward"), None),
            "inst_reward": share_entry(episode_mean(quadrant_rows, "inst_reward"), None),
            "best_scripted": share_entry(best_q, best_q),
        },
        "language": {
            "reward": share_entry(episode_mean(language_rows), best_l),
            "best_scripted": share_entry(best_l, best_l),
        },
        "coordination": {c: _spread([m.get(c) for m in coordination]) for c in COLUMNS},
        "training": {c: _spread([t.get(c) for t in tails]) for c in TRAINING_COLUMNS},
    }


def results(records: Path, budget: list[str]) -> dict:
    screens = {}
    for name, s in SCREENS.items():
        found = screen_results(records / name) if (records / name).is_dir() else None
        if found is not None:
            screens[name] = {
                "lever": s.lever,
                "method": s.method,
                "ce_coef": s.ce_coef,
                "entropy_coef": s.entropy_coef,
                "ce_clamp": s.clamp,
                **found,
            }
    return {"budget": budget, "control": CONTROL, "screens": screens}


def _cell(value: dict | None, decimals: int = 1, share: bool = False) -> str:
    if not value:
        return "–"
    text = f"{value['mean']:.{decimals}f} ± {value['std']:.{decimals}f}"
    if share and value.get("share_of_best_scripted") is not None:
        text += f" ({share_text(value['share_of_best_scripted'])})"
    return text


def _against_control(entry: dict, control: dict | None) -> str:
    reward, base = entry["quadrants"]["reward"], (control or {}).get("quadrants", {}).get("reward")
    if not reward or not base:
        return "–"
    return compare(
        Mean(reward["mean"], reward["std"], reward["n"]), Mean(base["mean"], base["std"], base["n"])
    ).text()


def where_section(path: Path) -> str:
    """The chosen screen against ICCO w/o CE where the paper says consistency matters, from
    ``where.py``'s results (nothing before they exist)."""
    if not path.is_file():
        return ""
    res = json.loads(path.read_text())
    chosen = res["chosen"]
    return f"""
## Where the paper says consistency matters

`{chosen}` against ICCO w/o CE (`{res["baseline"]}`), the screens' own policies, {res["trials"]}
trials per seed: ambiguous instructions (`icco instruct`, plans served), zero-shot teams of 5 and
6, and adaptive broadcast (beta 0.5). {MEANS}

{where_table(res)}

{where_reading(res)}

Written by `python experiments/consistency/where.py --chosen {chosen}` into `where.json`.
"""


def five_m_section(path: Path) -> str:
    """ICCO at 5M (the default weight) against ICCO w/o CE at 5M, from ``where.py --five-m``."""
    if not path.is_file():
        return ""
    res = json.loads(path.read_text())
    return f"""
## At 5M: the reproduction's ICCO against ICCO w/o CE

ICCO at the default weight and ICCO w/o CE, 5M frames, 3 seeds each (the
[four-quadrant reproduction](../four_quadrants/5m/README.md)'s policies), {res["trials"]} trials
per seed: four quadrants as trained, with the coordination measures, and the settings where the
paper says consistency matters, as above. {MEANS}

{where_table(res)}

{where_reading(res)}

Written by `python experiments/consistency/where.py --five-m` into `where_5m.json`.
"""


MEANS = (
    "Rewards: mean ± std over trials, seeds pooled (share of the best scripted team's at that "
    "setting); measures: mean ± std over seeds."
)


def where_reading(res: dict) -> str:
    """The section's table in words: for reward, swap consistency and being in place, the
    settings grouped by the verdict of the chosen team against the baseline; for the
    mutual-information bound, its margin over its floor per team (the floor moves too)."""
    chosen, base = res["chosen"], res["baseline"]
    words = (AHEAD, BEHIND, WITHIN)
    lines = []
    for label, match in (
        ("reward", lambda k: k == "reward"),
        ("swap consistency", lambda k: k == "consistency"),
        ("in place", lambda k: k.startswith("in_place")),
    ):
        found = {w: [] for w in words}
        for setting, verdicts in res["verdicts"].items():
            for key, text in verdicts.items():
                word = next((w for w in words if text.startswith(w)), None)
                if match(key) and word:
                    what = key.removeprefix("in_place: ")
                    found[word].append(setting if what == key else f"{setting} ({what})")
        parts = [f"{w} in {', '.join(s)}" for w, s in found.items() if s]
        if parts:
            lines.append(f"- `{chosen}` against `{base}`, {label}: " + "; ".join(parts) + ".")
    margins = []
    for setting, teams in res["settings"].items():
        gain = {}
        for team in (chosen, base):
            entry = teams.get(team) or {}
            if entry.get("mi_bound") and entry.get("mi_null"):
                gain[team] = entry["mi_bound"]["mean"] - entry["mi_null"]["mean"]
        if len(gain) == 2:
            margins.append(f"{setting} {gain[chosen]:+.1f} against {gain[base]:+.1f}")
    if margins:
        lines.append(
            f"- The bound above its floor (nats, `{chosen}` against `{base}`): "
            + "; ".join(margins)
            + "."
        )
    return "\n".join(lines)


def where_table(res: dict) -> str:
    """One row per setting and measure: the two teams and the verdict."""
    chosen, base = res["chosen"], res["baseline"]
    lines = [
        f"| setting | measure | `{chosen}` | `{base}` | `{chosen}` against `{base}` |",
        "|---|---|---|---|---|",
    ]
    for setting, teams in res["settings"].items():
        for key, entry in (teams.get(chosen) or {}).items():
            other = (teams.get(base) or {}).get(key)
            share = key == "reward"
            verdict = res["verdicts"].get(setting, {}).get(key, "–")
            cells = [_cell(entry, digits(key), share), _cell(other, digits(key), share)]
            lines.append(f"| {setting} | {key} | " + " | ".join(cells) + f" | {verdict} |")
    return "\n".join(lines)


DEFAULT_RULE = (
    "Rule for the default (highest reward; at equal reward, the MI bound beyond the spread)"
)


def decision(screens: dict, top: str, gain) -> str:
    """Issue 48's rule for ICCO's default, in words: the weight that wins on reward (``top``),
    or, among the weights within the spread of its reward, the one whose bound above its floor
    wins: above ``top``'s beyond the seeds' spread (``gain``: ``(gain, spread)`` or None; the
    intervals ``gain ± spread`` do not overlap, the test the reading applies against ICCO w/o
    CE). A weight whose bound is only higher on the mean does not win."""
    r = screens[top]["quadrants"]["reward"]
    level = [top]
    for name, entry in screens.items():
        q = entry["quadrants"]["reward"]
        if name == top or entry["method"] != "icco" or "n" not in q or "n" not in r:
            continue
        if (
            compare(Mean(q["mean"], q["std"], q["n"]), Mean(r["mean"], r["std"], r["n"])).word
            == WITHIN
        ):
            level.append(name)
    names = lambda group: ", ".join(f"`{n}`" for n in group)  # noqa: E731
    if len(level) == 1:
        return f"{DEFAULT_RULE}: `{top}`, the highest reward."
    mine = gain(screens[top])
    gains = {n: gain(screens[n]) for n in level[1:]}
    winners = {
        n: g
        for n, g in gains.items()
        if g is not None and mine is not None and g[0] - g[1] > mine[0] + mine[1]
    }
    if winners:
        pick = max(winners, key=lambda n: winners[n][0])
        return (
            f"{DEFAULT_RULE}: `{pick}`, of the weights at equal reward ({names(level)}), the bound "
            f"above its floor beyond the seeds' spread of `{top}`'s."
        )
    shown = lambda n, g: f"`{n}` {g[0]:+.2f} ± {g[1]:.2f}"  # noqa: E731
    margins = ", ".join(shown(n, g) for n, g in gains.items() if g is not None)
    return (
        f"{DEFAULT_RULE}: `{top}`, the highest reward; no weight at equal reward "
        f"({names(level[1:])}) has its bound above its floor beyond the seeds' spread of "
        f"`{top}`'s (nats above the floor, ± the seeds' spread: "
        + (f"{shown(top, mine)}, " if mine is not None else "")
        + f"{margins})."
    )


def reading(screens: dict) -> str:
    """What the table says, in words, from the numbers alone: the best screen on reward, the best
    weight of ICCO's term, and each weight's mutual-information bound above its floor against
    ICCO w/o CE's (a gain counts only beyond the spread of the seeds)."""
    rewarded = {n: e for n, e in screens.items() if e["quadrants"]["reward"]}
    if not rewarded:
        return ""

    def reward(name):
        return rewarded[name]["quadrants"]["reward"]["mean"]

    def gain(entry):  # the bound above its floor, seed by seed spread added
        c = entry["coordination"]
        if not c.get("mi_bound") or not c.get("mi_null"):
            return None
        return c["mi_bound"]["mean"] - c["mi_null"]["mean"], c["mi_bound"]["std"] + c["mi_null"][
            "std"
        ]

    best = max(rewarded, key=reward)
    icco = [n for n in rewarded if rewarded[n]["method"] == "icco"]
    lines = [f"- Highest four-quadrant reward: `{best}` ({reward(best):.1f})."]
    if icco:
        top = max(icco, key=reward)
        lines.append(f"- Of ICCO's weights, the highest: `{top}` ({reward(top):.1f}).")
        lines.append(f"- {decision(rewarded, top, gain)}")
    base = gain(screens["wo_ce"]) if "wo_ce" in screens else None
    for name in icco:
        g = gain(screens[name])
        if g is None or base is None:
            continue
        above = g[0] - g[1] > base[0] + base[1]
        lines.append(
            f"- `{name}`: bound above its floor by {g[0]:+.2f} nats (ICCO w/o CE: {base[0]:+.2f}); "
            + (
                "above ICCO w/o CE's beyond the seeds' spread."
                if above
                else "not above ICCO w/o CE's beyond the seeds' spread."
            )
        )
    return "\n".join(["**Reading** (written from the numbers above):", "", *lines])


def render(res: dict, command: str) -> str:
    """The README of ``res`` (:func:`results`)."""
    screens, control = res["screens"], res["screens"].get(res["control"])
    head = [
        "screen",
        "-log q, -H weights",
        "clamps",
        "seeds",
        "four quadrants (share of best scripted)",
        f"vs {res['control']}",
        "language (share)",
        "I bound (nats)",
        "floor (nats)",
        "swap consistency",
        "loss_ce / loss_td at the end",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, e in screens.items():
        c, t = e["coordination"], e["training"]
        ratio = "–"
        if t.get("loss_ce") and t.get("loss_td") and t["loss_td"]["mean"]:
            ratio = f"{t['loss_ce']['mean']:.3g} / {t['loss_td']['mean']:.3g}"
        lines.append(
            "| "
            + " | ".join(
                [
                    f"`{name}`",
                    f"{e['ce_coef']:g}, {e['entropy_coef']:g}",
                    "on" if e["ce_clamp"] else "off",
                    ", ".join(map(str, e["seeds"])),
                    _cell(e["quadrants"]["reward"], share=True),
                    "control" if name == res["control"] else _against_control(e, control),
                    _cell(e["language"]["reward"], share=True),
                    _cell(c.get("mi_bound")),
                    _cell(c.get("mi_null")),
                    _cell(c.get("consistency"), 3),
                    ratio,
                ]
            )
            + " |"
        )
    missing = [n for n in SCREENS if n not in screens]
    return f"""# Consistency term: its weight, COPA's clamps, and what it does

Issue 48. The paper trains on `L_RL + L_CE` at unit weight; COPA weights `-log q` by 1e-3 and `-H`
by 1e-4 and clamps both per dimension; the project's default is 1e-3 for both, clamped (the
`{res["control"]}` screen, this page's choice; it was `ce1e-4`, unclamped, before). Each screen is
ICCO trained at the budget below with the weights shown (`method.ce_coef`, `method.entropy_coef`)
and COPA's clamps (`train.ce_clamp`) off or on, two seeds; `wo_ce` is ICCO w/o CE. Every run is
then measured alike (`docs/consistency.md`): the four-quadrant and language protocols (team reward,
20 trials per seed, seeds pooled, and its share of the best scripted team's on the same episodes),
the mutual-information lower bound `E[log q] + H` with a posterior fitted after training on
held-out rollouts, its floor (z redrawn independently of the behaviour: what the estimator gives
when the behaviour reveals nothing), and swap consistency (1: robots read z alike, 0: z changes no
action).

Budget: `{" ".join(res["budget"])}`.

{chr(10).join(lines) if screens else "No screen measured yet: run the command below."}

The default trained at the method's scale (5M frames, 3 seeds) against ICCO w/o CE: the
[four-quadrant reproduction](../four_quadrants/5m/README.md) and, plans served,
[the language protocol](../language/5m/README.md).

Rewards: mean ± std over trials (seeds pooled). Coordination and training columns: mean ± std
over seeds. "vs {res["control"]}": the four-quadrant reward against the control's. {RULE}
{("Not measured yet: " + ", ".join(f"`{n}`" for n in missing) + ".") if missing else ""}

{reading(screens)}

Reproduce (resumable; records in `experiments/consistency/records/<screen>/<run>/`, each with its
policy weights `policy.pt`):

    {command}

{where_section(HERE / "where.json")}
{five_m_section(HERE / "where_5m.json")}
This page is written from `results.json` by `python experiments/consistency/run.py --report-only`.
"""


def report(
    records: Path, results_path: Path, readme: Path, budget: list[str], command: str
) -> None:
    res = results(records, budget)
    write_json(res, results_path)
    readme.write_text(render(res, command))
    print(f"results: {results_path}\nreadme: {readme}", flush=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--out", type=Path, help="sweep folder (default multirun/consistency[_smoke])"
    )
    parser.add_argument(
        "--only",
        nargs="+",
        choices=list(SCREENS),
        metavar="NAME",
        help=f"screens: {', '.join(SCREENS)}",
    )
    parser.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    parser.add_argument(
        "--budget",
        nargs="*",
        help="training overrides instead of BUDGET (with --smoke: added to the smoke budget)",
    )
    parser.add_argument(
        "--jobs", type=jobs.positive, default=2, help="training runs side by side (one core each)"
    )
    parser.add_argument(
        "--trials", type=jobs.positive, default=20, help="evaluation trials per checkpoint"
    )
    parser.add_argument(
        "--steps", type=jobs.positive, default=145, help="steps per quadrant and per instruction"
    )
    parser.add_argument(
        "--records", type=Path, help="records folder (default here, or the sweep's with --smoke)"
    )
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="seconds-long runs, 4 trials of 20 steps: a pipeline check",
    )
    parser.add_argument("--train-only", action="store_true")
    parser.add_argument(
        "--report-only", action="store_true", help="results.json and README.md from the records"
    )
    args = parser.parse_args(argv)
    out = (args.out or Path("multirun/consistency" + "_smoke" * args.smoke)).resolve()
    budget = jobs.budget(args.smoke, args.budget, BUDGET)
    records = (args.records or (out / "records" if args.smoke else HERE / "records")).resolve()
    page = out if args.smoke else HERE
    names = args.only or list(SCREENS)
    trials, steps = (4, 20) if args.smoke else (args.trials, args.steps)
    command = "python experiments/consistency/run.py" + (
        "" if args.budget is None else " --budget " + " ".join(args.budget)
    )
    if not args.report_only:
        train(out, names, args.seeds, budget, args.jobs)
        if args.train_only:
            return
        for name in names:
            s = SCREENS[name]
            checkpoints = [
                p
                for p in (out / name / f"{s.method}_seed{k}" / "checkpoint.pt" for k in args.seeds)
                if p.is_file()
            ]
            if not checkpoints:
                print(f"{name}: no checkpoint, not evaluated", flush=True)
                continue
            evaluate(out / name, checkpoints, trials, steps, args.smoke)
            keep(out / name, records / name)
    report(records, page / "results.json", page / "README.md", budget, command)


if __name__ == "__main__":
    main()
