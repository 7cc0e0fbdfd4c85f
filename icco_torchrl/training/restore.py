"""Rebuild a trained policy from a checkpoint (through the one assembler): evaluation, demos.

What a checkpoint holds and how it is read, checked and exported is
:mod:`icco_torchrl.training.checkpoint`'s; this module only assembles the networks around it.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from icco_torchrl.training.build import EVAL_SEED_OFFSET, Run, build
from icco_torchrl.training.checkpoint import (  # noqa: F401 (export_policy: its old home)
    POLICY_KEYS,
    check_compatible,
    export_policy,
    load_checkpoint,
    load_weights,
    policy_weights,
)
from icco_torchrl.training.config import resolve_device, validate


def restore(
    path: str | Path,
    *,
    num_envs: int | None = None,
    device: str = "cpu",
    seed: int | None = None,
    **env_overrides,
) -> Run:
    """The checkpoint's :class:`~icco_torchrl.training.build.Run` with its weights loaded
    (``run.checkpoint`` holds the file's contents; ``run["policy"]`` etc. as before).

    ``env_overrides`` change env parameters for evaluation (e.g. ``max_steps=580``,
    ``waypoint_mode="external"``); parameters that change the observation layout (robot,
    resource, invader or waypoint counts) are refused with a message naming them.
    """
    ckpt = load_checkpoint(path)
    cfg = validate(OmegaConf.create(ckpt["cfg"]))
    cfg.device = str(resolve_device(device))
    run = build(
        cfg,
        num_envs=num_envs,
        seed=cfg.seed + EVAL_SEED_OFFSET if seed is None else seed,
        **env_overrides,
    )
    check_compatible(ckpt, cfg, run.layout, path)
    load_weights(run.loss, policy_weights(ckpt, run.loss), path, cfg.method.name)
    run.checkpoint = ckpt
    return run
