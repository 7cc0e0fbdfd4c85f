"""Rebuild a trained policy from a checkpoint (through the one assembler): evaluation, demos."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from icco_torchrl.training.build import EVAL_SEED_OFFSET, Run, build
from icco_torchrl.training.checkpoint import (
    check_compatible,
    load_checkpoint,
    load_weights,
    save_checkpoint,
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
    weights = ckpt["loss"]
    if ckpt.get(
        "policy_only"
    ):  # an exported policy (export_policy): the targets are the online weights
        weights = {
            **weights,
            **{
                f"target_{k}": v
                for k, v in weights.items()
                if f"target_{k}" in run.loss.state_dict()
            },
        }
    load_weights(run.loss, weights, path, cfg.method.name)
    run.checkpoint = ckpt
    return run


POLICY_KEYS = ("format_version", "cfg", "layout", "frames", "updates")


def export_policy(src: str | Path, dst: str | Path) -> Path:
    """A small weights-only checkpoint of ``src`` for acting, not for training: the networks without
    their target copies, the optimiser, the RNG state or the replay bookkeeping (about half the
    size). :func:`restore` loads it like any checkpoint; ``resume=`` cannot continue from it."""
    ckpt = load_checkpoint(src)
    slim = {k: ckpt[k] for k in POLICY_KEYS if k in ckpt}
    slim["loss"] = {k: v for k, v in ckpt["loss"].items() if not k.startswith("target_")}
    slim["policy_only"] = True
    return save_checkpoint(dst, slim)
