"""Figures of an evaluation, each saved as PNG and PDF.

- :func:`plot_trajectories`: robot paths for chosen segments, one panel per method and segment
  (paper Fig. 4 / Fig. 6): field, instructed quadrant shaded, home, resources, the invader's
  path, and where each pick, delivery and defense happened.
- :func:`plot_bars`: mean ± std of a metric per method, grouped by segment (Fig. 5a / 5b).
- :func:`plot_curves`: learning curves, mean ± std across seeds.
- :func:`plot_learning_curve`: one training run's greedy evaluations (its ``learning_curve.png``).

Figures are built on ``matplotlib.figure.Figure`` (Agg canvas) rather than pyplot, so
plotting never switches the backend or leaves figures open in the caller's process.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle

from icco_torchrl.envs.reference_policies import BEST_SCRIPTED_LABEL
from icco_torchrl.envs.render import robot_color
from icco_torchrl.envs.waypoints import QUADRANT_SIGNS
from icco_torchrl.evaluation.metrics import EPISODE, Curve
from icco_torchrl.evaluation.protocols import ScheduleRun
from icco_torchrl.training.logger import read_column

RESOURCE, INVADER, HOME, SHADE = "#daa520", "#c81e2d", "#c8d6e5", "#f4c7c3"
METHOD_COLORS = (
    "#1f77b4",
    "#ff7f0e",
    "#2ca02c",
    "#9467bd",
    "#8c564b",
    "#e377c2",
    "#7f7f7f",
    "#17becf",
    "#bcbd22",
    "#d62728",
)  # tab10, red last; distinct for up to 10 rows (5 methods + 5 references)


def save(fig: Figure, stem: str | Path) -> list[Path]:
    """Write ``stem.png`` and ``stem.pdf``; returns both paths."""
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    paths = [stem.with_suffix(".png"), stem.with_suffix(".pdf")]
    for path in paths:
        fig.savefig(path, dpi=150, bbox_inches="tight")
    return paths


def _rgb(i: int) -> tuple[float, float, float]:
    return tuple(c / 255 for c in robot_color(i))


def _events(carry: np.ndarray, defended: np.ndarray) -> dict[str, np.ndarray]:
    """Boolean ``[T, N]`` masks of the steps where each robot picked, delivered or defended.

    A robot carries at most one resource and picks only when empty, so the carry flag going
    up is a pick and going down is a delivery; ``defended`` is set on the step of a hit.
    """
    return {
        "pick": carry[1:] & ~carry[:-1],
        "collect": ~carry[1:] & carry[:-1],
        "defense": defended[1:],
    }


def draw_segment(ax, run: ScheduleRun, segment: int, trial: int = 0) -> None:
    """One panel: the field during ``segment`` of ``trial``."""
    half = run.geometry["half"]
    start, stop = run.bounds[segment]
    traj = {k: v[start : stop + 1, trial] for k, v in run.trajectory.items() if k != "waypoints"}
    _draw_field(ax, run, segment)
    _draw_items(ax, traj, run.trajectory["waypoints"][start:stop, trial].reshape(-1, 2))
    events = _events(traj["carry"], traj["defended"])
    _draw_robots(ax, traj["pos"])
    _draw_events(ax, events, traj["pos"])
    counts = ", ".join(f"{name} {int(mask.sum())}" for name, mask in events.items())
    ax.set_title(f"{run.names[segment]}\n{counts}", fontsize=8)
    ax.set_xlim(-half * 1.03, half * 1.03)
    ax.set_ylim(-half * 1.03, half * 1.03)
    ax.set_aspect("equal")
    ax.set_axis_off()  # the field's own border frames the panel


def _draw_field(ax, run: ScheduleRun, segment: int) -> None:
    """Draw the field's border, the instructed quadrant (shaded) and home."""
    half = run.geometry["half"]
    ax.add_patch(Rectangle((-half, -half), 2 * half, 2 * half, fill=False, lw=1.2, color="0.35"))
    quadrant = run.quadrants[segment]
    if quadrant is not None:
        sx, sy = QUADRANT_SIGNS[quadrant]
        ax.add_patch(
            Rectangle(
                (min(0, sx * half), min(0, sy * half)), half, half, color=SHADE, alpha=0.6, lw=0
            )
        )
    ax.add_patch(
        Circle((0, 0), run.geometry["home_radius"], color=HOME, ec="0.35", zorder=2, label="home")
    )


def _draw_items(ax, traj: dict[str, np.ndarray], wps: np.ndarray) -> None:
    """Draw the resources, the waypoints ``wps`` [M, 2] in force and the invaders' paths."""
    resources = np.unique(np.round(traj["res_pos"].reshape(-1, 2), 4), axis=0)
    ax.scatter(
        resources[:, 0],
        resources[:, 1],
        s=40,
        c=RESOURCE,
        edgecolors="0.3",
        zorder=3,
        label="resource",
    )
    ax.scatter(wps[:, 0], wps[:, 1], s=3, c="0.5", alpha=0.15, zorder=1, label="waypoints")
    for i in range(traj["inv_pos"].shape[1]):
        path = np.where(traj["inv_active"][:, i, None], traj["inv_pos"][:, i], np.nan)
        ax.plot(
            path[:, 0],
            path[:, 1],
            ls="--",
            lw=1,
            c=INVADER,
            zorder=3,
            label="invader" if i == 0 else None,
        )


def _draw_robots(ax, pos: np.ndarray) -> None:
    """Draw each robot's path ``pos`` [T, N, 2], hollow at its start and filled at its end."""
    for i in range(pos.shape[1]):
        ax.plot(pos[:, i, 0], pos[:, i, 1], c=_rgb(i), lw=1.3, zorder=4, label=f"robot {i}")
        ax.scatter(
            *pos[0, i],
            s=25,
            facecolors="none",
            edgecolors=[_rgb(i)],
            zorder=5,
            label="start (hollow)" if i == 0 else None,
        )
        ax.scatter(
            *pos[-1, i], s=25, c=[_rgb(i)], zorder=5, label="end (filled)" if i == 0 else None
        )


def _draw_events(ax, events: dict[str, np.ndarray], pos: np.ndarray) -> None:
    """Mark where each pick, delivery and defense of :func:`_events` happened."""
    styles = {
        "pick": dict(marker="*", s=90, c=RESOURCE),
        "collect": dict(marker="s", s=40, c=HOME),
        "defense": dict(marker="X", s=60, c=INVADER),
    }
    for name, mask in events.items():
        steps, robots = np.nonzero(mask)
        points = pos[steps + 1, robots]
        ax.scatter(
            points[:, 0],
            points[:, 1],
            edgecolors="k",
            linewidths=0.6,
            zorder=6,
            label=name,
            **styles[name],
        )


def plot_trajectories(
    runs: Mapping[str, ScheduleRun],
    stem: str | Path,
    segments: Sequence[int] = (0,),
    trial: int = 0,
) -> list[Path]:
    """A grid of panels, one row per segment and one column per method (``runs`` by label)."""
    if not runs:
        raise ValueError("plot_trajectories needs at least one run")
    # Constrained layout keeps every row's titles clear of the panels above and the legend below
    # (tight_layout let the second row's titles overlap the first row's equal-aspect panels).
    fig = Figure(figsize=(2.8 * len(runs), 2.9 * len(segments) + 0.5), layout="constrained")
    axes = fig.subplots(len(segments), len(runs), squeeze=False)
    for col, (label, run) in enumerate(runs.items()):
        for row, segment in enumerate(segments):
            draw_segment(axes[row, col], run, segment, trial)
            if row == 0:
                axes[row, col].set_title(f"{label}\n" + axes[row, col].get_title(), fontsize=8)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    rows = (
        2 if len(labels) > 6 else 1
    )  # robots, home, start/end and the events: two lines when many
    fig.legend(
        handles,
        labels,
        loc="outside lower center",
        ncol=-(-len(labels) // rows),
        fontsize=7,
        frameon=False,
    )
    return save(fig, stem)


def plot_bars(
    summary: Sequence[Mapping],
    stem: str | Path,
    metric: str = "reward",
    segments: Sequence[str] = (EPISODE,),
    missing: Sequence[str] = (),
    ylabel: str | None = None,
) -> list[Path]:
    """Grouped bars: one group per segment, one bar per method, error bars = std over trials.

    Methods in ``missing`` are named under the axis, so a gap in a comparison is visible.
    """
    methods = list(dict.fromkeys(row["method"] for row in summary))
    cell = {(row["method"], row["segment"]): row for row in summary}
    width = 0.8 / max(len(methods), 1)
    fig = Figure(figsize=(max(4.0, 1.2 + 0.5 * len(methods) * len(segments)), 3.4))
    ax = fig.subplots()
    x = np.arange(len(segments))
    for m, method in enumerate(methods):
        rows = [cell.get((method, s)) for s in segments]
        means = [r[metric] if r else math.nan for r in rows]
        stds = [r[f"{metric}_std"] if r else math.nan for r in rows]
        ax.bar(
            x + (m - (len(methods) - 1) / 2) * width,
            means,
            width,
            yerr=stds,
            capsize=3,
            label=method,
            color=METHOD_COLORS[m % len(METHOD_COLORS)],
        )
    ax.set_xticks(x, [s if s != EPISODE else "whole episode" for s in segments])
    ax.axhline(0, color="0.3", lw=0.8)
    ax.set_ylabel(ylabel or metric.replace("_", " "))
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    if missing:
        ax.set_xlabel("missing: " + ", ".join(missing), color=INVADER)
    fig.tight_layout()
    return save(fig, stem)


def plot_curves(
    curves: Mapping[str, Curve], stem: str | Path, ylabel: str = "episode team reward"
) -> list[Path]:
    """Mean ± std across seeds against env steps, one line per method."""
    if not curves:
        raise ValueError("plot_curves needs at least one curve")
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    for m, (label, curve) in enumerate(curves.items()):
        color = METHOD_COLORS[m % len(METHOD_COLORS)]
        ax.plot(curve.frames, curve.mean, color=color, label=f"{label} ({len(curve.runs)} seeds)")
        ax.fill_between(
            curve.frames, curve.mean - curve.std, curve.mean + curve.std, color=color, alpha=0.2
        )
    ax.set_xlabel("env steps")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save(fig, stem)


def plot_learning_curve(
    run_dir: str | Path, references: Mapping[str, Mapping[str, float]] | None = None
) -> Path | None:
    """``learning_curve.png`` of a training run: its greedy evaluations (``eval.csv``: team reward
    and task reward, ± std over episodes) against frames, with the ``references`` (the reference
    policies' metrics by label) as horizontal lines; with a best scripted reference the title
    gives the last evaluation's team reward as a share of its. None when the run has no
    evaluation yet."""
    run_dir = Path(run_dir)
    evaluation = read_column(run_dir, "eval", "reward")
    if evaluation is None:
        return None
    refs = references or {}
    best = next((m for k, m in refs.items() if k.startswith(BEST_SCRIPTED_LABEL)), None)
    fig = Figure(figsize=(11, 4))
    axes = fig.subplots(1, 2)
    for ax, key, title in (
        (axes[0], "reward", "team reward (task + instruction)"),
        (axes[1], "task_reward", "task reward (picks, deliveries, defenses, invasions)"),
    ):
        column = read_column(run_dir, "eval", key)
        if column is None:
            continue
        (x, y), (_, s) = column, read_column(run_dir, "eval", f"{key}_std")
        if key == "reward" and best is not None and best["reward"] > 0:
            title += (
                f"\nlast: {100 * y[-1] / best['reward']:.0f} % of the {BEST_SCRIPTED_LABEL} team's"
            )
        (line,) = ax.plot(x, y, marker="o", color="C0", label="trained policy, greedy")
        ax.fill_between(
            x, y - s, y + s, color=line.get_color(), alpha=0.2, label="± std over episodes"
        )
        for i, (label, m) in enumerate(refs.items()):
            if key in m:
                ax.axhline(m[key], color=f"C{i + 1}", ls="--", lw=1, label=label)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("env steps")
        ax.set_ylabel("per 145-step episode (team total)")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8, loc="best")
    fig.tight_layout()
    out = run_dir / "learning_curve.png"
    fig.savefig(out, dpi=120)
    return out
