"""Where the paper says consistency matters: a screen's ICCO against ICCO w/o CE (issue 48, 3).

    python experiments/consistency/where.py --chosen ce1          # evaluate, then where.json
    python experiments/consistency/where.py --report-only         # where.json from the evaluations
    python experiments/consistency/where.py --five-m              # the 5M runs, into where_5m.json

Both teams are the screen's own records (``records/<screen>/*/policy.pt``, 2 seeds each, trained
by ``run.py``), so nothing is retrained. Each setting is one evaluation of the four policies
with the scripted references on the same episodes:

- ``ambiguous``: ``icco instruct "Spread out; Gather center"`` (offline planner, plans served),
  20 trials per seed: team reward, and ``in_place`` (a person's reading of the instruction,
  ``evaluation/placement.py``) per instruction;
- ``team 5``, ``team 6``: four quadrants with ``eval.team_size`` 5 and 6 (trained on 3: zero
  shot), with the coordination measures (``docs/consistency.md``);
- ``broadcast 0.5``: four quadrants with ``eval.broadcast_threshold=0.5`` (a robot gets a new z
  only when it moved by more than 0.5; experiments/team_size: about a quarter of the every-T
  broadcasts), with the coordination measures.

``--five-m`` holds the 5M reproduction's ICCO (at the default weight) against its ICCO w/o CE
instead, 3 seeds each, their policies kept in ``experiments/four_quadrants/5m/records``, in the
setting ``as trained`` (four quadrants with the coordination measures) and in each of the above
(``--settings`` narrows them), into ``where_5m.json``.

``where.json`` holds, per setting and team: reward (mean ± std over trials, seeds pooled; share of
the best scripted team's), the setting's measures (mean ± std over seeds) and the verdict of the
chosen screen against ICCO w/o CE (``experiments/verdict.py``). ``run.py --report-only`` renders
it into this folder's README.
"""

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from icco_torchrl.evaluation.metrics import write_json

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from verdict import (  # noqa: E402
    Mean,
    best_scripted,
    compare,
    digits,
    episode_mean,
    read_rows,
    share_entry,
)

BASELINE = "wo_ce"
AMBIGUOUS = ("Spread out", "Gather center")
SETTINGS = {
    "ambiguous": ("instruct", []),
    "team 5": ("eval", ["eval.team_size=5"]),
    "team 6": ("eval", ["eval.team_size=6"]),
    "broadcast 0.5": ("eval", ["eval.broadcast_threshold=0.5"]),
    "as trained": ("eval", []),  # --five-m's own setting
}
FIVE_M = HERE.parent / "four_quadrants" / "5m" / "records"
FIVE_M_TEAM = "icco_5m"
COORDINATION = ("mi_bound", "mi_null", "consistency")  # of docs/consistency.md


def policies(records: Path, screen: str) -> list[Path]:
    found = sorted((records / screen).glob("*/policy.pt"))
    if not found:
        raise SystemExit(f"{records / screen}: no policy.pt (train and keep it with run.py)")
    return found


def five_m_policies(method: str) -> list[Path]:
    found = sorted(FIVE_M.glob(f"{method}_seed*/policy.pt"))
    if not found:
        raise SystemExit(f"{FIVE_M}: no {method}_seed*/policy.pt (the 5M reproduction keeps them)")
    return found


def evaluate(out: Path, setting: str, checkpoints: list[Path], trials: int) -> None:
    command, overrides = SETTINGS[setting]
    folder = out / setting.replace(" ", "_")
    args = [
        f"eval.checkpoints=[{','.join(map(str, checkpoints))}]",
        f"eval.trials={trials}",
        *overrides,
        f"eval.out_dir={folder}",
        f"hydra.run.dir={folder}",
    ]
    if command == "instruct":
        args = ["; ".join(AMBIGUOUS), *args, "llm=offline"]
    else:
        args = [*args, "eval.protocol=quadrants"]
    print(f"$ icco {command} " + " ".join(args), flush=True)
    subprocess.run([sys.executable, "-m", "icco_torchrl", command, *args], check=True)


def key(path) -> tuple[str, ...]:
    """A policy's name in an evaluation, wherever the clone lies: ``(screen, run, file)``."""
    return Path(path).parts[-3:]


def setting_results(folder: Path, command: str, teams: dict[str, list[Path]]) -> dict:
    """Each team's reward and measures in one setting's evaluation ``folder``."""
    name = "instruct" if command == "instruct" else "quadrants"
    rows = read_rows(folder / f"{name}_trials.csv")
    best = best_scripted(rows)
    out = {"best_scripted": share_entry(best, best)}
    entries = {
        key(c["path"]): c for c in json.loads((folder / f"{name}.json").read_text())["checkpoints"]
    }
    for team, paths in teams.items():
        mine = {key(p) for p in paths}
        own = [r for r in rows if key(r["checkpoint"]) in mine]
        result = {"reward": share_entry(episode_mean(own), best)}
        if command == "instruct":
            for text in AMBIGUOUS:
                result[f"in_place: {text}"] = share_entry(episode_mean(own, "in_place", text), None)
        else:
            coordination = [entries[key(p)].get("coordination") or {} for p in paths]
            for measure in COORDINATION:
                values = [c[measure] for c in coordination if c.get(measure) is not None]
                if not values:
                    result[measure] = None
                    continue
                spread = Mean(float(np.mean(values)), float(np.std(values)), len(values))
                result[measure] = share_entry(spread, None)
        out[team] = result
    return out


def verdicts(res: dict, chosen: str) -> dict:
    """The chosen screen against ICCO w/o CE on each setting's reward and measures."""
    out = {}
    for setting, teams in res.items():
        a, b = teams.get(chosen) or {}, teams.get(BASELINE) or {}
        out[setting] = {
            key: compare(
                Mean(a[key]["mean"], a[key]["std"], a[key]["n"]),
                Mean(b[key]["mean"], b[key]["std"], b[key]["n"]),
            ).text(digits(key))
            for key in a
            if a.get(key) and b.get(key)
        }
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--chosen", help="the screen to hold against wo_ce (e.g. ce1)")
    parser.add_argument("--records", type=Path, default=HERE / "records")
    parser.add_argument("--out", type=Path, default=Path("multirun/consistency_where"))
    parser.add_argument("--trials", type=int, default=20)
    screened = [s for s in SETTINGS if s != "as trained"]
    parser.add_argument("--settings", nargs="+", choices=screened, default=screened)
    parser.add_argument("--results", type=Path, default=HERE / "where.json")
    parser.add_argument("--report-only", action="store_true")
    parser.add_argument("--five-m", action="store_true", help="the 5M runs (see above)")
    args = parser.parse_args(argv)
    if args.five_m:
        args.settings = ["as trained", *args.settings]
        args.results = (
            HERE / "where_5m.json" if args.results == HERE / "where.json" else args.results
        )
        args.out = args.out.with_name(args.out.name + "_5m")
    previous = json.loads(args.results.read_text()) if args.results.is_file() else {}
    chosen = FIVE_M_TEAM if args.five_m else args.chosen or previous.get("chosen")
    if chosen is None:
        raise SystemExit("--chosen: which screen to hold against wo_ce (e.g. --chosen ce1)")
    out = args.out.resolve()
    if args.five_m:
        teams = {chosen: five_m_policies("icco"), BASELINE: five_m_policies("icco_wo_ce")}
    else:
        teams = {chosen: policies(args.records, chosen), BASELINE: policies(args.records, BASELINE)}
    if not args.report_only:
        for setting in args.settings:
            evaluate(out, setting, [p for paths in teams.values() for p in paths], args.trials)
    settings = {
        s: setting_results(out / s.replace(" ", "_"), SETTINGS[s][0], teams)
        for s in SETTINGS
        if (out / s.replace(" ", "_")).is_dir()
    }
    if not settings:  # never overwrite the results with nothing
        raise SystemExit(f"{out}: no evaluations here (run without --report-only, or name --out)")
    trials = previous.get("trials", args.trials) if args.report_only else args.trials
    res = {"chosen": chosen, "baseline": BASELINE, "trials": trials, "settings": settings}
    res["verdicts"] = verdicts(settings, chosen)
    write_json(res, args.results)
    print(f"results: {args.results}", flush=True)


if __name__ == "__main__":
    main()
