"""``icco eval``: evaluate one or several checkpoints with a protocol and write the results.

    icco eval checkpoint=PATH [eval.protocol=random_walk|quadrants] [eval.trials=20] [eval.gif=true]
    icco eval eval.checkpoints='[runs/icco/*/checkpoint.pt,runs/qmix/*/checkpoint.pt]'

``eval.checkpoints`` (paths or globs) compares several checkpoints, one row per method.

    icco eval checkpoint=PATH eval.protocol=quadrants eval.team_size=5     # another team size
    icco eval checkpoint=PATH eval.broadcast_threshold=0.5                  # another beta

``eval.team_size`` runs every checkpoint and reference with that many robots (default: the
checkpoints' ``n_agents``); a checkpoint trained on another size acts zero-shot when its agent
and coordinator read any team, and is refused in one line otherwise.
``eval.broadcast_threshold`` replaces the coordinators' beta (no retraining); the tables then
report ``broadcast_rate``, the share of robot-steps on which a robot received a z.

A checkpoint with a coordinator is also measured for what the consistency term is for
(``eval.coordination``: the mutual-information lower bound with a posterior fitted after
training, and swap consistency; docs/consistency.md), about 5 s each;
``eval.coordination.enabled=false`` skips it.

Outputs go to ``eval.out_dir`` or to ``eval_<protocol>/`` next to the checkpoint(s) (for the
demo policy and other checkpoints that ship with the project, to
``runs/<checkpoint name>/eval_<protocol>/``: :func:`~icco_torchrl.commands.results_dir`); what
is measured and written: :mod:`icco_torchrl.evaluation.runner`.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from icco_torchrl.commands import Command, clean_errors, results_dir
from icco_torchrl.evaluation.runner import (
    PROTOCOL_TITLES,
    evaluate_checkpoints,
    find_checkpoints,
    protocol_schedules,
    write_report,
)


def run_eval(cfg: DictConfig, run_dir: str | Path) -> float:
    """``icco eval``: the mean episode team reward of the first method (see the module doc)."""
    with clean_errors("eval"):
        schedules = protocol_schedules(cfg)
        paths = find_checkpoints(cfg)
        given = bool(cfg.checkpoint or cfg.eval.checkpoints)
        print(
            ("evaluating " if given else "no checkpoint= given: evaluating the newest, ")
            + ", ".join(map(str, paths)),
            flush=True,
        )
        name = cfg.eval.protocol
        out_dir = results_dir(cfg.eval.out_dir, paths, f"eval_{name}")
        result = evaluate_checkpoints(
            cfg,
            paths,
            schedules,
            gif_stem=out_dir / name if cfg.eval.gif else None,
            coordination=cfg.eval.coordination.enabled,
        )
        return write_report(
            result, cfg, name=name, out_dir=out_dir, title=PROTOCOL_TITLES[name], traj_segments=[0]
        )


EVAL = Command(run=run_eval)
