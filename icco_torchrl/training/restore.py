"""Rebuild a trained policy from a checkpoint, for evaluation, demos and language protocols."""
from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from icco_torchrl.modules.policy import make_policy
from icco_torchrl.training.build import EVAL_SEED_OFFSET, action_count, make_env, make_loss, make_modules
from icco_torchrl.training.checkpoint import CheckpointError, load_checkpoint, load_weights, save_checkpoint
from icco_torchrl.training.config import resolve_device, validate


def restore(path: str | Path, *, num_envs: int | None = None, device: str = "cpu", seed: int | None = None,
            **env_overrides) -> dict:
    """``{"cfg", "env", "policy", "loss", "layout", "checkpoint"}`` with the trained weights loaded.

    ``env_overrides`` change env parameters for evaluation (e.g. ``max_steps=580``,
    ``waypoint_mode="external"``); parameters that change the observation layout (robot,
    resource, invader or waypoint counts) are refused with a message naming them.
    """
    ckpt = load_checkpoint(path)
    cfg = validate(OmegaConf.create(ckpt["cfg"]))
    dev = resolve_device(device)
    cfg.device = str(dev)
    env = make_env(cfg, num_envs=num_envs, seed=cfg.seed + EVAL_SEED_OFFSET if seed is None else seed, device=dev, **env_overrides)
    layout = env.base_env.layout
    saved = ckpt.get("layout", {})
    diffs = [f"{k}: checkpoint {saved[k]} vs env {getattr(layout, k)}" for k in saved if saved[k] != getattr(layout, k)]
    if diffs:
        raise CheckpointError(f"checkpoint {path} was trained for another env layout: " + "; ".join(diffs))
    mods = make_modules(cfg, layout, dev, n_actions=action_count(env))
    loss = make_loss(cfg, mods)
    weights = ckpt["loss"]
    if ckpt.get("policy_only"):  # an exported policy (export_policy): the targets are the online weights
        weights = {**weights, **{f"target_{k}": v for k, v in weights.items() if f"target_{k}" in loss.state_dict()}}
    load_weights(loss, weights, path, cfg.method.name)
    policy = make_policy(mods["agent"], env.full_action_spec_unbatched, mods["coordinator"])
    return {"cfg": cfg, "env": env, "policy": policy, "loss": loss, "layout": layout, "checkpoint": ckpt}


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
