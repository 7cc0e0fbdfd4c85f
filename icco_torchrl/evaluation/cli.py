"""``icco eval``: evaluate one or several checkpoints with a protocol and write the results.

    icco eval checkpoint=PATH [eval.protocol=random_walk|quadrants] [eval.trials=20] [eval.gif=true]
    icco eval eval.checkpoints='[runs/icco/*/checkpoint.pt,runs/qmix/*/checkpoint.pt]' eval.protocol=quadrants

Checkpoints of one method (several seeds) are pooled into one table row. Every checkpoint is
evaluated in the env the command line composes (by default the paper's task), so all methods
are scored by the same rewards; parameters that differ from a checkpoint's training env are
reported, and a different observation layout is refused. All checkpoints face the same initial
configurations (the env seed is ``seed + 20000``). Outputs go to ``eval.out_dir`` or to
``eval_<protocol>/`` next to the checkpoint(s): ``<name>_trials.csv`` (one row per
checkpoint, trial and segment, plus the whole episode), ``<name>_summary.csv``,
``<name>.json``, ``<name>.md`` and figures (PNG + PDF, GIFs with ``eval.gif=true``).
:func:`evaluate_and_report` is shared with ``icco instruct``.
"""
from __future__ import annotations

import glob
import logging
import os
import re
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Sequence

import torch
from omegaconf import DictConfig, OmegaConf

from icco_torchrl.evaluation.metrics import (EPISODE, markdown_table, method_label, segment_table, summarize,
                                             write_csv, write_json)
from icco_torchrl.evaluation.protocols import PROTOCOLS, Schedule, ScheduleRun, check_schedule, run_schedule, schedule_env
from icco_torchrl.training.checkpoint import CheckpointError, load_checkpoint
from icco_torchrl.training.config import ConfigError

logger = logging.getLogger(__name__)
EVAL_SEED_OFFSET = 20_000  # evaluation envs never replay the training envs' episodes
GIF_MAX_FRAMES = 300       # longer episodes are recorded every few steps
GIF_SIZE = 320


@contextmanager
def clean_errors(command: str):
    """Bad input (missing or incompatible checkpoint, bad value) ends the command with a
    one-line message and exit code 2 instead of a traceback."""
    try:
        yield
    except (CheckpointError, ConfigError, ValueError) as err:
        print(f"icco {command}: {err}", file=sys.stderr)
        raise SystemExit(2) from None


def find_checkpoints(cfg: DictConfig, root: str | Path = ".") -> list[Path]:
    """``checkpoint`` and ``eval.checkpoints`` (paths or globs), in order, without repeats.

    With neither given, the newest ``runs/*/*/checkpoint.pt`` under ``root``; a glob that
    matches nothing is an error naming it (a comparison never silently loses a method).
    """
    patterns = ([cfg.checkpoint] if cfg.checkpoint else []) + list(cfg.eval.checkpoints or [])
    if not patterns:
        found = sorted(Path(root).glob("runs/*/*/checkpoint.pt"), key=lambda p: p.stat().st_mtime)
        if not found:
            raise ValueError(f"no checkpoint given (checkpoint=PATH) and none found under "
                             f"{Path(root).resolve() / 'runs'}/*/*/checkpoint.pt: run `make train` first")
        return [found[-1]]
    paths: list[Path] = []
    for pattern in patterns:
        matches = sorted(glob.glob(str(pattern))) if glob.has_magic(str(pattern)) else [str(pattern)]
        if not matches:
            raise ValueError(f"checkpoint pattern {pattern!r} matched no file")
        paths += [Path(m) for m in matches if Path(m) not in paths]
    return paths


def default_out_dir(paths: Sequence[Path], name: str) -> Path:
    """``<folder of the checkpoints>/<name>``: the run folder, or the sweep folder holding them."""
    return Path(os.path.commonpath([str(p.resolve().parent) for p in paths])) / name


def _differences(eval_params: dict, trained_params: dict) -> list[str]:
    keys = sorted(set(eval_params) | set(trained_params))
    return [f"{k}: trained {trained_params.get(k)!r}, evaluated {eval_params.get(k)!r}"
            for k in keys if eval_params.get(k) != trained_params.get(k)]


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


def evaluate_and_report(cfg: DictConfig, paths: Sequence[Path], make_schedule: Callable[[], Schedule], *,
                        name: str, out_dir: Path, title: str, traj_segments: Sequence[int] | None = None,
                        label_suffix: str = "", meta: dict | None = None) -> float:
    """Run ``make_schedule()`` (fresh sources per checkpoint) on every checkpoint, write the
    tables, figures and GIFs into ``out_dir``, print the Markdown; returns the first method's
    mean episode reward. ``traj_segments`` picks the segments drawn (default: all);
    ``label_suffix`` is appended to the method names (e.g. "-TAP"); ``meta`` goes into the JSON."""
    from icco_torchrl.evaluation.plots import plot_bars, plot_trajectories

    torch.set_num_threads(cfg.train.threads)  # tiny networks: extra threads only contend on shared CPUs
    e = cfg.eval
    eval_params = OmegaConf.to_container(cfg.env.params, resolve=True)
    rows, runs, checkpoints, sources, gifs = [], {}, [], [], []
    for path in paths:
        schedule = make_schedule()
        total = check_schedule(schedule, e.trials)
        try:
            restored = schedule_env(path, total, e.trials, device=cfg.device, seed=cfg.seed + EVAL_SEED_OFFSET,
                                    **eval_params)
        except CheckpointError as err:
            trained = load_checkpoint(path)["cfg"]["env"]["params"]
            raise CheckpointError(f"{err} (env.params on the command line vs training: "
                                  f"{'; '.join(_differences(eval_params, trained)) or 'none'})") from None
        trained = OmegaConf.to_container(restored["cfg"], resolve=True)
        label, seed = method_label(trained, label_suffix), trained["seed"]
        diffs = _differences(eval_params, trained["env"]["params"])
        if diffs:
            print(f"note: {path} is evaluated in another env than it was trained in: " + "; ".join(diffs))
        checkpoints.append(dict(path=str(path), method=label, seed=seed, frames=restored["checkpoint"].get("frames"),
                                env_differences=diffs))
        for episode in range(e.episodes):
            record = e.gif and episode == 0 and label not in runs
            on_step, frames = _gif_recorder(total) if record else (None, None)
            run = run_schedule(restored["env"], restored["policy"], schedule, e.trials, on_step=on_step,
                               method=label, seed=seed, checkpoint=str(path), episode=episode)
            rows += run.rows
            sources += [dict(method=label, seed=seed, episode=episode, **s) for s in run.sources]
            runs.setdefault(label, run)
            if record:
                from icco_torchrl.envs.render import write_gif

                gifs.append(out_dir / f"{name}_{slug(label)}.gif")
                write_gif(frames, gifs[-1], fps=10)

    summary = summarize(rows, by=("method", "segment"))
    segments = list(dict.fromkeys(r["segment"] for r in rows if r["segment"] != EPISODE))
    table = markdown_table(summary)
    per_segment = segment_table(summary, "reward")
    steps = {r["segment"]: r["steps"] for r in rows}
    header = (f"# {title}\n\n{e.trials} trials x {e.episodes} episode(s) per checkpoint; segments: "
              + ", ".join(f"{s} ({steps[s]} steps)" for s in segments)
              + ".\nMean ± std over trials (seeds pooled). Rewards are team totals (sum over robots).\n")
    markdown = f"{header}\n## Whole episode\n\n{table}\n\n## Team reward per segment\n\n{per_segment}\n"
    out_dir.mkdir(parents=True, exist_ok=True)
    write_csv(rows, out_dir / f"{name}_trials.csv")
    write_csv(summary, out_dir / f"{name}_summary.csv")
    (out_dir / f"{name}.md").write_text(markdown)
    figures = plot_bars(summary, out_dir / f"{name}_reward", "reward", segments=[*segments, EPISODE],
                        ylabel="team reward")
    figures += plot_trajectories(runs, out_dir / f"{name}_trajectories",
                                 segments=range(len(segments)) if traj_segments is None else traj_segments)
    write_json(dict(**(meta or {}), title=title, name=name, trials=e.trials, episodes=e.episodes, segments=segments,
                    segment_steps={s: steps[s] for s in segments},
                    checkpoints=checkpoints, summary=summary, sources=sources,
                    figures=[str(p) for p in figures], gifs=[str(p) for p in gifs]), out_dir / f"{name}.json")
    print(markdown)
    print(f"results: {out_dir}")
    first = next(r for r in summary if r["segment"] == EPISODE)
    return float(first["reward"])


def run_eval(cfg: DictConfig, run_dir: str | Path) -> float:
    """``icco eval``: the mean episode team reward of the first method (see the module doc)."""
    with clean_errors("eval"):
        if cfg.eval.protocol not in PROTOCOLS:
            raise ValueError(f"eval.protocol must be one of {sorted(PROTOCOLS)}, got {cfg.eval.protocol!r}")
        paths = find_checkpoints(cfg)
        name = cfg.eval.protocol
        out_dir = Path(cfg.eval.out_dir) if cfg.eval.out_dir else default_out_dir(paths, f"eval_{name}")
        protocol = PROTOCOLS[name]
        title = {"quadrants": "Four-quadrant protocol (paper Sec. V-B, Fig. 4/5a)",
                 "random_walk": "Random-walk instructions (the training distribution)"}[name]
        return evaluate_and_report(cfg, paths, lambda: protocol(cfg.eval.steps, seed=cfg.seed), name=name,
                                   out_dir=out_dir, title=title, traj_segments=[0])
