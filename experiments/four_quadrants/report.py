"""Write the four-quadrant README from a sweep folder (see ``run.py``).

    python experiments/four_quadrants/report.py multirun/four_quadrants [--readme PATH]
    python experiments/four_quadrants/report.py --from-results [--readme PATH]

Reads ``<sweep>/eval_quadrants/quadrants.json`` (from ``icco eval``), the runs' CSVs and
``<sweep>/sweep.json`` (budget, machine, wall time), copies the PNG figures next to the README
and fills ``README.template.md``. With ``--records DIR`` (``run.py --records``) the table, the
bars and the curves pool every run record in ``DIR`` instead, whichever machine trained it.
The comparison with the paper is computed from the numbers, not written in advance, each
verdict by the rule of ``experiments/verdict.py`` (n: trials pooled across seeds), and a
method without a checkpoint is listed as missing. ``--from-results`` rewrites only that
comparison, from the ``results.json`` beside the README (where the sweep is not on this
machine); the rest of the page stays as rendered. With ``--records`` and no ``sweep.json`` (the
sweep is not on this machine), the page's reproduce lines, note and budget section stay as
rendered and the rest is rendered from the records.

``--from-results --references TRIALS`` (a ``references_trials.csv``: the scripted references'
rows on this protocol's episodes, from any ``icco eval eval.protocol=quadrants eval.trials=20``
at seed 0, e.g. ``checkpoint=assets/demo_icco.pt``) gives a page without records the references
it lacks (the best scripted team) and every row its share of the best scripted team's reward:
in ``results.json``, and in the page's tables, whose other rows stay as rendered (the bar
figure too). The references the page has must come out of ``TRIALS`` with the same numbers
(the same episodes), or nothing is written.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shlex
import shutil
import sys
from pathlib import Path
from string import Template

from icco_torchrl import methods
from icco_torchrl.envs.reference_policies import REFERENCE_POLICIES
from icco_torchrl.evaluation.metrics import (
    EPISODE,
    SHARE,
    SHARE_KEY,
    learning_curves,
    markdown_table,
    result_name,
    results_json,
    segment_table,
    share_text,
    summarize,
    write_json,
)
from icco_torchrl.evaluation.plots import plot_bars, plot_curves
from icco_torchrl.training.logger import clock_seconds

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
import jobs  # noqa: E402  (experiments/jobs.py)
import verdict  # noqa: E402  (experiments/verdict.py: the rule every page judges gaps by)
from aggregate import find_runs, markdown_rows, table_at, table_rows  # noqa: E402  (experiments/aggregate.py, a sibling script)

EXPECTED = [methods.label(name) for name in methods.names()]
COLUMNS = (
    "reward",
    "task_reward",
    "inst_reward",
    "pick",
    "collect",
    "defense",
    "invasion",
    "waypoint_dist",
    "in_quadrant",
)
SMOKE_FRAMES = 100_000  # below this a run has learned nothing worth comparing
# The project's target for a learned team: this share of the best scripted team's reward on the
# same episodes (reference_policies.BEST_SCRIPTED); the moonshot is all of it.
TARGET_SHARE, MOONSHOT_SHARE = 0.9, 1.0
# Why the best scripted team is the yardstick (and why collecting is not reward-optimal).
CALIBRATION = HERE.parent / "calibration" / "README.md"


def _mean(xs: list[float]) -> float:
    return sum(xs) / len(xs) if xs else math.nan


def _duration(seconds: float | None) -> str:
    if seconds is None:
        return "?"
    hours, minutes = divmod(round(seconds / 60), 60)
    return f"{hours} h {minutes:02d} min" if hours else f"{seconds / 60:.1f} min"


def sweep_note(info: dict) -> str:
    """The sweep's own remark on how it was run (``"note"`` in ``sweep.json``), as a quote."""
    note = info.get("note")
    if not note:
        return ""
    return "\n".join(f"> {line}".rstrip() for line in note.strip().splitlines()) + "\n\n"


def budget_section(runs: dict[str, list[Path]], info: dict) -> tuple[str, bool]:
    """Frames, wall time and SPS per method, then the machine; and whether it is a smoke budget."""
    lines = [
        "| method | runs | env steps per run | training wall time per run | env steps / s |",
        "|---|---|---|---|---|",
    ]
    smoke = False
    for label, dirs in runs.items():
        timing = [row for d in dirs if (row := jobs.last_row(d / "timing.csv"))]
        frames = [float(r["frames"]) for r in timing]
        wall = [clock_seconds(r) for r in timing]
        sps = [float(r["sps"]) for r in timing]
        smoke |= bool(frames) and max(frames) < SMOKE_FRAMES
        lines.append(
            f"| {label} | {len(dirs)} | {_mean(frames):,.0f} | {_mean(wall) / 60:.1f} min | "
            f"{_mean(sps):,.0f} |"
        )
    m = info.get("machine", {})
    # The seeds of the runs shown (record folders <method>_seed<seed>), else those run.py was given.
    named = [d.name.rpartition("_seed")[2] for dirs in runs.values() for d in dirs]
    seeds = sorted({int(s) for s in named if s.isdigit()}) or info.get("seeds", "?")
    lines += [
        "",
        f"Training overrides: `{' '.join(info.get('budget', [])) or '(defaults)'}`; seeds "
        f"{seeds}. Training wall time summed over run.py invocations (parallel "
        f"invocations add up): {_duration(info.get('train_wall_s'))}; "
        f"{_duration(info.get('eval_wall_s'))} evaluation.",
        f"Machine: {m.get('cpu', '?')} ({m.get('cores', '?')} cores), GPU: "
        f"{m.get('gpu') or 'none'}, torch {m.get('torch', '?')}, Python {m.get('python', '?')}, "
        f"{m.get('platform', '?')}.",
    ]
    return "\n".join(lines), smoke or bool(info.get("smoke"))


def _rule_line(rows: dict) -> str:
    """The verdict rule and each row's n (trials pooled across seeds)."""
    return (
        f"- **How to read the verdicts.** {verdict.RULE} n = trials pooled across seeds: "
        + verdict.pooled_n({name: r["n"] for name, r in rows.items()})
        + "."
    )


def calibration_link(readme: Path) -> str:
    """The calibration page (why the best scripted team is the yardstick) relative to ``readme``."""
    return Path(os.path.relpath(CALIBRATION, Path(readme).resolve().parent)).as_posix()


def comparison(
    summary: list[dict], missing: list[str], calibration: str = "../calibration/README.md"
) -> str:
    """Statements of the paper's findings, each judged on these numbers by ``verdict.py``;
    ``calibration``: the link to the calibration page from the page's folder."""
    every = {r["method"]: r for r in summary if r["segment"] == EPISODE}
    refs = {name: r for name, r in every.items() if result_name(name) in REFERENCE_POLICIES}
    rows = {name: r for name, r in every.items() if name not in refs}
    if "ICCO" not in rows or len(rows) < 2:
        return (
            "Not enough methods were evaluated to compare (ICCO and at least one baseline are "
            "needed)."
        )
    ranked = sorted(rows.values(), key=lambda r: r["reward"], reverse=True)
    order = " > ".join(f"{r['method']} ({r['reward']:.1f})" for r in ranked)
    icco, others = rows["ICCO"], [r for r in ranked if r["method"] != "ICCO"]
    mean = verdict.Mean.of_row
    gaps = {r["method"]: verdict.compare(mean(icco), mean(r)) for r in others}
    lines = [
        _rule_line(every),
        f"- **Paper: ICCO gets the highest reward**: {verdict.claim(g.word for g in gaps.values())}"
        f". Ranking: {order}. ICCO against "
        + "; ".join(f"{name}: {g.text()}" for name, g in gaps.items())
        + ".",
    ]
    parts, words = [], []
    for metric in ("collect", "defense"):
        against = {
            r["method"]: verdict.compare(mean(icco, metric), mean(r, metric)) for r in others
        }
        words += [g.word for g in against.values()]
        parts.append(
            f"{metric} ICCO {icco[metric]:.1f} ± {icco[f'{metric}_std']:.1f}, against "
            + ", ".join(
                f"{name} {rows[name][metric]:.1f}: {g.text()}" for name, g in against.items()
            )
        )
    lines.append(
        "- **Paper: the baselines fail at collecting and defending; ICCO does both** (read here "
        "as: ICCO delivers and defends more than each baseline; a statement of what the teams do, "
        "not of what earns reward: under the calibrated reward collecting is not reward-optimal, "
        "the best scripted team collects only near its robots and leaves the rest, see "
        f"[the calibration]({calibration})): {verdict.claim(words)}. Per episode: "
        + "; ".join(parts)
        + "."
    )
    follow = ", ".join(f"{r['method']} {r['in_quadrant']:.2f}" for r in ranked)
    lines.append(
        "- **Paper: all methods follow the quadrant (ICCO approximately).** Fraction of "
        f"robot-steps inside the instructed quadrant: {follow}."
    )
    flat = rows.get(methods.label("qmix_full_flat"))
    if flat is not None:
        gap = verdict.compare(mean(icco), mean(flat))
        lines.append(
            "- **Paper: ICCO gets more reward than QMIX (FULL), against the paper's QMIX (FULL)** "
            "(the global state as one flat vector; `qmix_full` reads it as relative entity "
            f"tokens): {verdict.claim([gap.word])}. ICCO {icco['reward']:.1f} vs "
            f"{flat['reward']:.1f}: {gap.text()}."
        )
    lines += criteria(rows, refs, calibration)
    if missing:
        lines.append(f"- Missing from this comparison (no checkpoint): {', '.join(missing)}.")
    lines.append(
        "- Our environment is a re-implementation (geometry scaled from COPA, see docs/task.md), "
        "so absolute rewards differ from the paper's; the ordering is what to compare."
    )
    return "\n".join(lines)


def criteria(rows: dict, refs: dict, calibration: str = "../calibration/README.md") -> list[str]:
    """The project's target, checked for ICCO and QMIX (FULL): a team's reward as a share of the
    best scripted team's on the same episodes, at least :data:`TARGET_SHARE` of it (the moonshot:
    :data:`MOONSHOT_SHARE`). Each check is ``verdict.compare(team, best scripted, share)``, the
    gap ``a - share x b``."""
    best = next((r for name, r in refs.items() if result_name(name) == "best_scripted"), None)
    if best is None:
        return [
            f"- **Target: a learned team earns at least {100 * TARGET_SHARE:.0f} % of the best "
            f"scripted team's reward**: {verdict.MISSING} (no best scripted row on these episodes)."
        ]
    lines = [
        f"- **Target: a learned team earns at least {100 * TARGET_SHARE:.0f} % of the best "
        f"scripted team's reward on the same episodes** (the {best['method']}, "
        f"{best['reward']:.1f}; "
        f"moonshot {100 * MOONSHOT_SHARE:.0f} %; why this yardstick: [the calibration]"
        f"({calibration})), judged on team reward - {TARGET_SHARE:g} x the best scripted team's:"
    ]
    mean = verdict.Mean.of_row
    for name in ("ICCO", "QMIX (FULL)"):
        if name not in rows:
            continue
        r = rows[name]
        target = verdict.compare(mean(r), mean(best), TARGET_SHARE)
        moonshot = verdict.compare(mean(r), mean(best), MOONSHOT_SHARE)
        share = r["reward"] / best["reward"] if best["reward"] > 0 else math.nan
        lines.append(
            f"  - {name}: {verdict.claim([target.word])}. {100 * share:.0f} % of the best scripted "
            f"team's reward ({r['reward']:.1f} vs {best['reward']:.1f}); against "
            f"{100 * TARGET_SHARE:.0f} %: {target.text()}; against {100 * MOONSHOT_SHARE:.0f} % "
            f"(moonshot): {moonshot.text()}."
        )
    return lines


def summary_from_results(results: dict) -> list[dict]:
    """Whole-episode summary rows (label, ``n``, ``seeds``, ``{metric}`` and ``{metric}_std``)
    from a ``results.json``: what :func:`comparison` reads, n being the trials per checkpoint
    pooled across seeds (a reference's: its trials)."""
    rows = []
    for name, entry in results["methods"].items():
        if name in REFERENCE_POLICIES or "label" in entry:
            label = entry.get("label", name)
        else:
            label = methods.label(name)
        row = dict(
            method=label,
            segment=EPISODE,
            n=results["trials"] * max(entry["seeds"], 1),
            seeds=max(entry["seeds"], 1),
        )
        for metric in COLUMNS:
            value = entry.get(metric, {"mean": math.nan, "std": math.nan})
            row[metric], row[f"{metric}_std"] = value["mean"], value["std"]
        rows.append(row)
    return rows


COMPARISON_HEADING = "## Comparison with the paper\n\n"


def rewrite_comparison(readme: Path) -> Path:
    """Rewrite the comparison section of ``readme`` from the ``results.json`` beside it (the
    section the template ends with); the tables and figures stay as rendered."""
    results = json.loads((readme.parent / "results.json").read_text())
    summary = summary_from_results(results)
    present = {r["method"] for r in summary}
    missing = [label for label in EXPECTED if label not in present]
    text = readme.read_text()
    head = text[: text.index(COMPARISON_HEADING) + len(COMPARISON_HEADING)]
    readme.write_text(head + comparison(summary, missing, calibration_link(readme)) + "\n")
    return readme


REPRODUCE, RESULTS_HEADING = "**Reproduce.**", "## Results\n\n"
TOLERANCE = 1e-5  # a reference reproduced on another machine: float32 sums in another order


def _share_cell(entry: dict) -> str:
    return share_text(entry.get(SHARE_KEY))


def _is_reference(label: str) -> bool:
    return result_name(label) in REFERENCE_POLICIES


def check_references(results: dict, added: dict) -> None:
    """Every reference ``results`` has must be in ``added`` (``results_json`` entries) with the
    same numbers, to :data:`TOLERANCE`: the same episodes; a one-line error otherwise."""
    for name, bad in verdict.unreproduced_references(results, added, TOLERANCE):
        raise SystemExit(
            f"report.py: the references' trials do not reproduce the page's {name} "
            f"({bad or 'missing'}): not the page's episodes, nothing written"
        )


def add_references(readme: Path, trials: Path) -> Path:
    """Give ``readme`` and its ``results.json`` the references of ``trials`` they lack and every
    row its share of the best scripted team's reward (see the module doc), then rewrite the
    comparison (:func:`rewrite_comparison`)."""
    path = readme.parent / "results.json"
    results = json.loads(path.read_text())
    rows = _read_trials(trials)
    if len({r["trial"] for r in rows}) != results["trials"]:
        raise SystemExit(f"report.py: {trials} has not the page's {results['trials']} trials")
    summary = summarize(rows, by=("method", "segment"))
    added = results_json(
        summary, protocol=results["protocol"], steps=results["steps"], trials=results["trials"]
    )["methods"]
    check_references(results, added)
    if "best_scripted" not in added:
        raise SystemExit(f"report.py: {trials} has no best scripted rows")
    for name, entry in added.items():
        results["methods"].setdefault(name, entry)
    best = results["methods"]["best_scripted"]["reward"]["mean"]
    for entry in results["methods"].values():
        entry[SHARE_KEY] = entry["reward"]["mean"] / best if best > 0 else None
    text = readme.read_text()

    # The whole-episode table: the learned rows as rendered, the references from ``trials``.
    start, end, table = table_at(text, "| method | trials |")
    head = [c for c in table[0] if c != SHARE]
    width = len(head)
    refs = table_rows(markdown_table(summary, head[2:]))[2:]
    learned = [r[:width] for r in table[1:] if not _is_reference(r[0]) and r[1] != "missing"]
    missing = [r[:width] for r in table[1:] if r[1] == "missing"]
    new = [
        [*r, _share_cell(results["methods"][result_name(r[0])]) if r[1] != "missing" else "–"]
        for r in learned + [r[:width] for r in refs] + missing
    ]
    text = text[:start] + markdown_rows([[*head, SHARE], *new]) + text[end:]

    # The reward per quadrant: the same.
    start, end, table = table_at(text, "| method | quadrant 1 |")
    refs = table_rows(segment_table(summary, "reward"))
    if refs[0] != table[0]:
        raise SystemExit(f"report.py: {trials} has other segments than the page ({refs[0]})")
    learned = [r for r in table[1:] if not _is_reference(r[0])]
    text = text[:start] + markdown_rows([table[0], *learned, *refs[2:]]) + text[end:]

    # The results' introduction, as the template words it now.
    template = (HERE / "README.template.md").read_text()
    intro = template[template.index(RESULTS_HEADING) : template.index("$table")]
    intro = Template(intro).substitute(
        episode_steps=results["steps"], calibration=calibration_link(readme)
    )
    start = text.index(RESULTS_HEADING)
    end = text.index("| method | trials |", start)
    write_json(results, path)
    readme.write_text(text[:start] + intro + text[end:])
    return rewrite_comparison(readme)


def _number(value: str):
    try:
        return float(value)
    except ValueError:
        return value


def _read_trials(path: Path) -> list[dict]:
    """A trials CSV back to rows: numbers as floats, labels as strings."""
    with path.open() as handle:
        rows = [{k: _number(v) for k, v in r.items()} for r in csv.DictReader(handle)]
    for row in rows:
        row["method"], row["segment"] = str(row["method"]), str(row["segment"])
    return rows


def pooled_records(records: Path) -> tuple[list[dict], list[dict], list[Path]]:
    """Trial rows, checkpoint entries and run folders of every record in ``records`` (see
    ``jobs.keep_records``), methods in the paper's order, then the scripted references."""
    order = {label: i for i, label in enumerate(EXPECTED)}
    entries = []
    for path in records.glob("*/checkpoint.json"):
        entry = json.loads(path.read_text())
        entries.append((order.get(entry["method"], len(order)), entry["seed"], path.parent, entry))
    entries.sort(key=lambda e: e[:2])
    jobs.check_one_recipe({folder: entry["method"] for *_, folder, entry in entries})
    rows = [row for *_, folder, _ in entries for row in _read_trials(folder / "trials.csv")]
    references = records / jobs.REFERENCES_TRIALS
    if references.is_file():
        rows += _read_trials(references)
    return rows, [e[-1] for e in entries], [e[2] for e in entries]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("sweep", type=Path, nargs="?", help="the sweep folder written by run.py")
    parser.add_argument("--readme", type=Path, default=HERE / "README.md")
    parser.add_argument("--records", type=Path, help="pool the run records in this folder")
    parser.add_argument(
        "--from-results",
        action="store_true",
        help="only rewrite the comparison section from the results.json beside the README",
    )
    parser.add_argument(
        "--references",
        type=Path,
        help="with --from-results: add the references of this references_trials.csv",
    )
    args = parser.parse_args(argv)
    if args.references is not None and not args.from_results:
        parser.error("--references goes with --from-results (--records reads its own)")
    if args.from_results:
        if args.references is not None:
            page = add_references(args.readme, args.references)
            print(f"added the references of {args.references} to {page}")
        else:
            print(f"rewrote the comparison of {rewrite_comparison(args.readme)}")
        return 0
    if args.sweep is None:
        parser.error("the sweep folder is needed (or --from-results)")
    results = args.sweep / "eval_quadrants" / "quadrants.json"
    if args.records is not None:
        rows, checkpoints, record_runs = pooled_records(args.records)
        if not checkpoints:
            print(f"report.py: no run records in {args.records}", file=sys.stderr)
            return 2
        summary = summarize(rows, by=("method", "segment"))
        payload = dict(
            checkpoints=checkpoints,
            trials=len({r["trial"] for r in rows}),
            segment_steps={r["segment"]: int(r["steps"]) for r in rows if r["segment"] != EPISODE},
        )
    elif not results.is_file():
        print(
            f"report.py: {results} not found: run experiments/four_quadrants/run.py (or icco eval) "
            "first",
            file=sys.stderr,
        )
        return 2
    else:
        payload = json.loads(results.read_text())
        summary = [
            {k: (math.nan if v is None else v) for k, v in row.items()}
            for row in payload["summary"]
        ]
    info_path = args.sweep / "sweep.json"
    info = json.loads(info_path.read_text()) if info_path.is_file() else {}
    # Records without their sweep on this machine: what only the sweep knows stays as rendered.
    kept = None
    if args.records is not None and not info_path.is_file() and args.readme.is_file():
        rendered = args.readme.read_text()
        kept = rendered[rendered.index(REPRODUCE) : rendered.index(RESULTS_HEADING)]
        old_results = args.readme.parent / "results.json"
        if old_results.is_file():
            info["budget"] = json.loads(old_results.read_text()).get("budget")
    if args.records is not None:  # the seeds of the records, not of this machine's invocation
        info["seeds"] = sorted({c["seed"] for c in payload["checkpoints"]})
    present = {r["method"] for r in summary}
    missing = [label for label in EXPECTED if label not in present]

    figures = args.readme.parent / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    for name in ("quadrants_reward.png", "quadrants_trajectories.png"):
        if (args.sweep / "eval_quadrants" / name).is_file():  # this machine's evaluation
            shutil.copyfile(args.sweep / "eval_quadrants" / name, figures / name)
    if args.records is not None:
        segments = [*payload["segment_steps"], EPISODE]
        plot_bars(summary, figures / "quadrants_reward", segments=segments, ylabel="team reward")
        (figures / "quadrants_reward.pdf").unlink()
    found = find_runs(record_runs if args.records is not None else [args.sweep])
    runs = {
        label: found[label] for label in [*EXPECTED, *found] if label in found
    }  # the paper's order
    curves = learning_curves(runs)
    if curves:
        plot_curves(curves, figures / "learning_curves")
        (figures / "learning_curves.pdf").unlink()  # the README shows PNGs; PDFs stay in the sweep

    budget, smoke = budget_section(runs, info)
    banner = (
        "> **Smoke budget: these numbers only show that the pipeline runs end to end; the policies "
        "have learned nothing. Re-run without `--smoke` for results.**"
        if smoke
        else ""
    )
    steps = payload["segment_steps"]["quadrant 1"]
    if info.get("smoke"):
        budget_args = "--smoke"
    else:
        budget_args = " ".join(shlex.quote(a) for a in ["--budget", *info.get("budget", [])])
    page = []  # where this page and its records live, when not the default
    if args.readme.resolve() != (HERE / "README.md").resolve():
        page += ["--readme", os.path.relpath(args.readme)]
    if args.records is not None:
        page += ["--records", os.path.relpath(args.records)]
    page_args = "".join(" " + shlex.quote(a) for a in page)
    if os.path.relpath(args.sweep) != os.path.join("multirun", "four_quadrants"):
        budget_args += " --sweep " + shlex.quote(os.path.relpath(args.sweep))
    text = Template((HERE / "README.template.md").read_text()).substitute(
        banner=banner,
        steps=steps,
        episode_steps=4 * steps,
        trials=payload["trials"],
        budget_args=budget_args + page_args,
        sweep=shlex.quote(os.path.relpath(args.sweep)) + page_args,
        note=sweep_note(info),
        budget=budget,
        table=markdown_table(summary, COLUMNS, missing=missing),
        segment_table=segment_table(summary, "reward"),
        comparison=comparison(summary, missing, calibration_link(args.readme)),
        calibration=calibration_link(args.readme),
    )
    if kept is not None:
        text = text[: text.index(REPRODUCE)] + kept + text[text.index(RESULTS_HEADING) :]
    args.readme.write_text(text)
    frames = {}
    for c in payload["checkpoints"]:
        frames[c["method"]] = max(frames.get(c["method"], 0), c.get("frames") or 0)
    write_json(
        results_json(
            summary,
            protocol="quadrants",
            steps=4 * steps,
            trials=payload["trials"],
            frames=frames,
            budget=info.get("budget"),
        ),
        args.readme.parent / "results.json",
    )
    print(f"wrote {args.readme} and results.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
