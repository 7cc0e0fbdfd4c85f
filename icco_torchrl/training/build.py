"""Config -> env, modules, policy, loss, segment cutter. Every method goes through here.

A method differs only by its ``method`` config group: with or without a coordinator (and its
posterior), agents reading their local view or the global state, CE weights.
"""
from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs import TransformedEnv

from icco_torchrl.envs import ResourceCollectionEnv
from icco_torchrl.modules import make_agent, make_coordinator, make_mixer, make_posterior
from icco_torchrl.modules.policy import make_policy, make_primer
from icco_torchrl.objectives import ICCOLoss
from icco_torchrl.training.config import resolve_device, validate
from icco_torchrl.training.segments import SegmentCutter

def _conf_dir() -> Path:
    """The Hydra config tree: ``conf/`` of a source checkout, else the copy a wheel installs as
    ``icco_torchrl/conf`` (pyproject maps the top-level folder into the package)."""
    checkout = Path(__file__).resolve().parents[2] / "conf"
    if (checkout / "config.yaml").is_file():
        return checkout
    return Path(__file__).resolve().parents[1] / "conf"


CONF_DIR = _conf_dir()
# The methods (conf/method/*.yaml) and the paper's names for them.
METHODS = ("icco", "icco_wo_ce", "qmix", "qmix_full")
METHOD_LABELS = {"icco": "ICCO", "icco_wo_ce": "ICCO w/o CE", "qmix": "QMIX", "qmix_full": "QMIX (FULL)"}
# Env seeds relative to cfg.seed: training uses the seed itself, the evaluations during training
# seed + VALIDATION_SEED_OFFSET, evaluations of a trained policy (icco eval/instruct, restore) seed +
# EVAL_SEED_OFFSET, so none replays another's episodes; evaluation episode e draws its reference
# walks with seed + EPISODE_SEED_STRIDE * e.
VALIDATION_SEED_OFFSET = 10_000
EVAL_SEED_OFFSET = 20_000
EPISODE_SEED_STRIDE = 1_000


def compose_config(overrides: list[str] | None = None, config_name: str = "config") -> DictConfig:
    """The validated config from ``conf/`` with Hydra-style overrides (for scripts and tests)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose(config_name=config_name, overrides=list(overrides or []))
    return validate(cfg)


def make_env(cfg: DictConfig, *, num_envs: int | None = None, seed: int | None = None,
             device: torch.device | str = "cpu", **overrides) -> TransformedEnv:
    """The batched env with the primer that carries the policy's recurrent state."""
    params = {**OmegaConf.to_container(cfg.env.params, resolve=True), **overrides}
    base = ResourceCollectionEnv(num_envs=num_envs or cfg.env.num_envs, device=device,
                                 seed=cfg.seed if seed is None else seed, **params)
    m = cfg.method
    return TransformedEnv(base, make_primer(base.n_agents, m.hidden, m.z_dim if m.coordinator else 0, device=device,
                                            n_actions=action_count(base)))


def action_count(env) -> int:
    """The number of discrete actions, read from the env's action spec."""
    return int(env.full_action_spec[env.action_key].space.n)


def make_modules(cfg: DictConfig, layout, device, *, n_actions: int) -> dict:
    """Agent, mixer and (for ICCO) coordinator and posterior, on ``device``."""
    m = cfg.method
    z_dim = m.z_dim if m.coordinator else 0
    mods = {"agent": make_agent(layout, n_actions=n_actions, hidden=m.hidden, z_dim=z_dim, full_state=m.full_state,
                                encoder=m.encoder, state_encoder=m.state_encoder),
            "mixer": make_mixer(layout.state_dim, layout.n_agents, device=device),
            "coordinator": None, "posterior": None}
    if m.coordinator:
        mods["coordinator"] = make_coordinator(layout, z_dim=m.z_dim, hidden=m.hidden, period=m.period,
                                               encoder=m.encoder, state_encoder=m.state_encoder,
                                               init_logvar=m.z_init_logvar)
        if m.ce_coef > 0:
            mods["posterior"] = make_posterior(layout, n_actions=n_actions, z_dim=m.z_dim, hidden=m.hidden,
                                               combine=m.posterior)
    for mod in mods.values():
        if mod is not None:
            mod.to(device)
    return mods


def make_loss(cfg: DictConfig, mods: dict) -> ICCOLoss:
    m, t = cfg.method, cfg.train
    return ICCOLoss(mods["agent"], mods["mixer"], mods["coordinator"], mods["posterior"], gamma=t.gamma,
                    td_lambda=t.td_lambda, double_q=t.double_q, ce_coef=m.ce_coef if m.coordinator else 0.0,
                    entropy_coef=m.entropy_coef if m.coordinator else 0.0)


def build_components(cfg: DictConfig | None = None, *, method: str | None = None, num_envs: int | None = None,
                     device: str = "cpu", seed: int = 0) -> dict:
    """Everything but the collector/buffer, for benchmarks, tests and evaluation."""
    if cfg is None:
        cfg = compose_config([f"method={method or 'icco'}", f"seed={seed}", f"device={device}"])
    device = resolve_device(cfg.device)
    env = make_env(cfg, num_envs=num_envs, device=device)
    layout = env.base_env.layout
    mods = make_modules(cfg, layout, device, n_actions=action_count(env))
    policy = make_policy(mods["agent"], env.full_action_spec_unbatched, mods["coordinator"],
                         eps_init=cfg.train.eps_init, eps_end=cfg.train.eps_end)
    loss = make_loss(cfg, mods)
    cutter = SegmentCutter(length=cfg.method.period)
    return {"cfg": cfg, "env": env, "layout": layout, "policy": policy, "loss": loss, "cutter": cutter, **mods}
