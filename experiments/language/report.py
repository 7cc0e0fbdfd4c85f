"""Write the language README from the folder ``run.py`` wrote (``fig5b/`` and ``table2_tap/``).

    python experiments/language/report.py multirun/language [--readme PATH]
    python experiments/language/report.py --references experiments/language/references
    python experiments/language/report.py --table2 multirun/language_5m_tap --readme PAGE

Tables come from the ``icco instruct`` outputs; the comparison with the paper is computed from
the numbers, each verdict by the rule of ``experiments/verdict.py`` (n: trials pooled across
seeds; Table II's, instruction segments). A method the paper compares but this run lacks is
listed as missing. Every table row that has a best scripted row beside it gets its share of the
best scripted team's reward on the same episodes.

``--references DIR`` serves a page whose run folder is not on this machine: ``DIR`` holds the
scripted references' trial rows on this protocol's episodes, ``fig5b_trials.csv`` (from
``icco instruct "Go right; Move top; Gather center; Spread out" eval.trials=20 eval.steps=145``
at seed 0 with the offline planner and any checkpoint of the team size, e.g.
``checkpoint=assets/demo_icco.pt``: the references need one only for the size) and
``table2_tap_trials.csv`` (the same with ``llm.prompt=tap``). The page and its ``results.json``
get the references they lack (the best scripted team; Table II's only where the page has a
task-aligned run) and every row its share; the other rows, the figures and the comparison stay
as rendered. The references the page has must come out of ``DIR`` with the same numbers (the
same episodes), or nothing is written.

``--table2 DIR`` adds Table II's task-aligned runs to a page that has Fig. 5b: ``DIR`` is a folder
of ``run.py --methods qmix`` (only ``table2_tap/``). The page keeps its ICCO row (its Fig. 5b run,
from its ``results.json``) and gets the QMIX-TAP rows, their references, the verdict and the
planner's statistics; a folder of other instructions, steps or trials is refused.
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

import numpy as np

from icco_torchrl import methods
from icco_torchrl.envs.reference_policies import BEST_SCRIPTED_LABEL, REFERENCE_POLICIES
from icco_torchrl.evaluation.metrics import (
    EPISODE,
    METRICS,
    SHARE,
    SHARE_KEY,
    markdown_table,
    result_name,
    results_json,
    segment_table,
    share_text,
    summarize,
    write_json,
)

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
import verdict  # noqa: E402  (experiments/verdict.py: the rule every page judges gaps by)
from aggregate import markdown_rows, table_at, table_rows  # noqa: E402

TABLE2 = ("QMIX-TAP", "QMIX-TAP w/o TR", "ICCO")
PAPER_TABLE2 = {
    "QMIX-TAP": (5.1, 3.0, 6.8),
    "QMIX-TAP w/o TR": (3.0, 1.1, 2.0),
    "ICCO": (5.6, 3.7, 10.5),
}
COUNTS = ("pick", "collect", "defense")
EPISODE_COLUMNS = ("reward", "pick", "collect", "defense", "invasion", "waypoint_dist")
SMOKE_FRAMES = 100_000
# Why the best scripted team is the yardstick (and why collecting is not reward-optimal).
CALIBRATION = HERE.parent / "calibration" / "README.md"
TOLERANCE = 1e-5  # a reference reproduced on another machine: float32 sums in another order
RECIPE_NOTE = (  # the default page's history; other pages (5m/) have none
    "> **Recipe.** Today's defaults: 16-step replay items, lambda-returns (0.6), collect\n"
    "> shaping in the training env, chosen by the\n"
    "> [sequence-replay screens](../sequence_replay/README.md). This page at the recipe\n"
    "> before them (commit 396580d) is\n"
    "> `git show ae04e50:experiments/language/README.md`.\n"
)


def load(folder: Path) -> tuple[dict, list[dict]]:
    payload = json.loads((folder / "instruct.json").read_text())
    payload["summary"] = [
        {k: (math.nan if v is None else v) for k, v in r.items()} for r in payload["summary"]
    ]
    return payload, list(csv.DictReader((folder / "instruct_trials.csv").open()))


def table2(rows: list[dict], given: dict | None = None) -> tuple[str, dict]:
    """Markdown of picks/collects/defenses per instruction segment, and ``{method: (Mean, ...)}``
    (``verdict.Mean`` per count, n = the method's instruction segments, seeds pooled). ``given``:
    rows already reduced to their means (a page's own ICCO row, :func:`add_table2`)."""
    lines = [
        "| method | segments | pick | collect | defense | paper (pick / collect / defense) |",
        "|---|---|---|---|---|---|",
    ]
    means = dict(given or {})
    for method in TABLE2:
        segs = [r for r in rows if r["method"] == method and r["segment"] != EPISODE]
        if segs:
            values = {k: np.array([float(r[k]) for r in segs]) for k in COUNTS}
            means[method] = tuple(
                verdict.Mean(float(values[k].mean()), float(values[k].std()), len(segs))
                for k in COUNTS
            )
        paper = " / ".join(f"{v:.1f}" for v in PAPER_TABLE2[method])
        if method not in means:
            lines.append(f"| {method} | missing | – | – | – | {paper} |")
            continue
        cells = " | ".join(f"{m.mean:.1f} ± {m.std:.1f}" for m in means[method])
        lines.append(f"| {method} | {means[method][0].n} | {cells} | {paper} |")
    # The scripted reference policies, driven by the same task-aligned plans (extra rows, not in the
    # paper).
    for method in dict.fromkeys(
        r["method"] for r in rows if result_name(r["method"]) in REFERENCE_POLICIES
    ):
        segs = [r for r in rows if r["method"] == method and r["segment"] != EPISODE]
        values = {k: np.array([float(r[k]) for r in segs]) for k in COUNTS}
        cells = " | ".join(f"{values[k].mean():.1f} ± {values[k].std():.1f}" for k in COUNTS)
        lines.append(f"| {method} (reference) | {len(segs)} | {cells} | – |")
    return "\n".join(lines), means


def _per_instruction(cell: dict, a: str, b: str, segments: list[str]) -> tuple[str, str]:
    """``a`` against ``b`` on every instruction's reward: the claim's verdict and the detail."""
    gaps = {
        s: verdict.compare(verdict.Mean.of_row(cell[a, s]), verdict.Mean.of_row(cell[b, s]))
        for s in segments
    }
    counts = {w: sum(g.word == w for g in gaps.values()) for w in (verdict.AHEAD, verdict.BEHIND)}
    detail = (
        f"{a} is ahead on {counts[verdict.AHEAD]} and behind on {counts[verdict.BEHIND]} of "
        f"{len(segments)} instructions ("
        + "; ".join(f"{s}: {g.text()}" for s, g in gaps.items())
        + f"); whole episode {cell[a, EPISODE]['reward']:.1f} vs {cell[b, EPISODE]['reward']:.1f}"
    )
    return verdict.claim(g.word for g in gaps.values()), detail


TABLE2_N = "; Table II: instruction segments, "


def table2_n(means: dict) -> str:
    """Table II's trials as the verdict line counts them (instruction segments per method)."""
    return verdict.pooled_n({m: v[0].n for m, v in means.items()})


def table2_claim(means: dict) -> str:
    """The paper's Table II ordering, ICCO > QMIX-TAP > QMIX-TAP w/o TR, judged per count."""
    if len(means) < len(TABLE2):
        return (
            f"- Table II: missing {', '.join(m for m in TABLE2 if m not in means)}; no comparison."
        )
    parts, words = [], []
    for i, name in enumerate(COUNTS):
        icco, tap, wo_tr = (means[m][i] for m in ("ICCO", "QMIX-TAP", "QMIX-TAP w/o TR"))
        first, second = verdict.compare(icco, tap), verdict.compare(tap, wo_tr)
        words += [first.word, second.word]
        parts.append(
            f"{name} {verdict.claim([first.word, second.word])} ({icco.mean:.1f} / "
            f"{tap.mean:.1f} / {wo_tr.mean:.1f}; ICCO against QMIX-TAP {first.text(2)}, "
            f"QMIX-TAP against w/o TR {second.text(2)})"
        )
    return (
        "- **Paper (Table II): ICCO > QMIX-TAP > QMIX-TAP w/o TR on picks, deliveries and "
        f"defenses**: {verdict.claim(words)}. Per count: " + "; ".join(parts) + "."
    )


def comparison(fig5b: list[dict], means: dict) -> str:
    """The paper's findings, each judged on these numbers by ``verdict.py``."""
    cell = {(r["method"], r["segment"]): r for r in fig5b}
    episode = {m: r for (m, s), r in cell.items() if s == EPISODE}
    ns = "Fig. 5b: " + verdict.pooled_n({m: r["n"] for m, r in episode.items()})
    if means:
        ns += TABLE2_N + table2_n(means)
    lines = [
        f"- **How to read the verdicts.** {verdict.RULE} n = trials pooled across seeds ({ns})."
    ]
    if ("ICCO", EPISODE) in cell and ("QMIX (FULL)", EPISODE) in cell:
        segments = [s for (m, s) in cell if m == "ICCO" and s != EPISODE]
        held, detail = _per_instruction(cell, "ICCO", "QMIX (FULL)", segments)
        lines.append(
            "- **Paper: ICCO gets more reward than QMIX (FULL) for every instruction**: "
            f"{held}. {detail}."
        )
        if ("ICCO", "Gather center") in cell:
            icco, full = cell["ICCO", "Gather center"], cell["QMIX (FULL)", "Gather center"]
            mean = verdict.Mean.of_row
            gaps = {  # each oriented so that "ahead" is ICCO doing better
                "distance to the waypoints (m)": (
                    verdict.compare(mean(full, "waypoint_dist"), mean(icco, "waypoint_dist")),
                    icco["waypoint_dist"],
                    full["waypoint_dist"],
                    2,
                ),
                "deliveries": (
                    verdict.compare(mean(icco, "collect"), mean(full, "collect")),
                    icco["collect"],
                    full["collect"],
                    1,
                ),
                "defenses": (
                    verdict.compare(mean(icco, "defense"), mean(full, "defense")),
                    icco["defense"],
                    full["defense"],
                    1,
                ),
            }
            lines.append(
                "- **Paper: in Gather Center ICCO gathers and also collects/defends better**: "
                f"{verdict.claim(g.word for g, *_ in gaps.values())}. ICCO vs QMIX (FULL), "
                '"ahead" meaning ICCO does better: '
                + "; ".join(
                    f"{name} {a:.{d}f} vs {b:.{d}f}: {g.text(d)}"
                    for name, (g, a, b, d) in gaps.items()
                )
                + "."
            )
        flat = methods.label("qmix_full_flat")
        if (flat, EPISODE) in cell:  # the paper's own QMIX (FULL): the global state as one vector
            held, detail = _per_instruction(cell, "ICCO", flat, segments)
            lines.append(
                "- **Paper: ICCO gets more reward than QMIX (FULL) for every instruction, against "
                "the paper's QMIX (FULL)** (one flat state vector; `qmix_full` reads relative "
                f"entity tokens): {held}. {detail}."
            )
    else:
        lines.append("- Fig. 5b: ICCO or QMIX (FULL) is missing; no comparison.")
    lines += following_costs(fig5b)
    lines.append(table2_claim(means))
    lines.append(
        "- Our environment is a re-implementation and the default planner is a rule program, so "
        "absolute numbers differ from the paper's; the orderings are what to compare."
    )
    return "\n".join(lines)


def planner_stats(payloads: dict[str, dict]) -> str:
    lines = ["| run | method | requests | rejected attempts | fallbacks |", "|---|---|---|---|---|"]
    for run, payload in payloads.items():
        totals: dict[str, list[int]] = {}
        for s in payload["sources"]:
            t = totals.setdefault(s["method"], [0, 0, 0])
            t[0], t[1], t[2] = t[0] + s["plans"], t[1] + s["failures"], t[2] + s["fallbacks"]
        lines += [f"| {run} | {m} | {a} | {b} | {c} |" for m, (a, b, c) in totals.items()]
    return "\n".join(lines)


def _frames(*payloads: dict) -> dict[str, int]:
    frames: dict[str, int] = {}
    for payload in payloads:
        for c in payload["checkpoints"]:
            frames[c["method"]] = max(frames.get(c["method"], 0), c.get("frames") or 0)
    return frames


def following_costs(summary: list[dict]) -> list[str]:
    """What being in place costs in this reward, from the perfect path follower (``pursuit``,
    which ignores the task) beside the best scripted team (which ignores the instruction where
    the task pays more): one bullet, none when either is missing."""
    cell = {(r["method"], r["segment"]): r for r in summary}
    best = next((m for m, s in cell if s == EPISODE and m.startswith(BEST_SCRIPTED_LABEL)), None)
    if best is None or ("pursuit", EPISODE) not in cell:
        return []
    segments = [s for m, s in cell if m == best and s != EPISODE]

    def places(method: str) -> str:
        return "/".join(f"{100 * cell[method, s].get('in_place', math.nan):.0f}" for s in segments)

    ceiling, top = cell["pursuit", EPISODE]["reward"], cell[best, EPISODE]["reward"]
    share = share_text(ceiling / top if top > 0 else None)
    return [
        "- **Being in place against the reward.** The perfect path follower (`pursuit`, which "
        f"ignores the task) is in place {places('pursuit')} % ({', '.join(segments)}) and earns "
        f"{ceiling:.1f}, {share} of the best scripted team's {top:.1f}; the best scripted team "
        f"is in place {places(best)} %. In this reward a team is paid for the task, not for "
        "standing where it was told, so a team in place at least 80 % of the time earns the best "
        "scripted team's reward only if it still does the task from its slots."
        + "".join(
            " The scripted team of highest reward in place on every instruction (searched in "
            f"experiments/language/frontier), `{m}`, is in place {places(m)} % and earns "
            f"{cell[m, EPISODE]['reward']:.1f}, "
            f"{share_text(cell[m, EPISODE]['reward'] / top if top > 0 else None)}."
            for m, s in cell
            if s == EPISODE and m.endswith("; follow=pursuit)")
        )
    ]


def per_instruction(rows: list[dict]) -> list[dict]:
    """Trial rows as Table II pools them: every instruction segment one row of segment
    ``"instruction"``."""
    out = [
        {
            **{k: float(r[k]) for k in METRICS if r.get(k) not in (None, "")},
            "method": r["method"],
            "seed": r["seed"],
            "segment": "instruction",
        }
        for r in rows
        if r["segment"] != EPISODE
    ]
    for r in out:
        r.setdefault("in_quadrant", math.nan)
    return out


PLAN_TEXT = {
    "served": (
        "the planner is prompted once, per trial, with the robots' positions at that moment, for\n"
        "each robot's route to a slot, and the plan is served as the instruction the team trained\n"
        "on: at every waypoint refresh each robot's K = 4 waypoints start at its position and\n"
        "advance along its route (`icco_torchrl/instructions/serving.py`). The planner is asked\n"
        "again only when an episode starts"
    ),
    "fixed": (
        "the planner is prompted once, per trial, with the robots' positions at that moment, and\n"
        "its K = 4 waypoints per robot are kept for the whole instruction (the old interface, a\n"
        "comparison: `eval.plan=fixed`)"
    ),
}


def placement(summary: list[dict]) -> str:
    """Where the robots are, judged as a person would (``icco_torchrl/evaluation/placement.py``):
    in place per instruction, and over the episode at slot, formation and time to slot."""
    episode = {r["method"]: r for r in summary if r["segment"] == EPISODE}
    segments = list(dict.fromkeys(r["segment"] for r in summary if r["segment"] != EPISODE))
    cell = {(r["method"], r["segment"]): r.get("in_place") for r in summary}

    def shown(value, scale=100.0, unit=" %"):
        return "–" if value is None or value != value else f"{scale * value:.0f}{unit}"

    head = ["method", *segments, "at slot", "formation", "time to slot (steps)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for method, row in episode.items():
        cells = [shown(cell.get((method, s))) for s in segments]
        cells += [shown(row.get("at_slot")), shown(row.get("formation"))]
        cells.append(shown(row.get("time_to_slot"), 1.0, ""))
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def whole_episode(summary: list[dict], missing=(), calibration: str = "../calibration/README.md"):
    """Fig. 5b's whole-episode table with the sentence that introduces it."""
    return (
        "Whole episode. The last rows are the scripted reference policies\n"
        "(`icco_torchrl.envs.reference_policies`) on the same episodes; the best scripted team\n"
        "defends at any distance, collects within 1 m and delivers within 2 m (the best scripted\n"
        f"point at the calibrated reward, see [the calibration]({calibration})).\n"
        f"`{SHARE}`: a team's mean reward over the best scripted team's on the same episodes.\n\n"
        + markdown_table(summary, EPISODE_COLUMNS, missing=missing)
    )


def language_results(
    fig5b: dict, fig5b_rows: list[dict], tap: dict | None, tap_rows: list[dict], steps: int
) -> dict:
    """results.json: Fig. 5b (whole 4-instruction episode) and, under ``table2``, the
    per-instruction means of Table II (ICCO with the plain prompt, QMIX-TAP and QMIX-TAP w/o TR with
    the task-aligned one; ICCO's alone without ``tap``)."""
    n_segments = len(fig5b["segment_steps"])
    out = results_json(
        fig5b["summary"],
        protocol="language",
        steps=steps * n_segments,
        trials=fig5b["trials"],
        frames=_frames(fig5b),
        instructions=list(fig5b["segment_steps"]),
        model=fig5b["model"],
    )
    rows = [r for r in fig5b_rows if r["method"] == "ICCO"] + tap_rows
    out["table2"] = results_json(
        summarize(per_instruction(rows)),
        protocol="language_tap",
        steps=steps,
        trials=fig5b["trials"] * n_segments,
        frames=_frames(fig5b, *([tap] if tap else [])),
        segment="instruction",
    )
    return out


def run_arguments(out: Path, llm: str | None, readme: Path | None) -> str:
    """``run.py``'s arguments for this folder: budget, seeds, and the agents and folders it was
    given (``run.json``, if written); ``readme``: this page, ``None`` for the default one."""
    saved = json.loads((out / "run.json").read_text()) if (out / "run.json").is_file() else {}
    words = ["--budget", *saved["budget"]] if saved.get("budget") else []
    words += ["--seeds", *map(str, saved["seeds"])] if saved.get("seeds") else []
    words += ["--methods", *saved["methods"]] if saved.get("methods") else []
    words += ["--kept-only"] if saved.get("kept_only") else []
    for folder in ("sweep", "wo_tr_sweep", "records", "wo_tr_records", "out"):
        words += [f"--{folder.replace('_', '-')}", saved[folder]] if saved.get(folder) else []
    words += ["--readme", os.path.relpath(readme)] if readme else []
    if llm:
        words += ["--llm", llm]
    return " ".join(shlex.quote(w) for w in words)


def folder_note(out: Path) -> str | None:
    """The folder's own remark on its agents (``"note"`` in ``run.json``), as a quote."""
    saved = json.loads((out / "run.json").read_text()) if (out / "run.json").is_file() else {}
    note = saved.get("note")
    if not note:
        return None
    return "\n".join(f"> {line}".rstrip() for line in note.strip().splitlines()) + "\n"


def calibration_link(readme: Path) -> str:
    """The calibration page (why the best scripted team is the yardstick) relative to ``readme``."""
    return Path(os.path.relpath(CALIBRATION, Path(readme).resolve().parent)).as_posix()


def _read_trials(path: Path) -> list[dict]:
    """A trials CSV back to rows: numbers as floats, labels as strings."""
    rows = list(csv.DictReader(path.open()))
    for row in rows:
        for key, value in row.items():
            if key not in ("method", "segment", "checkpoint"):
                row[key] = float(value)
    return rows


def _reference(label: str) -> bool:
    return result_name(label.removesuffix(" (reference)")) in REFERENCE_POLICIES


def _merge(results: dict, summary: list[dict], segment: str, source: Path) -> None:
    """Add the references of ``summary`` that ``results`` (a ``results_json``) lacks, after
    checking that those it has come out the same (to :data:`TOLERANCE`), and give every entry
    its share of the best scripted team's reward."""
    added = results_json(
        summary,
        protocol=results["protocol"],
        steps=results["steps"],
        trials=results["trials"],
        segment=segment,
    )["methods"]
    for name, bad in verdict.unreproduced_references(results, added, TOLERANCE):
        raise SystemExit(
            f"report.py: {source} does not reproduce the page's {name} ({bad or 'missing'}): "
            "not the page's episodes, nothing written"
        )
    if "best_scripted" not in added:
        raise SystemExit(f"report.py: {source} has no best scripted rows")
    for name, entry in added.items():
        results["methods"].setdefault(name, entry)
    best = results["methods"]["best_scripted"]["reward"]["mean"]
    for entry in results["methods"].values():
        entry[SHARE_KEY] = entry["reward"]["mean"] / best if best > 0 else None


def add_references(readme: Path, folder: Path) -> Path:
    """Give ``readme`` and its ``results.json`` the references of ``folder`` they lack, and every
    row its share of the best scripted team's reward (see the module doc)."""
    path = readme.parent / "results.json"
    results = json.loads(path.read_text())
    fig5b = _read_trials(folder / "fig5b_trials.csv")
    if len({r["trial"] for r in fig5b}) != results["trials"]:
        raise SystemExit(f"report.py: {folder} has not the page's {results['trials']} trials")
    summary = summarize(fig5b)
    _merge(results, summary, EPISODE, folder / "fig5b_trials.csv")
    tap_results = results.get("table2")
    tap = []
    if tap_results and any(not e.get("seeds") for e in tap_results["methods"].values()):
        tap = _read_trials(folder / "table2_tap_trials.csv")
        _merge(tap_results, summarize(per_instruction(tap)), "instruction", folder)
    text = readme.read_text()

    # Fig. 5b per instruction: the learned rows as rendered, the references from ``folder``.
    start, end, table = table_at(text, "| method | " + " | ".join(results["instructions"]))
    refs = table_rows(segment_table(summary, "reward"))
    if refs[0] != table[0]:
        raise SystemExit(f"report.py: {folder} has other instructions than the page ({refs[0]})")
    learned = [r for r in table[1:] if not _reference(r[0])]
    text = text[:start] + markdown_rows([table[0], *learned, *refs[2:]]) + text[end:]

    # The whole episode: the same, and every row's share (results.json's).
    start = text.index("Whole episode")
    _, end, table = table_at(text, "| method | trials |")
    learned = [r for r in table[1:] if not _reference(r[0]) and r[1] != "missing"]
    missing = [r[0] for r in table[1:] if r[1] == "missing"]
    intro, new = whole_episode(summary, missing, calibration_link(readme)).split("\n\n", 1)
    new = table_rows(new)  # the references' rows, then the missing ones
    share = new[0].index(SHARE)
    for row in learned:  # cells as rendered, the share from results.json
        entry = results["methods"][result_name(row[0])]
        row[share:] = [share_text(entry[SHARE_KEY])]
    text = text[:start] + intro + "\n\n" + markdown_rows([new[0], *learned, *new[2:]]) + text[end:]

    # Table II: its references (task-aligned plans) where the page has any.
    if tap:
        start, end, table = table_at(text, "| method | segments |")
        refs = [r for r in table_rows(table2(tap)[0]) if r[0].endswith(" (reference)")]
        learned = [r for r in table[1:] if not r[0].endswith(" (reference)")]
        text = text[:start] + markdown_rows([table[0], *learned, *refs]) + text[end:]
    write_json(results, path)
    readme.write_text(text)
    return readme


TABLE2_SOURCE = "The task-aligned rows come from "


def add_table2(readme: Path, folder: Path) -> Path:
    """Give ``readme`` (a page with Fig. 5b and ICCO's Table II row) and its ``results.json`` the
    task-aligned rows of ``folder/table2_tap`` (``run.py --methods qmix``), Table II's verdict and
    the planner's statistics; ICCO's row stays the page's own (its Fig. 5b run)."""
    path = readme.parent / "results.json"
    results = json.loads(path.read_text())
    tap, tap_rows = load(folder / "table2_tap")
    pooled = results.get("table2", {})
    icco = pooled.get("methods", {}).get("icco")
    if icco is None or icco.get("seeds", 0) < 1:
        raise SystemExit(f"report.py: {readme} has no ICCO row in Table II: render it first")
    steps = next(iter(tap["segment_steps"].values()))
    if (
        list(tap["segment_steps"]) != results["instructions"]
        or steps != pooled["steps"]
        or tap["trials"] * len(tap["segment_steps"]) != pooled["trials"]
    ):
        raise SystemExit(
            f"report.py: {folder} has other instructions, steps or trials than {readme}: "
            "not the page's protocol, nothing written"
        )
    n = icco["seeds"] * pooled["trials"]
    given = {"ICCO": tuple(verdict.Mean(icco[k]["mean"], icco[k]["std"], n) for k in COUNTS)}
    table, means = table2(tap_rows, given)
    source = (
        f"{TABLE2_SOURCE}`python experiments/language/run.py "
        f"{run_arguments(folder, None, readme)}`; ICCO's row is its Fig. 5b run above."
    )
    text = _page_with_table2(readme.read_text(), table, source, tap, means)
    added = results_json(
        summarize(per_instruction(tap_rows)),
        protocol=pooled["protocol"],
        steps=steps,
        trials=pooled["trials"],
        frames=_frames(tap),
        segment="instruction",
    )["methods"]
    pooled["methods"] = {"icco": icco, **{k: v for k, v in added.items() if k != "icco"}}
    best = pooled["methods"].get("best_scripted", {}).get("reward", {}).get("mean")
    for entry in pooled["methods"].values():
        entry[SHARE_KEY] = entry["reward"]["mean"] / best if best and best > 0 else None
    write_json(results, path)
    readme.write_text(text)
    return readme


def _page_with_table2(text: str, table: str, source: str, tap: dict, means: dict) -> str:
    """The page ``text`` with Table II ``table`` and its ``source`` line (replacing an earlier
    one), the task-aligned run's planner statistics, and Table II's verdict and n."""
    start, end, _ = table_at(text, "| method | segments |")
    rest = text[end:]
    if rest.startswith("\n\n" + TABLE2_SOURCE):  # a second addition replaces the first's line
        rest = rest[rest.index("\n", 2) :]
    text = text[:start] + table + "\n\n" + source + rest
    start, end, rows = table_at(text, "| run | method | requests |")
    added = table_rows(planner_stats({"table2_tap": tap}))[2:]
    text = (
        text[:start] + markdown_rows([r for r in rows if r[0] != "table2_tap"] + added) + text[end:]
    )
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("- Table II: missing") or line.startswith("- **Paper (Table II)"):
            lines[i] = table2_claim(means)
        elif line.startswith("- **How to read the verdicts.**"):
            head = line.split(TABLE2_N)[0].removesuffix(").")
            lines[i] = head + TABLE2_N + table2_n(means) + ")."
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("out", type=Path, nargs="?", help="the results folder written by run.py")
    parser.add_argument("--readme", type=Path, default=HERE / "README.md")
    parser.add_argument(
        "--references",
        type=Path,
        help="add the scripted references of this folder to the page (no run folder needed)",
    )
    parser.add_argument(
        "--table2",
        type=Path,
        help="add the Table II runs of this folder (run.py --methods qmix) to the page",
    )
    args = parser.parse_args(argv)
    if args.table2 is not None:
        page = add_table2(args.readme, args.table2)
        print(f"added the Table II runs of {args.table2} to {page}")
        return 0
    if args.references is not None:
        page = add_references(args.readme, args.references)
        print(f"added the references of {args.references} to {page}")
        return 0
    if args.out is None:
        parser.error("the results folder is needed (or --references)")
    if not (args.out / "fig5b" / "instruct.json").is_file():
        print(
            f"report.py: {args.out / 'fig5b' / 'instruct.json'} not found: run "
            "experiments/language/run.py first",
            file=sys.stderr,
        )
        return 2
    fig5b, fig5b_rows = load(args.out / "fig5b")
    # Table II's QMIX-TAP runs exist only when run.py's --methods had qmix.
    tap, tap_rows = (
        load(args.out / "table2_tap")
        if (args.out / "table2_tap" / "instruct.json").is_file()
        else (None, [])
    )
    payloads = {"fig5b": fig5b, **({"table2_tap": tap} if tap else {})}
    # a page other than the default one: named in its reproduce lines, without the default's history
    page = None if args.readme.resolve() == (HERE / "README.md").resolve() else args.readme
    figures = args.readme.parent / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(args.out / "fig5b" / "instruct_reward.png", figures / "fig5b_reward.png")
    shutil.copyfile(
        args.out / "fig5b" / "instruct_trajectories.png", figures / "fig6_trajectories.png"
    )

    table, means = table2([r for r in fig5b_rows if r["method"] == "ICCO"] + tap_rows)
    frames = [c["frames"] or 0 for p in payloads.values() for c in p["checkpoints"]]
    smoke = min(frames) < SMOKE_FRAMES
    model = fig5b["model"]
    offline = model.startswith("offline/")
    steps = next(iter(fig5b["segment_steps"].values()))
    fig5b_missing = [
        m for m in ("ICCO", "QMIX (FULL)") if m not in {r["method"] for r in fig5b["summary"]}
    ]
    text = Template((HERE / "README.template.md").read_text()).substitute(
        banner=(
            "> **Smoke budget: these numbers only show that the pipeline runs end to end; the "
            "policies have learned nothing. Re-run without `--smoke` for results.**"
            if smoke
            else ""
        ),
        steps=steps,
        plan_text=PLAN_TEXT[fig5b.get("plan", "fixed")],
        placement_table=placement(fig5b["summary"]),
        model=model,
        trials=fig5b["trials"],
        planner_note=(
            "**Planner caveat.** The default planner is the offline rule program (not a language "
            "model): it draws the four formations exactly, and under the task-aligned prompt it "
            "bends them toward the task by a fixed rule (the robot nearest the invader's path "
            "intercepts it; a robot within 1.5 m of a resource passes through it on the way to its "
            "slot). A language model decides this itself: run with `--llm openai` (or any litellm "
            "model) for the paper's setting."
            if offline
            else ""
        ),
        run_args="--smoke"
        if smoke
        else run_arguments(args.out, None if offline else fig5b["llm_backend"], page),
        out=" ".join(
            shlex.quote(w)
            for w in [
                os.path.relpath(args.out),
                *(["--readme", os.path.relpath(page)] if page else []),
            ]
        ),
        fig5b_table=segment_table(fig5b["summary"], "reward")
        + "\n\n"
        + whole_episode(fig5b["summary"], fig5b_missing, calibration_link(args.readme)),
        table2=table,
        recipe_note=folder_note(args.out) or ("" if page else RECIPE_NOTE),
        planner_stats=planner_stats(payloads),
        comparison=comparison(fig5b["summary"], means),
    )
    args.readme.write_text(text)
    write_json(
        language_results(fig5b, fig5b_rows, tap, tap_rows, steps),
        args.readme.parent / "results.json",
    )
    print(f"wrote {args.readme} and results.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
