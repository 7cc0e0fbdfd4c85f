"""Typed schema of the Hydra config: unknown or ill-typed fields fail before any work starts.

The YAML tree under ``conf/`` is composed by Hydra, then merged into these dataclasses with
OmegaConf in struct mode, so a typo (``train.totl_frames``) or a wrong type
(``train.total_frames=lots``) raises a ``ConfigError`` naming the field. Field meanings are
commented in the YAML files.
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Any, Optional

import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from icco_torchrl.envs.reference_policies import REFERENCE_POLICIES
from icco_torchrl.envs.resource_collection import SPAWN_MODES


class ConfigError(ValueError):
    """A config value is missing, unknown, ill-typed or out of range."""


@dataclass
class MethodConfig:
    name: str = "icco"
    coordinator: bool = True
    full_state: bool = False
    ce_coef: float = 1e-3
    entropy_coef: float = 1e-4
    posterior: str = "product"
    encoder: str = "attention"
    state_encoder: str = "relative"
    z_init_logvar: float = 0.0
    hidden: int = 64
    z_dim: int = 32
    period: int = 4


@dataclass
class EnvConfig:
    name: str = "resource_collection"
    num_envs: int = 32
    params: dict = field(default_factory=dict)


@dataclass
class TrainConfig:
    total_frames: int = 1_200_000
    steps_per_batch: int = 16
    buffer_segments: int = 20_000
    batch_segments: int = 128
    updates_per_batch: int = 2
    warmup_segments: int = 512
    lr: float = 3e-4
    optimizer: str = "rmsprop"
    grad_clip: float = 10.0
    gamma: float = 0.99
    td_lambda: float = 0.0
    double_q: bool = True
    target_update: str = "hard"
    target_update_interval: int = 200
    tau: float = 0.005
    eps_init: float = 1.0
    eps_end: float = 0.05
    eps_decay_frames: int = 800_000
    eval_interval: int = 100_000
    eval_envs: int = 16
    checkpoint_interval: int = 200_000
    checkpoint_buffer: bool = True
    threads: int = 1


@dataclass
class WandbConfig:
    mode: str = "disabled"
    project: str = "icco-torchrl"
    entity: Optional[str] = None
    group: Optional[str] = None


@dataclass
class LoggerConfig:
    progress: bool = True
    log_interval: int = 1
    wandb: WandbConfig = field(default_factory=WandbConfig)


@dataclass
class EvalConfig:
    protocol: str = "random_walk"
    trials: int = 20
    episodes: int = 1
    gif: bool = False
    out_dir: Optional[str] = None
    checkpoints: list[str] = field(default_factory=list)
    steps: int = 145
    replan_every: Optional[int] = None
    references: list[str] = field(default_factory=lambda: ["random", "follower", "heuristic", "blend"])
    blend_radius: float = 1.75


@dataclass
class LiveConfig:
    host: str = "127.0.0.1"
    port: int = 8765
    web_port: int = 8000
    web: bool = False
    rate_hz: float = 10.0
    timeout_s: float = 0.5
    fleet: bool = False
    seconds: Optional[float] = None
    max_speed: float = 0.5
    max_turn: float = 2.0
    max_accel: float = 1.0
    max_turn_accel: float = 4.0
    robot_radius: float = 0.15


@dataclass
class Config:
    seed: int = 0
    device: str = "auto"
    resume: Optional[str] = None
    checkpoint: Optional[str] = None
    method: MethodConfig = field(default_factory=MethodConfig)
    env: EnvConfig = field(default_factory=EnvConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    live: LiveConfig = field(default_factory=LiveConfig)
    llm: Any = None


_CHOICES = {
    "method.posterior": ("product", "sum"), "method.encoder": ("attention", "mlp"),
    "method.state_encoder": ("relative", "flat"),
    "train.optimizer": ("rmsprop", "adam"), "train.target_update": ("hard", "soft"),
    "logger.wandb.mode": ("disabled", "offline", "online"),
}
_POSITIVE = ("env.num_envs", "train.total_frames", "train.steps_per_batch", "train.buffer_segments",
             "train.batch_segments", "train.target_update_interval", "train.eval_envs", "train.threads",
             "method.hidden", "method.period", "eval.trials", "eval.episodes", "logger.log_interval",
             "live.rate_hz", "live.timeout_s", "live.max_speed", "live.max_turn", "live.max_accel",
             "live.max_turn_accel", "live.robot_radius")
_NON_NEGATIVE = ("train.updates_per_batch", "train.warmup_segments", "train.eval_interval", "train.checkpoint_interval",
                 "train.eps_decay_frames", "method.ce_coef", "method.entropy_coef", "method.z_dim", "train.grad_clip")


def validate(cfg: DictConfig | dict) -> DictConfig:
    """Merge ``cfg`` into the schema and check ranges; raises ``ConfigError`` naming the field."""
    schema = OmegaConf.structured(Config)
    try:
        merged = OmegaConf.merge(schema, cfg)
    except OmegaConfBaseException as err:
        key = getattr(err, "full_key", None) or "?"
        raise ConfigError(f"config field '{key}': {err.msg if hasattr(err, 'msg') else err}") from None
    for key, allowed in _CHOICES.items():
        if OmegaConf.select(merged, key) not in allowed:
            raise ConfigError(f"config field '{key}' must be one of {allowed}, got {OmegaConf.select(merged, key)!r}")
    for key in _POSITIVE:
        if not OmegaConf.select(merged, key) > 0:
            raise ConfigError(f"config field '{key}' must be > 0, got {OmegaConf.select(merged, key)}")
    for key in _NON_NEGATIVE:
        if OmegaConf.select(merged, key) < 0:
            raise ConfigError(f"config field '{key}' must be >= 0, got {OmegaConf.select(merged, key)}")
    m, t = merged.method, merged.train
    if m.coordinator and m.z_dim < 1:
        raise ConfigError("config field 'method.z_dim' must be >= 1 when method.coordinator is true")
    if not -10 <= m.z_init_logvar <= 0:
        raise ConfigError(f"config field 'method.z_init_logvar' must be in [-10, 0] (the clamp), got {m.z_init_logvar}")
    if m.coordinator and m.full_state:
        raise ConfigError("config fields 'method.coordinator' and 'method.full_state' are exclusive")
    if t.batch_segments > t.buffer_segments:
        raise ConfigError(f"config field 'train.batch_segments' ({t.batch_segments}) exceeds "
                          f"'train.buffer_segments' ({t.buffer_segments})")
    if not 0 <= t.eps_end <= t.eps_init <= 1:
        raise ConfigError("config fields 'train.eps_init'/'train.eps_end' need 0 <= eps_end <= eps_init <= 1")
    if not 0 <= t.td_lambda <= 1:
        raise ConfigError(f"config field 'train.td_lambda' must be in [0, 1], got {t.td_lambda}")
    if not 0 <= t.gamma <= 1:
        raise ConfigError(f"config field 'train.gamma' must be in [0, 1], got {t.gamma}")
    if t.updates_per_batch < 1:
        raise ConfigError(f"config field 'train.updates_per_batch' must be >= 1, got {t.updates_per_batch}")
    if not t.lr > 0:
        raise ConfigError(f"config field 'train.lr' must be > 0, got {t.lr}")
    if not 0 < t.tau <= 1:
        raise ConfigError(f"config field 'train.tau' must be in (0, 1], got {t.tau}")
    if t.warmup_segments > t.buffer_segments:
        raise ConfigError(f"config field 'train.warmup_segments' ({t.warmup_segments}) exceeds "
                          f"'train.buffer_segments' ({t.buffer_segments}): training would never start")
    for key in ("port", "web_port"):
        if not 0 <= merged.live[key] <= 65535:
            raise ConfigError(f"config field 'live.{key}' must be in [0, 65535], got {merged.live[key]}")
    unknown = [name for name in merged.eval.references if name not in REFERENCE_POLICIES]
    if unknown:
        raise ConfigError(f"config field 'eval.references' has unknown policies {unknown}; "
                          f"choose from {list(REFERENCE_POLICIES)}")
    if not merged.eval.blend_radius >= 0:
        raise ConfigError(f"config field 'eval.blend_radius' must be >= 0, got {merged.eval.blend_radius}")
    spawn = merged.env.params.get("spawn", "uniform")
    if spawn not in SPAWN_MODES:
        raise ConfigError(f"config field 'env.params.spawn' must be one of {SPAWN_MODES}, got {spawn!r}")
    _check_env_params(merged.env.params)
    _check_llm(merged.llm)
    resolve_device(merged.device)
    return merged


def _check_env_params(params) -> None:
    """``env.params`` are the env's keyword arguments: unknown names and bad values are named here,
    before any work (the env's own checks, run on a one-env instance)."""
    from icco_torchrl.envs import ResourceCollectionEnv

    params = OmegaConf.to_container(params, resolve=True) if not isinstance(params, dict) else params
    accepted = set(inspect.signature(ResourceCollectionEnv.__init__).parameters) - {"self", "num_envs", "device", "seed"}
    for key in params:
        if key not in accepted:
            raise ConfigError(f"config field 'env.params.{key}' is not a parameter of ResourceCollectionEnv "
                              f"(known: {', '.join(sorted(accepted))})")
    try:
        ResourceCollectionEnv(num_envs=1, **params)
    except (ValueError, TypeError) as err:
        name = next((k for k in params if str(err).startswith(k)), None)
        raise ConfigError(f"config field 'env.params{'.' + name if name else ''}': {err}") from None


_LLM_NUMBERS = {"timeout_s": float, "deadline_s": float, "temperature": float, "backoff_s": float,
                "max_retries": int, "n_waypoints": int}


def _check_llm(llm) -> None:
    """The ``llm`` group is free-form (any litellm backend); its numeric fields are checked here."""
    if llm is None:
        return
    for key, kind in _LLM_NUMBERS.items():
        value = llm.get(key, None) if hasattr(llm, "get") else None
        if value is None:
            continue
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        if kind is int:
            ok = ok and float(value).is_integer()
        if not ok or value < 0:
            raise ConfigError(f"config field 'llm.{key}' must be a non-negative {'integer' if kind is int else 'number'}"
                              f", got {value!r}")


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when present; an unavailable device fails fast naming the field."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise ConfigError(f"config field 'device': {err}") from None
    if device.type == "cuda" and (not torch.cuda.is_available() or (device.index or 0) >= torch.cuda.device_count()):
        raise ConfigError(f"config field 'device' is {name!r} but no such CUDA device is available")
    if device.type not in ("cpu", "cuda"):
        raise ConfigError(f"config field 'device' must be auto, cpu or cuda[:i], got {name!r}")
    return device
