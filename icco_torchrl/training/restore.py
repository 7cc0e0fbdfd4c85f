"""Rebuild a trained policy from a checkpoint (through the one assembler): evaluation, demos.

What a checkpoint holds and how it is read, checked and exported is
:mod:`icco_torchrl.training.checkpoint`'s; this module only assembles the networks around it,
for the team size it was trained with or, when its acting networks read any team, another one.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from icco_torchrl.envs.layout import ObsLayout
from icco_torchrl.training.build import EVAL_SEED_OFFSET, Run, build
from icco_torchrl.training.checkpoint import (
    check_compatible,
    load_checkpoint,
    load_weights,
    policy_weights,
)
from icco_torchrl.training.config import resolve_device, validate
from icco_torchrl.training.run_folder import CheckpointError

# The networks that act (the policy): at another team size only their weights are loaded.
ACTING = (
    "agent_params.",
    "coordinator_params.",
    "target_agent_params.",
    "target_coordinator_params.",
)


def resized_layout(layout: dict, n_agents: int) -> dict:
    """A saved layout (``ObsLayout`` fields) for a team of ``n_agents``
    (:meth:`~icco_torchrl.envs.layout.ObsLayout.with_agents`, the env's layout rule)."""
    return {**layout, **vars(ObsLayout.from_dict(layout).with_agents(n_agents))}


def acting_weights(ckpt: dict, run: Run, path: str | Path, trained: int) -> dict:
    """The loss's state with the checkpoint's agent and coordinator weights in it (the mixer and
    posterior, which only training reads, keep their fresh weights); a checkpoint whose acting
    networks have a shape that depends on the team size is refused in one line."""
    team = run.layout.n_agents
    fresh = run.loss.state_dict()
    saved = {k: v for k, v in policy_weights(ckpt, run.loss).items() if k.startswith(ACTING)}
    sized = sorted(
        k for k, v in saved.items() if k in fresh and tuple(v.shape) != tuple(fresh[k].shape)
    )
    if sized:
        m = ckpt["cfg"]["method"]
        raise CheckpointError(
            f"checkpoint {path} cannot act in a team of {team} robots (trained with n_agents="
            f"{trained}): its acting networks depend on the team size (method.encoder="
            f"{m.get('encoder')}, state_encoder={m.get('state_encoder')}, full_state="
            f"{m.get('full_state')}; weights {', '.join(sized[:2])}); evaluate it at "
            f"eval.team_size={trained}"
        )
    return {**fresh, **saved}


def set_broadcast_threshold(run: Run, threshold: float) -> bool:
    """Set the acting coordinator's broadcast threshold (beta) and the restored config's; False
    when the method has no coordinator (nothing to set)."""
    from icco_torchrl.modules.coordinator import Coordinator

    if isinstance(threshold, bool) or not float(threshold) >= 0:
        raise ValueError(f"broadcast_threshold must be >= 0, got {threshold!r}")
    found = False
    for module in run.policy.modules():
        if isinstance(module, Coordinator):
            module.threshold, found = float(threshold), True
    if found:
        run.cfg.method.broadcast_threshold = float(threshold)
    return found


def restore(
    path: str | Path,
    *,
    num_envs: int | None = None,
    device: str = "cpu",
    seed: int | None = None,
    broadcast_threshold: float | None = None,
    **env_overrides,
) -> Run:
    """The checkpoint's :class:`~icco_torchrl.training.build.Run` with its weights loaded
    (``run.checkpoint`` holds the file's contents; ``run["policy"]`` etc. as before).

    ``env_overrides`` change env parameters for evaluation (e.g. ``max_steps=580``,
    ``waypoint_mode="external"``); parameters that change the observation layout (resource,
    invader or waypoint counts) are refused with a message naming them. ``n_agents`` other than
    the checkpoint's runs another team size: the agent and coordinator weights are loaded (they
    read any team with the default encoders), the mixer and posterior are left fresh (acting never
    reads them), and acting networks tied to one team size are refused in one line.
    ``broadcast_threshold`` replaces the coordinator's beta (:func:`set_broadcast_threshold`).
    """
    ckpt = load_checkpoint(path)
    cfg = validate(OmegaConf.create(ckpt["cfg"]))
    cfg.device = str(resolve_device(device))
    trained = int(cfg.env.params.n_agents)
    team = env_overrides.get("n_agents", trained)
    if isinstance(team, bool) or not isinstance(team, int) or team < 1:
        raise ValueError(f"n_agents (the team size) must be an integer >= 1, got {team!r}")
    run = build(
        cfg,
        num_envs=num_envs,
        seed=cfg.seed + EVAL_SEED_OFFSET if seed is None else seed,
        **env_overrides,
    )
    layout = ckpt["layout"] if team == trained else resized_layout(ckpt["layout"], team)
    check_compatible(ckpt["cfg"], layout, cfg, run.layout, path)
    if team == trained:
        weights = policy_weights(ckpt, run.loss)
    else:
        weights = acting_weights(ckpt, run, path, trained)
    load_weights(run.loss, weights, path, cfg.method.name)
    if broadcast_threshold is not None:
        set_broadcast_threshold(run, broadcast_threshold)
    run.checkpoint = ckpt
    return run
