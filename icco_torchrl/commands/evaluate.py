"""``icco eval``: evaluate one or several checkpoints with a protocol and write the results.

    icco eval checkpoint=PATH [eval.protocol=random_walk|quadrants] [eval.trials=20] [eval.gif=true]
    icco eval eval.checkpoints='[runs/icco/*/checkpoint.pt,runs/qmix/*/checkpoint.pt]'

``eval.checkpoints`` (paths or globs) compares several checkpoints, one row per method.

Outputs go to ``eval.out_dir`` or to ``eval_<protocol>/`` next to the checkpoint(s); what is
measured and written: :mod:`icco_torchrl.evaluation.runner`.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from icco_torchrl.commands import Command, clean_errors
from icco_torchrl.evaluation.runner import (
    PROTOCOL_TITLES,
    default_out_dir,
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
        out_dir = (
            Path(cfg.eval.out_dir) if cfg.eval.out_dir else default_out_dir(paths, f"eval_{name}")
        )
        result = evaluate_checkpoints(
            cfg, paths, schedules, gif_stem=out_dir / name if cfg.eval.gif else None
        )
        return write_report(
            result, cfg, name=name, out_dir=out_dir, title=PROTOCOL_TITLES[name], traj_segments=[0]
        )


EVAL = Command(run=run_eval)
