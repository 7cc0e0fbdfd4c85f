"""The one assembler: ``build(cfg) -> Run`` (env, evaluation env, networks, policy, loss, optimiser,
target updater, replay buffer, segment cutter). Every method and every user goes through here:
the trainer, checkpoint restore (``icco eval``, ``icco instruct``, the live loop), the benchmarks.

A method differs only by its ``method`` config group: with or without a coordinator (and its
posterior), agents reading their local view or the global state, CE weights.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer
from torchrl.envs import TransformedEnv

from icco_torchrl.envs import ResourceCollectionEnv
from icco_torchrl.envs.layout import ObsLayout
from icco_torchrl.envs.shaping import PotentialShaping
from icco_torchrl.modules import make_agent, make_coordinator, make_mixer, make_posterior
from icco_torchrl.modules.policy import make_policy, make_primer
from icco_torchrl.objectives import ICCOLoss, make_target_updater
from icco_torchrl.training.config import (
    ConfigError,
    compose_config,
    resolve_device,
    set_env_params,
)
from icco_torchrl.training.segments import SegmentCutter
from icco_torchrl.training.update import Update

# Env seeds relative to cfg.seed: training uses the seed itself, the evaluations during training
# seed + VALIDATION_SEED_OFFSET, evaluations of a trained policy (icco eval/instruct, restore) seed
# + EVAL_SEED_OFFSET, so none replays another's episodes; evaluation episode e draws its reference
# walks with seed + EPISODE_SEED_STRIDE * e.
VALIDATION_SEED_OFFSET = 10_000
EVAL_SEED_OFFSET = 20_000
EPISODE_SEED_STRIDE = 1_000


def make_env(
    cfg: DictConfig,
    *,
    num_envs: int | None = None,
    seed: int | None = None,
    device: torch.device | str = "cpu",
    shaping=None,
    **overrides,
) -> TransformedEnv:
    """The batched env with the primer that carries the policy's recurrent state, and with
    ``shaping`` (a ``train.shaping`` node) its potential-based reward shaping."""
    params = {**OmegaConf.to_container(cfg.env.params, resolve=True), **overrides}
    base = ResourceCollectionEnv(
        num_envs=num_envs or cfg.env.num_envs,
        device=device,
        seed=cfg.seed if seed is None else seed,
        **params,
    )
    m = cfg.method
    env = TransformedEnv(
        base,
        make_primer(
            base.n_agents,
            m.hidden,
            m.z_dim if m.coordinator else 0,
            device=device,
            n_actions=action_count(base),
        ),
    )
    if shaping is not None and shaping.potentials:
        potentials = list(shaping.potentials)
        env.append_transform(
            PotentialShaping.for_env(base, potentials, shaping.weight, cfg.train.gamma)
        )
    return env


def action_count(env) -> int:
    """The number of discrete actions, read from the env's action spec."""
    return int(env.full_action_spec[env.action_key].space.n)


def make_modules(cfg: DictConfig, layout, device, *, n_actions: int) -> dict:
    """Agent, mixer and (for ICCO) coordinator and posterior, on ``device``."""
    m = cfg.method
    z_dim = m.z_dim if m.coordinator else 0
    mods = {
        "agent": make_agent(
            layout,
            n_actions=n_actions,
            hidden=m.hidden,
            z_dim=z_dim,
            full_state=m.full_state,
            encoder=m.encoder,
            state_encoder=m.state_encoder,
            waypoint_features=m.waypoint_features,
            layer_norm=m.layer_norm,
        ),
        "mixer": make_mixer(
            layout.state_dim,
            layout.n_agents,
            kind=m.mixer,
            layout=layout,
            hidden=m.hidden,
            device=device,
        ),
        "coordinator": None,
        "posterior": None,
    }
    if m.coordinator:
        mods["coordinator"], mods["posterior"] = _make_coordination(m, layout, n_actions)
    for mod in mods.values():
        if mod is not None:
            mod.to(device)
    return mods


def _make_coordination(m: DictConfig, layout, n_actions: int) -> tuple:
    """The coordinator of ``method`` node ``m`` and, with ``ce_coef > 0``, its posterior."""
    coordinator = make_coordinator(
        layout,
        z_dim=m.z_dim,
        hidden=m.hidden,
        period=m.period,
        encoder=m.encoder,
        state_encoder=m.state_encoder,
        init_logvar=m.z_init_logvar,
        threshold=m.broadcast_threshold,
    )
    posterior = None
    if m.ce_coef > 0:
        posterior = make_posterior(
            layout,
            n_actions=n_actions,
            z_dim=m.z_dim,
            hidden=m.hidden,
            combine=m.posterior,
            inputs=m.posterior_input,
        )
    return coordinator, posterior


def make_loss(cfg: DictConfig, mods: dict, layout: ObsLayout) -> ICCOLoss:
    """The loss of ``mods`` (:func:`make_modules`) for an env of ``layout``."""
    m, t = cfg.method, cfg.train
    return ICCOLoss(
        mods["agent"],
        mods["mixer"],
        mods["coordinator"],
        mods["posterior"],
        gamma=t.gamma,
        td_lambda=t.td_lambda,
        burn_in=t.burn_in,
        double_q=t.double_q,
        ce_coef=m.ce_coef if m.coordinator else 0.0,
        entropy_coef=m.entropy_coef if m.coordinator else 0.0,
        ce_clamp=t.ce_clamp,
        layout=layout,
    )


def make_optimizer(cfg: DictConfig, loss: ICCOLoss) -> torch.optim.Optimizer:
    """``train.optimizer`` over the loss's parameters: foreach (multi-tensor kernels), or with
    ``train.compile`` or ``train.cudagraphs`` Adam's fused kernel (one op a step); capturable
    in a CUDA graph with ``train.cudagraphs``."""
    t = cfg.train
    graphs = bool(t.cudagraphs)
    if t.optimizer == "rmsprop":
        return torch.optim.RMSprop(
            loss.parameters(), lr=t.lr, alpha=0.99, eps=1e-5, foreach=True, capturable=graphs
        )
    if t.compile or graphs:
        return torch.optim.Adam(loss.parameters(), lr=t.lr, fused=True, capturable=graphs)
    return torch.optim.Adam(loss.parameters(), lr=t.lr, foreach=True)


def make_update(cfg: DictConfig, loss: ICCOLoss, optim: torch.optim.Optimizer) -> Update:
    """One gradient update of ``loss`` (``train.compile``, ``train.cudagraphs``)."""
    t = cfg.train
    return Update(
        loss,
        optim,
        grad_clip=t.grad_clip,
        compile=t.compile,
        compile_mode=t.compile_mode,
        cudagraphs=t.cudagraphs,
    )


@dataclass
class Run:
    """What :func:`build` assembles for one config. Training parts (evaluation env, optimiser,
    target updater, replay buffer) are None unless built ``for_training``; ``checkpoint`` is set
    by :func:`~icco_torchrl.training.restore.restore`. Indexing by name (``run["policy"]``) works as
    it did on the dicts ``build_components`` and ``restore`` returned."""

    cfg: DictConfig
    env: TransformedEnv
    layout: ObsLayout
    agent: nn.Module
    mixer: nn.Module
    coordinator: nn.Module | None
    posterior: nn.Module | None
    policy: nn.Module
    loss: ICCOLoss
    cutter: SegmentCutter
    eval_env: TransformedEnv | None = None
    optim: torch.optim.Optimizer | None = None
    updater: object | None = None
    update: Update | None = None
    buffer: TensorDictReplayBuffer | None = None
    checkpoint: dict | None = None

    def __getitem__(self, name: str):
        return getattr(self, name)

    def __contains__(self, name: str) -> bool:
        return name in self.__dataclass_fields__


def build(
    cfg: DictConfig,
    *,
    num_envs: int | None = None,
    seed: int | None = None,
    device=None,
    for_training: bool = False,
    **env_overrides,
) -> Run:
    """Assemble ``cfg`` on ``device`` (default ``cfg.device``). ``num_envs``, ``seed`` and
    ``env_overrides`` change the env (an evaluation env, say); ``for_training`` applies
    ``train.env_params`` and ``train.shaping`` to the training env and adds the evaluation env
    (``train.eval_envs`` envs, seed + VALIDATION_SEED_OFFSET, ``env.params`` without them),
    optimiser, target updater and replay buffer. Objects are made in a fixed order, so a seed gives
    the same weights every time."""
    device = resolve_device(cfg.device if device is None else str(device))
    t = cfg.train
    env, eval_env = _make_envs(
        cfg, num_envs=num_envs, seed=seed, device=device, for_training=for_training, **env_overrides
    )
    layout = env.base_env.layout
    mods = make_modules(cfg, layout, device, n_actions=action_count(env))
    guide = _explore_guide(cfg, env) if for_training and t.get("explore_guide") else None
    policy = make_policy(
        mods["agent"],
        env.full_action_spec_unbatched,
        mods["coordinator"],
        eps_init=t.eps_init,
        eps_end=t.eps_end,
        guide=guide,
    )
    loss = make_loss(cfg, mods, layout)
    run = Run(
        cfg=cfg,
        env=env,
        layout=layout,
        **mods,
        policy=policy,
        loss=loss,
        cutter=SegmentCutter(length=t.sequence_length),
        eval_env=eval_env,
    )
    if for_training:
        _add_training_parts(run, device)
    return run


def _make_envs(cfg: DictConfig, *, num_envs, seed, device, for_training: bool, **env_overrides):
    """:func:`build`'s env and, ``for_training``, its evaluation env (else None)."""
    t = cfg.train
    if for_training:  # training-only env parameters (reward shaping); evaluations keep env.params
        env_overrides = {**set_env_params(t.env_params), **env_overrides}
        if t.get("team_sizes"):  # per-env team sizes: the training env only, like env_params
            env_overrides.setdefault("team_sizes", tuple(t.team_sizes))
    shaping = t.shaping if for_training else None
    env = make_env(
        cfg, num_envs=num_envs, seed=seed, device=device, shaping=shaping, **env_overrides
    )
    eval_env = (
        make_env(cfg, num_envs=t.eval_envs, seed=cfg.seed + VALIDATION_SEED_OFFSET, device=device)
        if for_training
        else None
    )
    return env, eval_env


def _explore_guide(cfg: DictConfig, env: TransformedEnv):
    """``train.explore_guide``'s scripted policy."""
    from icco_torchrl.envs.reference_policies import make_reference_policy

    try:
        return make_reference_policy(
            cfg.train.explore_guide, env, radius=cfg.eval.blend_radius, seed=cfg.seed
        )
    except (TypeError, ValueError) as err:
        raise ConfigError(f"config field 'train.explore_guide': {err}") from None


def _add_training_parts(run: Run, device) -> None:
    """The optimiser, update, target updater and replay buffer of ``run``."""
    cfg, loss = run.cfg, run.loss
    t = cfg.train
    run.optim = make_optimizer(cfg, loss)
    run.update = make_update(cfg, loss, run.optim)
    run.updater = make_target_updater(
        loss, t.target_update, interval=t.target_update_interval, tau=t.tau
    )
    run.buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(t.buffer_segments, device=device),
        sampler=RandomSampler(),
        batch_size=t.batch_segments,
    )


def build_components(
    cfg: DictConfig | None = None,
    *,
    method: str | None = None,
    num_envs: int | None = None,
    device: str = "cpu",
    seed: int = 0,
) -> Run:
    """:func:`build` for scripts and tests: without ``cfg``, the composed config of ``method``."""
    if cfg is None:
        cfg = compose_config([f"method={method or 'icco'}", f"seed={seed}", f"device={device}"])
    return build(cfg, num_envs=num_envs)
