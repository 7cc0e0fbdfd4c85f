"""``icco live`` and ``icco bridge``: a trained team on a web page, or robots over UDP.

Both are implemented in :mod:`icco_torchrl.live.cli`; here they become commands, and an error
of the machine (a port in use, bad limits, no checkpoint) ends them in one line.
"""

from __future__ import annotations

import sys
from pathlib import Path

from omegaconf import DictConfig

from icco_torchrl.commands import Command, results_beside_checkpoint


def _run(command: str, cfg: DictConfig) -> float:
    from icco_torchrl.live.cli import run_bridge, run_live

    try:
        return (run_live if command == "live" else run_bridge)(cfg)
    except (OSError, ValueError) as err:
        print(f"icco {command}: {err}", file=sys.stderr)
        raise SystemExit(2) from None


def run_live(cfg: DictConfig, run_dir: str | Path) -> float:
    """``icco live [checkpoint=PATH]``: see :func:`icco_torchrl.live.cli.run_live`."""
    return _run("live", cfg)


def run_bridge(cfg: DictConfig, run_dir: str | Path) -> float:
    """``icco bridge checkpoint=PATH``: see :func:`icco_torchrl.live.cli.run_bridge`."""
    return _run("bridge", cfg)


def prepare(command: str, args: list[str]) -> tuple[list[str], dict]:
    """Hydra's overrides, as every command's, with the token kept out of the files Hydra writes
    (:func:`icco_torchrl.live.guard.keep_token_out`)."""
    from icco_torchrl.live.guard import keep_token_out

    overrides, options = results_beside_checkpoint(command, args)
    return keep_token_out(overrides), options


LIVE = Command(run=run_live, prepare=prepare)
BRIDGE = Command(run=run_bridge, prepare=prepare)
