"""Evaluation metrics: per-step quantities, per-trial and per-segment totals, summaries, tables.

Counts and rewards are summed over a segment's steps, so a trial's segments add up to its
episode; distances and fractions are averaged over steps, so the episode value is the
step-weighted mean of its segments'. Standard deviations are over trials (population std,
as in :func:`icco_torchrl.evaluation.rollout.evaluate`).
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from icco_torchrl import methods
from icco_torchrl.envs.reference_policies import BEST_SCRIPTED_LABEL, reference_key
from icco_torchrl.envs.resource_collection import EVENTS
from icco_torchrl.envs.waypoints import QUADRANT_SIGNS
from icco_torchrl.evaluation import placement
from icco_torchrl.training.logger import read_column

# Summed over steps: team reward, its instruction part, its task part, and the event counts.
ADDITIVE = ("reward", "task_reward", "inst_reward", *EVENTS)
# Averaged over steps: distance (m) from each robot to its nearest waypoint, the fraction of
# robots strictly inside the instructed quadrant (NaN for segments without a quadrant) and the
# broadcast rate, the share of present robots that received a coordinator's z (NaN without one;
# over a whole segment: the share of robot-steps, 1/T when every robot gets z every T steps).
AVERAGED = ("waypoint_dist", "in_quadrant", "broadcast_rate")
# Averaged over each segment's second half, when the team has had time to get there
# (:mod:`icco_torchrl.evaluation.placement`; NaN where the source has no plan or the instruction
# no region): the share of robots at their own slot, of steps with every robot that is not
# intercepting at its slot, and of steps with at least n - 1 of n robots where the instruction
# says ("in place").
SECOND_HALF = ("at_slot", "formation", "in_place")
# Steps from the segment's start until the formation first holds (its length when it never does).
TIME_TO_SLOT = "time_to_slot"
METRICS = ADDITIVE + AVERAGED + SECOND_HALF + (TIME_TO_SLOT,)
EPISODE = "episode"  # the segment name of a whole-episode row
# Every report states a team's reward as a share of the best scripted team's on the same episodes
# (reference_policies.BEST_SCRIPTED): this column in tables, this key in results.json.
SHARE = "share of best scripted"
SHARE_KEY = "share_of_best_scripted"
TASK_REWARDS = ("pick_reward", "collect_reward", "defense_reward", "invasion_penalty")


def method_label(cfg: Mapping, suffix: str = "") -> str:
    """The table label of a trained configuration (its method's, :mod:`icco_torchrl.methods`),
    ``suffix`` appended (e.g. "-TAP"); agents trained on the instruction reward alone (every task
    reward zero, ``experiment=inst_only``) get " w/o TR", as in "QMIX-TAP w/o TR"."""
    label = methods.label(cfg["method"]["name"]) + suffix
    params = cfg["env"]["params"]
    if all(float(params.get(key, 1.0)) == 0.0 for key in TASK_REWARDS):
        label += methods.WITHOUT_TASK_REWARD
    return label


def step_values(
    env,
    nxt,
    waypoints: torch.Tensor,
    quadrant: int | None,
    sent: torch.Tensor | None = None,
    present: torch.Tensor | None = None,
    slots: torch.Tensor | None = None,
    judge: placement.Judge | None = None,
) -> dict[str, torch.Tensor]:
    """This step's ``[B]`` values from the raw env (after the step) and its ``"next"`` td;
    ``sent [B, N, 1]`` marks the robots a coordinator sent z to, among ``present [B, N]`` (default:
    every robot); ``slots [B, N, 2]`` are the plan's slots and ``judge`` the instruction's region
    (:func:`~icco_torchrl.evaluation.placement.region`), when there are."""
    reward = nxt.get("reward").reshape(-1).float()
    inst = nxt.get(("events", "inst_reward")).float()
    out = {"reward": reward, "task_reward": reward - inst, "inst_reward": inst}
    for key in EVENTS:
        out[key] = nxt.get(("events", key)).float()
    out["waypoint_dist"] = (waypoints - env.pos.unsqueeze(-2)).norm(dim=-1).min(-1).values.mean(-1)
    if quadrant is None:
        out["in_quadrant"] = torch.full_like(reward, math.nan)
    else:
        signs = torch.tensor(QUADRANT_SIGNS[quadrant], device=env.pos.device)
        out["in_quadrant"] = (env.pos * signs > 0).all(-1).float().mean(-1)
    out.update(_placement(env, reward, present, slots, judge))
    if sent is None:
        out["broadcast_rate"] = torch.full_like(reward, math.nan)
    else:
        sent = sent.reshape(sent.shape[0], -1).float()
        team = torch.ones_like(sent) if present is None else present.reshape(sent.shape).float()
        out["broadcast_rate"] = (sent * team).sum(-1) / team.sum(-1).clamp_min(1.0)
    return out


def _placement(env, reward, present, slots, judge) -> dict[str, torch.Tensor]:
    """The :data:`SECOND_HALF` step values (NaN without slots, or without a region)."""
    nan = torch.full_like(reward, math.nan)
    team = torch.ones(env.pos.shape[:-1], dtype=torch.bool, device=env.pos.device)
    team = team if present is None else present.reshape(team.shape).bool()
    out = {"at_slot": nan, "formation": nan, "in_place": nan}
    if slots is not None:
        at = placement.at_slot(env.pos, slots)
        out["at_slot"] = (at & team).sum(-1) / team.sum(-1).clamp_min(1)
        excused = placement.intercepting(env.pos, team, env.inv_pos, env.inv_active)
        out["formation"] = placement.formation(at, team, excused).float()
    if judge is not None:
        out["in_place"] = placement.in_place(judge(env.pos, team), team).float()
    return out


def time_to_slot(formation: np.ndarray) -> float:
    """Steps until ``formation`` (a segment's per-step values) first holds; its length when it
    never does; NaN without a plan."""
    if not np.isfinite(formation).any():
        return math.nan
    held = np.flatnonzero(formation > 0)
    return float(held[0] + 1) if len(held) else float(len(formation))


def trial_rows(
    per_step: Mapping[str, np.ndarray],
    names: Sequence[str],
    bounds: Sequence[tuple[int, int]],
    **labels,
) -> list[dict]:
    """One row per trial and segment, then one ``"episode"`` row per trial.

    ``per_step[key]`` is ``[T, B]``; ``bounds`` are the segments' ``[start, stop)`` steps;
    ``labels`` (method, seed, ...) are copied into every row.
    """
    n_trials = next(iter(per_step.values())).shape[1]
    rows = []
    for b in range(n_trials):
        for name, (start, stop) in [*zip(names, bounds), (EPISODE, (bounds[0][0], bounds[-1][1]))]:
            row = {**labels, "trial": b, "segment": name, "steps": stop - start}
            for key in ADDITIVE:
                row[key] = float(per_step[key][start:stop, b].sum())
            for key in AVERAGED:
                row[key] = _mean(per_step[key][start:stop, b])
            parts = list(zip(names, bounds)) if name == EPISODE else [(name, (start, stop))]
            for key in SECOND_HALF:
                row[key] = _mean(np.concatenate(
                    [per_step[key][(a + z) // 2 : z, b] for _, (a, z) in parts]
                ))  # fmt: skip
            row[TIME_TO_SLOT] = _mean(
                np.array([time_to_slot(per_step["formation"][a:z, b]) for _, (a, z) in parts])
            )
            rows.append(row)
    return rows


def _mean(values: np.ndarray) -> float:
    return float(np.nanmean(values)) if np.isfinite(values).any() else math.nan


def _stats(values: np.ndarray) -> tuple[float, float]:
    values = values[np.isfinite(values)]
    return (float(values.mean()), float(values.std())) if len(values) else (math.nan, math.nan)


def summarize(rows: Iterable[Mapping], by: Sequence[str] = ("method", "segment")) -> list[dict]:
    """Mean and std over trials (``{key}`` and ``{key}_std``) per group, in first-seen order;
    ``n`` counts the trials and ``seeds`` the distinct ``seed`` values in the group."""
    groups: dict[tuple, list[Mapping]] = {}
    for row in rows:
        groups.setdefault(tuple(row[k] for k in by), []).append(row)
    out = []
    for key, members in groups.items():
        summary = dict(zip(by, key), n=len(members), seeds=len({m.get("seed") for m in members}))
        for metric in METRICS:
            summary[metric], summary[f"{metric}_std"] = _stats(
                np.array([m.get(metric, math.nan) for m in members], float)  # older rows lack some
            )
        out.append(summary)
    return out


def best_scripted_shares(summary: Sequence[Mapping], segment: str = EPISODE) -> dict[str, float]:
    """Each method's mean ``segment`` reward over the best scripted team's (its row's label starts
    with ``"best scripted"``), by label; empty without that row, NaN where its reward is <= 0."""
    rows = [row for row in summary if row["segment"] == segment]
    best = next((r for r in rows if str(r["method"]).startswith(BEST_SCRIPTED_LABEL)), None)
    if best is None:
        return {}
    scale = best["reward"] if best["reward"] > 0 else math.nan
    return {row["method"]: row["reward"] / scale for row in rows}


def share_text(value: float | None) -> str:
    """A share of the best scripted team's reward as a table cell: ``"96 %"``, ``"–"`` when
    unknown; rounded to an int, so a share just below zero reads "0 %", not "-0 %"."""
    return "–" if value is None or not math.isfinite(value) else f"{round(100 * value)} %"


def _cell(summary: Mapping, metric: str, digits: int) -> str:
    mean, std = summary[metric], summary[f"{metric}_std"]
    return "–" if not math.isfinite(mean) else f"{mean:.{digits}f} ± {std:.{digits}f}"


def markdown_table(
    summary: Sequence[Mapping],
    metrics: Sequence[str] = METRICS,
    *,
    segment: str = EPISODE,
    missing: Sequence[str] = (),
) -> str:
    """A Markdown table of ``segment`` rows, one per method (mean ± std over trials); methods
    in ``missing`` get a row saying so, so a comparison never silently loses one. Metrics
    without a value in any row (``in_quadrant`` without quadrants) are left out. With a best
    scripted row, a column gives each team reward as a share of its (:data:`SHARE`)."""
    digits = {"waypoint_dist": 2, "in_quadrant": 2, "broadcast_rate": 3, TIME_TO_SLOT: 0}
    digits.update(dict.fromkeys(SECOND_HALF, 2))
    rows = [row for row in summary if row["segment"] == segment]
    metrics = (
        [m for m in metrics if any(math.isfinite(row[m]) for row in rows)]
        if rows
        else list(metrics)
    )
    shares = best_scripted_shares(summary, segment)
    head = ["method", "trials"] + metrics + ([SHARE] if shares else [])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        cells = [str(row["method"]), f"{row['n']} ({row['seeds']} seed{'s' * (row['seeds'] != 1)})"]
        cells += [_cell(row, m, digits.get(m, 1)) for m in metrics]
        cells += [share_text(shares[row["method"]])] if shares else []
        lines.append("| " + " | ".join(cells) + " |")
    for method in missing:
        lines.append("| " + " | ".join([method, "missing"] + ["–"] * (len(head) - 2)) + " |")
    return "\n".join(lines)


def segment_table(summary: Sequence[Mapping], metric: str = "reward") -> str:
    """A Markdown table of ``metric`` per segment (columns) and method (rows)."""
    segments = list(dict.fromkeys(row["segment"] for row in summary))
    methods = list(dict.fromkeys(row["method"] for row in summary))
    cell = {(row["method"], row["segment"]): _cell(row, metric, 1) for row in summary}
    lines = ["| method | " + " | ".join(segments) + " |", "|" + "---|" * (len(segments) + 1)]
    for method in methods:
        lines.append(
            f"| {method} | " + " | ".join(cell.get((method, s), "–") for s in segments) + " |"
        )
    return "\n".join(lines)


def write_csv(rows: Sequence[Mapping], path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fields = list(dict.fromkeys(k for row in rows for k in row))
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    return path


def write_json(payload, path: str | Path) -> Path:
    """JSON with NaN written as null (strict JSON readers reject NaN)."""

    def clean(value):
        if isinstance(value, float) and not math.isfinite(value):
            return None
        if isinstance(value, dict):
            return {k: clean(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [clean(v) for v in value]
        return value

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(clean(payload), indent=2))
    return path


RESULT_METRICS = (
    "reward",
    "task_reward",
    "inst_reward",
    "pick",
    "collect",
    "defense",
    "invasion",
    "in_quadrant",
    *SECOND_HALF,
    TIME_TO_SLOT,
)


def result_name(label: str) -> str | None:
    """The results.json key of a table label: a method's (:func:`icco_torchrl.methods.result_name`)
    or a reference policy's (:func:`~icco_torchrl.envs.reference_policies.reference_key`:
    ``blend (r=...)`` -> ``blend``, ``best scripted (...)`` -> ``best_scripted``); None if
    unknown."""
    return reference_key(label) or methods.result_name(label)


def results_json(
    summary: Sequence[Mapping],
    *,
    protocol: str,
    steps: int,
    trials: int,
    frames: Mapping[str, int] | None = None,
    segment: str = EPISODE,
    **extra,
) -> dict:
    """The machine-readable report: ``{"protocol", "steps", "trials", "methods": {name: {"seeds",
    "frames", metric: {"mean", "std"}}}}`` from :func:`summarize` rows of ``segment``. ``frames``
    maps a table label to the training frames of its checkpoints (reference policies: 0);
    ``in_quadrant`` is left out where the protocol has no quadrants. With a best scripted row,
    every entry has ``share_of_best_scripted`` (:func:`best_scripted_shares`)."""
    methods = {}
    shares = best_scripted_shares(summary, segment)
    for row in summary:
        name = result_name(row["method"])
        if row["segment"] != segment or name is None:
            continue
        reference = reference_key(row["method"]) is not None
        entry = {
            "seeds": 0 if reference else row["seeds"],
            "frames": int((frames or {}).get(row["method"], 0)),
        }
        if reference and name != row["method"]:  # blends: the label says their radii
            entry["label"] = row["method"]
        for metric in RESULT_METRICS:
            if math.isfinite(row[metric]):
                entry[metric] = {"mean": row[metric], "std": row[f"{metric}_std"]}
        if shares:
            share = shares[row["method"]]
            entry[SHARE_KEY] = share if math.isfinite(share) else None
        methods[name] = entry
    return {"protocol": protocol, "steps": steps, "trials": trials, **extra, "methods": methods}


@dataclass
class Curve:
    """A learning curve across seeds: ``mean`` and ``std`` of ``column`` at each of ``frames``."""

    frames: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    runs: list[str]


def learning_curves(
    runs: Mapping[str, Sequence[str | Path]], stream: str = "eval", column: str = "reward"
) -> dict[str, Curve]:
    """Mean ± std over seeds of each method's runs (``{label: [run_dir, ...]}``).

    Seeds are aligned on the frames of the shortest run (interpolating the others), so runs
    stopped at different budgets still average point by point; runs without the CSV are skipped.
    """
    curves = {}
    for label, dirs in runs.items():
        read = [(str(d), c) for d in dirs if (c := read_column(d, stream, column)) is not None]
        if not read:
            continue
        grid = min((c[0] for _, c in read), key=lambda f: f[-1])
        values = np.stack([np.interp(grid, frames, vals) for _, (frames, vals) in read])
        curves[label] = Curve(grid, values.mean(0), values.std(0), [d for d, _ in read])
    return curves
