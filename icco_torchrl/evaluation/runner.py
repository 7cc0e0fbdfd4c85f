"""Evaluate trained checkpoints under an instruction schedule and write the results.

The library behind ``icco eval`` and ``icco instruct`` (:mod:`icco_torchrl.commands`):
:func:`find_checkpoints` resolves ``checkpoint``/``eval.checkpoints``; :func:`evaluate_checkpoints`
plays a schedule (any :class:`~icco_torchrl.envs.waypoints.InstructionSource` per segment) on every
checkpoint and on the reference policies; :func:`write_report` writes the tables and figures.

Checkpoints of one method (several seeds) are pooled into one table row. Every checkpoint is
evaluated in the env the command line composes (by default the paper's task), so all methods
are scored by the same rewards; parameters that differ from a checkpoint's training env are
reported, and a different observation layout is refused. The team size is ``eval.team_size``
(default: the checkpoints' ``n_agents``, which must then agree): a checkpoint trained on another
size acts zero-shot when its acting networks read any team
(:func:`~icco_torchrl.training.restore.restore`), and ``eval.broadcast_threshold`` replaces the
coordinators' beta. All checkpoints face the same initial configurations (the env seed is
``seed + EVAL_SEED_OFFSET``). Outputs: ``<name>_trials.csv`` (one row per checkpoint, trial and
segment, plus the whole episode), ``<name>_summary.csv``, ``<name>.json``, ``<name>.md`` and
figures (PNG + PDF, GIFs on request).
"""

from __future__ import annotations

import glob
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from icco_torchrl.envs import ResourceCollectionEnv
from icco_torchrl.envs.reference_policies import make_reference_policy, reference_label
from icco_torchrl.evaluation import consistency
from icco_torchrl.evaluation.metrics import (
    EPISODE,
    SHARE,
    best_scripted_shares,
    markdown_table,
    method_label,
    segment_table,
    summarize,
    write_csv,
    write_json,
)
from icco_torchrl.evaluation.protocols import (
    PROTOCOLS,
    Schedule,
    check_schedule,
    run_schedule,
    schedule_env,
)
from icco_torchrl.training.build import EPISODE_SEED_STRIDE, EVAL_SEED_OFFSET
from icco_torchrl.training.checkpoint import load_checkpoint
from icco_torchrl.training.run_folder import CheckpointError

GIF_MAX_FRAMES = 300  # longer episodes are recorded every few steps
GIF_SIZE = 320


def _demo_hint() -> str:
    """How to evaluate the demo policy of a source checkout (``icco live`` uses it by default);
    empty where there is none (an installed wheel)."""
    demo = Path(__file__).resolve().parents[2] / "assets" / "demo_icco.pt"
    if not demo.is_file():
        return ""
    shown = os.path.relpath(demo) if demo.is_relative_to(Path.cwd()) else demo
    return f", or evaluate the demo policy: icco eval checkpoint={shown} (assets/README.md)"


def find_checkpoints(cfg: DictConfig, root: str | Path = ".") -> list[Path]:
    """``checkpoint`` and ``eval.checkpoints`` (paths or globs), in order, without repeats.

    With neither given, the newest ``runs/*/*/checkpoint.pt`` under ``root``; a glob that
    matches nothing is an error naming it (a comparison never silently loses a method).
    """
    patterns = ([cfg.checkpoint] if cfg.checkpoint else []) + list(cfg.eval.checkpoints or [])
    if not patterns:
        found = sorted(Path(root).glob("runs/*/*/checkpoint.pt"), key=lambda p: p.stat().st_mtime)
        if not found:
            raise ValueError(
                f"no checkpoint given (checkpoint=PATH) and none found under "
                f"{Path(root).resolve() / 'runs'}/*/*/checkpoint.pt: run `make train` first"
                + _demo_hint()
            )
        return [found[-1]]
    paths: list[Path] = []
    for pattern in patterns:
        matches = (
            sorted(glob.glob(str(pattern))) if glob.has_magic(str(pattern)) else [str(pattern)]
        )
        if not matches:
            raise ValueError(f"checkpoint pattern {pattern!r} matched no file")
        paths += [Path(m) for m in matches if Path(m) not in paths]
    return paths


def default_out_dir(paths: Sequence[Path], name: str) -> Path:
    """``<folder of the checkpoints>/<name>``: the run folder, or the sweep folder holding them."""
    return Path(os.path.commonpath([str(p.resolve().parent) for p in paths])) / name


# What an env.params difference between training and evaluation changes (the note of
# ``icco eval``). Layout differences (what the networks read) never get this far: they are refused.
# The protocol sets the episode length and writes the waypoints: the instruction generator's
# parameters are unused in evaluation.
UNUSED_IN_EVAL = (
    "max_steps",
    "validate",
    "waypoint_interval",
    "waypoint_mode",
    "waypoint_path_prob",
    "waypoint_route_prob",
    "waypoint_route_step",
    "waypoint_sigma",
)
# The policy never sees its reward: these reweigh the reward columns, nothing else.
REWARD_WEIGHTS = (
    "pick_reward",
    "collect_reward",
    "defense_reward",
    "invasion_penalty",
    "inst_reward_scale",
    "inst_dist_coef",
)


def _differences(eval_params: dict, trained_params: dict) -> list[str]:
    keys = sorted(set(eval_params) | set(trained_params))
    return [
        f"{k}: trained {trained_params.get(k)!r}, evaluated {eval_params.get(k)!r}"
        for k in keys
        if eval_params.get(k) != trained_params.get(k)
    ]


def difference_effect(keys) -> str:
    """What env.params differing in ``keys`` do to the scores of a policy trained in another env,
    one clause per kind of difference."""
    kinds = [
        (
            "changed by {} (the task differs: the references face it too, and the policy may "
            "act outside its training)",
            [k for k in keys if k not in UNUSED_IN_EVAL + REWARD_WEIGHTS],
        ),
        (
            "reward columns only, by {} (counts and behaviour unchanged)",
            [k for k in keys if k in REWARD_WEIGHTS],
        ),
        (
            "unchanged by {} (the protocol sets the episode length and writes the waypoints)",
            [k for k in keys if k in UNUSED_IN_EVAL],
        ),
    ]
    return "; ".join(text.format(", ".join(ks)) for text, ks in kinds if ks)


def slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", text.lower()).strip("_")


def _gif_recorder(total: int):
    """``(on_step, frames)``: renders env 0 every few steps (at most ~GIF_MAX_FRAMES frames)."""
    from icco_torchrl.envs.render import render_frame

    stride, frames, calls = max(1, -(-total // GIF_MAX_FRAMES)), [], [0]

    def on_step(env) -> None:
        if calls[0] % stride == 0:
            frames.append(render_frame(env, 0, GIF_SIZE))
        calls[0] += 1

    return on_step, frames


@dataclass
class Evaluation:
    """Everything :func:`evaluate_checkpoints` measured, ready for :func:`write_report`."""

    rows: list = field(default_factory=list)  # metrics rows of every checkpoint, trial and segment
    runs: dict = field(default_factory=dict)  # the first ScheduleRun of each method, for figures
    checkpoints: list = field(default_factory=list)  # path, method, seed, frames, env differences
    sources: list = field(default_factory=list)  # per-segment counters of the LLM sources
    gifs: list = field(default_factory=list)
    team_size: int | None = None  # the robots of every evaluated team
    # per method: the coordination measures of each checkpoint (evaluation/consistency.py)
    coordination: dict = field(default_factory=dict)


def team_size(cfg: DictConfig, paths: Sequence[Path]) -> int:
    """``eval.team_size``, or the ``n_agents`` every checkpoint was trained with (checkpoints of
    different sizes need an explicit one: the references run one size)."""
    if cfg.eval.team_size is not None:
        size = cfg.eval.team_size
        if isinstance(size, bool) or not isinstance(size, int) or size < 1:
            raise ValueError(f"config field 'eval.team_size' must be an integer >= 1, got {size!r}")
        return size
    trained = {str(p): load_checkpoint(p)["cfg"]["env"]["params"]["n_agents"] for p in paths}
    if len(set(trained.values())) > 1:
        raise ValueError(
            "the checkpoints were trained for different team sizes ("
            + ", ".join(f"{p}: {n}" for p, n in trained.items())
            + "): give eval.team_size=K"
        )
    return int(next(iter(trained.values())))


def _restore(cfg: DictConfig, path: Path, total: int, eval_params: dict) -> dict:
    """The checkpoint's policy in the command line's env; a layout clash names the params."""
    try:
        return schedule_env(
            path,
            total,
            cfg.eval.trials,
            device=cfg.device,
            seed=cfg.seed + EVAL_SEED_OFFSET,
            broadcast_threshold=cfg.eval.broadcast_threshold,
            **eval_params,
        )
    except CheckpointError as err:
        trained = load_checkpoint(path)["cfg"]["env"]["params"]
        raise CheckpointError(
            f"{err} (env.params on the command line vs training: "
            f"{'; '.join(_differences(eval_params, trained)) or 'none'})"
        ) from None


def _note_differences(path: Path, diffs: list[str]) -> None:
    """Print which env.params differ from the checkpoint's training env, and what that does."""
    if diffs:
        print(
            f"note: {path} is evaluated in another env than it was trained in: "
            + "; ".join(diffs)
            + ". Scores: "
            + difference_effect([d.split(":")[0] for d in diffs])
        )


def _checkpoint_entry(
    path: Path, restored: dict, trained: dict, label: str, diffs: list[str], size: int
) -> dict:
    """The :attr:`Evaluation.checkpoints` entry of one checkpoint."""
    return dict(
        path=str(path),
        method=label,
        seed=trained["seed"],
        frames=restored["checkpoint"].get("frames"),
        env_differences=diffs,
        team_size=size,
        trained_team_size=trained["env"]["params"]["n_agents"],
        trained_team_sizes=trained["train"].get("team_sizes"),
        broadcast_threshold=(
            trained["method"]["broadcast_threshold"] if trained["method"]["coordinator"] else None
        ),
    )


def _add_run(out: Evaluation, label: str, run) -> None:
    """Add a schedule run's metrics rows to ``out`` (and keep the method's first run)."""
    out.rows += run.rows
    out.runs.setdefault(label, run)


def _evaluate_checkpoint(
    cfg: DictConfig,
    path: Path,
    make_schedule: Callable[[int], Schedule],
    total: int,
    eval_params: dict,
    out: Evaluation,
    gif_stem: Path | None,
    label_suffix: str,
    coordination: bool = False,
) -> None:
    """Play every episode with the checkpoint at ``path`` into ``out`` (and record its GIF); with
    ``coordination``, measure a coordinator's information and consistency too."""
    restored = _restore(cfg, path, total, eval_params)
    trained = OmegaConf.to_container(restored["cfg"], resolve=True)
    label, seed = method_label(trained, label_suffix), trained["seed"]
    diffs = _differences(eval_params, trained["env"]["params"])
    _note_differences(path, diffs)
    out.checkpoints.append(_checkpoint_entry(path, restored, trained, label, diffs, out.team_size))
    if coordination and restored["coordinator"] is not None:
        measured = consistency.for_eval(
            path,
            cfg.eval.coordination,
            seed=cfg.seed + EVAL_SEED_OFFSET,
            broadcast_threshold=cfg.eval.broadcast_threshold,
            **eval_params,
        )
        out.checkpoints[-1]["coordination"] = measured
        out.coordination.setdefault(label, []).append(measured)
    for episode in range(cfg.eval.episodes):
        record = gif_stem is not None and episode == 0 and label not in out.runs
        on_step, frames = _gif_recorder(total) if record else (None, None)
        run = run_schedule(
            restored["env"],
            restored["policy"],
            make_schedule(episode),
            cfg.eval.trials,
            on_step=on_step,
            method=label,
            seed=seed,
            checkpoint=str(path),
            episode=episode,
        )
        out.sources += [dict(method=label, seed=seed, episode=episode, **s) for s in run.sources]
        _add_run(out, label, run)
        if record:
            from icco_torchrl.envs.render import write_gif

            out.gifs.append(gif_stem.with_name(f"{gif_stem.name}_{slug(label)}.gif"))
            write_gif(frames, out.gifs[-1], fps=10)


def _evaluate_reference(
    cfg: DictConfig,
    name: str,
    make_schedule: Callable[[int], Schedule],
    total: int,
    eval_params: dict,
    out: Evaluation,
) -> None:
    """Play every episode with the reference policy ``name`` into ``out``."""
    e = cfg.eval
    label = reference_label(name, e.blend_radius)
    for episode in range(e.episodes):
        env = ResourceCollectionEnv(
            num_envs=e.trials,
            seed=cfg.seed + EVAL_SEED_OFFSET,
            **{**eval_params, "max_steps": total, "waypoint_mode": "external"},
        )
        policy = make_reference_policy(name, env, radius=e.blend_radius, seed=cfg.seed + episode)
        run = run_schedule(
            env,
            policy,
            make_schedule(episode),
            e.trials,
            method=label,
            seed=-1,
            checkpoint="",
            episode=episode,
        )
        _add_run(out, label, run)


def evaluate_checkpoints(
    cfg: DictConfig,
    paths: Sequence[Path],
    make_schedule: Callable[[int], Schedule],
    *,
    gif_stem: Path | None = None,
    label_suffix: str = "",
    coordination: bool = False,
) -> Evaluation:
    """Run ``make_schedule(episode)`` (fresh sources per checkpoint and episode) on every
    checkpoint, ``eval.episodes`` times ``eval.trials`` trials. ``label_suffix`` is appended to
    the method names (e.g. "-TAP"); with ``gif_stem`` trial 0 of each method's first checkpoint
    is recorded to ``<gif_stem>_<method>.gif``. With ``coordination`` each checkpoint with a
    coordinator is also measured (:mod:`~icco_torchrl.evaluation.consistency`, at the budget of
    ``eval.coordination``)."""
    # tiny networks: extra threads only contend on shared CPUs
    torch.set_num_threads(cfg.train.threads)
    size = team_size(cfg, paths)
    eval_params = {**OmegaConf.to_container(cfg.env.params, resolve=True), "n_agents": size}
    out = Evaluation(team_size=size)
    total = check_schedule(make_schedule(0), cfg.eval.trials)
    for path in paths:
        _evaluate_checkpoint(
            cfg, path, make_schedule, total, eval_params, out, gif_stem, label_suffix, coordination
        )
    for name in cfg.eval.references:  # scripted yardsticks on the same initial configurations
        _evaluate_reference(cfg, name, make_schedule, total, eval_params, out)
    return out


def _report_markdown(
    result: Evaluation, e: DictConfig, title: str, summary: list, steps: dict, segments: list
) -> str:
    """The report's Markdown: title, setup, the whole-episode table and rewards per segment."""
    header = (
        f"# {title}\n\n{e.trials} trials x {e.episodes} episode(s) per checkpoint"
        + (f", teams of {result.team_size} robots" if result.team_size else "")
        + "; segments: "
        + ", ".join(f"{s} ({steps[s]} steps)" for s in segments)
        + ".\nMean ± std over trials (seeds pooled). Rewards are team totals (sum over robots); "
        + "the columns are defined in docs/metrics.md.\n"
        + (
            f"'{SHARE}': the mean team reward over the best scripted team's on the same episodes.\n"
            if best_scripted_shares(summary)
            else ""
        )
    )
    return (
        f"{header}\n## Whole episode\n\n{markdown_table(summary)}\n\n"
        f"## Team reward per segment\n\n{segment_table(summary, 'reward')}\n"
    )


def _report_figures(
    result: Evaluation,
    summary: list,
    out_dir: Path,
    name: str,
    segments: list,
    traj_segments: Sequence[int] | None,
) -> list[Path]:
    """The reward bars and the trajectory panels, written into ``out_dir``; returns their paths."""
    from icco_torchrl.evaluation.plots import plot_bars, plot_trajectories

    figures = plot_bars(
        summary,
        out_dir / f"{name}_reward",
        "reward",
        segments=[*segments, EPISODE],
        ylabel="team reward",
    )
    return figures + plot_trajectories(
        result.runs,
        out_dir / f"{name}_trajectories",
        segments=range(len(segments)) if traj_segments is None else traj_segments,
    )


def write_report(
    result: Evaluation,
    cfg: DictConfig,
    *,
    name: str,
    out_dir: Path,
    title: str,
    traj_segments: Sequence[int] | None = None,
    meta: dict | None = None,
) -> float:
    """Tables (CSV, Markdown, JSON with ``meta``) and figures into ``out_dir``; prints the
    Markdown and returns the first method's mean episode reward. ``traj_segments`` picks the
    segments drawn (default: all)."""
    rows, e = result.rows, cfg.eval
    summary = summarize(rows, by=("method", "segment"))
    if result.coordination:  # the coordination columns (NaN where not measured)
        consistency.add_columns(summary, result.coordination)
    steps = {r["segment"]: r["steps"] for r in rows}
    segments = [s for s in steps if s != EPISODE]
    markdown = _report_markdown(result, e, title, summary, steps, segments)
    markdown += consistency.coordination_table(summary)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_csv(rows, out_dir / f"{name}_trials.csv")
    write_csv(summary, out_dir / f"{name}_summary.csv")
    (out_dir / f"{name}.md").write_text(markdown)
    figures = _report_figures(result, summary, out_dir, name, segments, traj_segments)
    write_json(
        dict(
            **(meta or {}),
            title=title,
            name=name,
            team_size=result.team_size,
            broadcast_threshold=e.broadcast_threshold,
            trials=e.trials,
            episodes=e.episodes,
            segments=segments,
            segment_steps={s: steps[s] for s in segments},
            checkpoints=result.checkpoints,
            summary=summary,
            sources=result.sources,
            figures=[str(p) for p in figures],
            gifs=[str(p) for p in result.gifs],
        ),
        out_dir / f"{name}.json",
    )
    print(markdown)
    print(f"results: {out_dir}")
    return float(next(r for r in summary if r["segment"] == EPISODE)["reward"])


PROTOCOL_TITLES = {
    "quadrants": "Four-quadrant protocol (paper Sec. V-B, Fig. 4/5a)",
    "random_walk": "Random-walk instructions (the training distribution)",
}


def protocol_schedules(cfg: DictConfig) -> Callable[[int], Schedule]:
    """``episode -> schedule`` of ``eval.protocol``: each episode draws its own reference walks (the
    env draws its own initial states)."""
    if cfg.eval.protocol not in PROTOCOLS:
        raise ValueError(
            f"eval.protocol must be one of {sorted(PROTOCOLS)}, got {cfg.eval.protocol!r}"
        )
    protocol = PROTOCOLS[cfg.eval.protocol]
    return lambda episode: protocol(cfg.eval.steps, seed=cfg.seed + EPISODE_SEED_STRIDE * episode)
