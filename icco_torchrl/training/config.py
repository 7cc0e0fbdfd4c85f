"""Typed configs: every group is a structured config, registered once in Hydra's ConfigStore.

The dataclasses below are the schema *and* the defaults (each field commented); ``conf/`` holds
only presets, YAML files that override some of these defaults (``method/qmix.yaml``,
``experiment/smoke.yaml``, ``reward/paper.yaml``, ``llm/openai.yaml``...). Hydra composes the
presets onto the registered schema, so a typo (``train.totl_frames``) or a wrong type
(``train.total_frames=lots``) fails while composing; :func:`validate` then checks choices, ranges
and the rules between fields (warm-up within the buffer, batch within the buffer, ...) and the
env's own parameter checks. Every failure is a :class:`ConfigError` naming the field, before any
work starts; :func:`check_command_line` gives the ``icco`` command the same one line for errors
Hydra would report while composing.

The env parameters (``env.params``) are generated from the env's one table of parameters,
:class:`~icco_torchrl.envs.params.ResourceCollectionParams`: their names, types, defaults, docs
and checks are the env's own.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from typing import Optional

import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from icco_torchrl.envs.params import SPAWN_MODES, ResourceCollectionParams
from icco_torchrl.envs.reference_policies import (
    EVAL_REFERENCES,
    REFERENCE_POLICIES,
    parse_reference,
)
from icco_torchrl.envs.resource_collection import check_team_sizes
from icco_torchrl.envs.shaping import POTENTIALS, missing_for
from icco_torchrl.envs.waypoints import PLAN_INTERFACES
from icco_torchrl.modules.mixer import MIXERS
from icco_torchrl.modules.posterior import COMBINES, POSTERIOR_INPUTS
from icco_torchrl.modules.relative import STATE_ENCODERS
from icco_torchrl.objectives.defaults import LOSS_DEFAULTS
from icco_torchrl.paths import CONF_DIR


class ConfigError(ValueError):
    """A config value is missing, unknown, ill-typed or out of range."""


def _field(
    default,
    *,
    choices: tuple | None = None,
    gt: float | None = None,
    ge: float | None = None,
    le: float | None = None,
):
    """A dataclass field with its allowed values (checked by :func:`validate`)."""
    meta = {k: v for k, v in dict(choices=choices, gt=gt, ge=ge, le=le).items() if v is not None}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass
class MethodConfig:
    """``method``: which learner. The methods are the presets in ``conf/method/`` (ICCO is these
    defaults); their names and labels come from :mod:`icco_torchrl.methods`."""

    # The method's name: its preset file, run folders, results.json keys.
    name: str = "icco"
    # What tables and figures print (each preset sets its own; empty: the name).
    label: str = ""
    # A coordinator g_phi(s, v) broadcasts z per robot.
    coordinator: bool = True
    # Agents also read the global state (QMIX (FULL)).
    full_state: bool = False
    # Weight of -log q_xi(z | future behaviour). COPA: 1e-3; the paper: 1. 1e-3 with entropy 1e-3
    # and COPA's clamps has the highest reward of ICCO's weights in experiments/consistency (the
    # default was 1e-4, unclamped, before it). The loss's own default (objectives/defaults.py).
    ce_coef: float = _field(LOSS_DEFAULTS.ce_coef, ge=0)
    # Weight of -H(z | s, v) (COPA: 1e-4; chosen with ce_coef).
    entropy_coef: float = _field(LOSS_DEFAULTS.entropy_coef, ge=0)
    # The posterior's factors: product of Gaussians | sum of log-likelihoods (COPA).
    posterior: str = _field("product", choices=COMBINES)
    # What the posterior reads: the flat state, joint action and observation (one team size) |
    # robot and entity tokens (any team up to env.params.n_agents; modules/posterior.py).
    posterior_input: str = _field("flat", choices=POSTERIOR_INPUTS)
    # The mixer: TorchRL's QMixer on the flat state (one team size) | a masked QMIX whose
    # per-robot weights come from the state tokens (any team; modules/mixer.py).
    mixer: str = _field("qmix", choices=MIXERS)
    # Local observation encoder: entity tokens | flat MLP.
    encoder: str = _field("attention", choices=("attention", "mlp"))
    # Global-state encoder (coordinator, QMIX (FULL)): entities seen from each robot | absolute.
    state_encoder: str = _field("relative", choices=STATE_ENCODERS)
    # Initial log-variance bias of z, in COPA's clamp [-10, 0] (0 measured slower).
    z_init_logvar: float = _field(-5.0, ge=-10, le=0)
    # Width of encoders, GRU and heads.
    hidden: int = _field(64, gt=0)
    # TACI size per robot (COPA: 128); 0 without a coordinator.
    z_dim: int = _field(32, ge=0)
    # z is redrawn every `period` steps and held in between (T).
    period: int = _field(4, gt=0)
    # Adaptive broadcast (COPA's beta): every T steps robot i receives the new z only if it moved
    # more than this (L2) from the z it holds; 0 sends every T steps.
    broadcast_threshold: float = _field(0.0, ge=0)
    # Agents also read the nearest own waypoint and the path direction r_inst scores
    # (modules/waypoint_features.py).
    waypoint_features: bool = True
    # LayerNorm in the agent's trunk (the GRU's input) and Q head (modules/agent.py). On by
    # default: the best-team screen (experiments/best_team) measured ICCO at 88 % of the best
    # scripted team at 2M frames with it, 78 % without (2 seeds each); false is the paper's agent.
    layer_norm: bool = True


# A checkpoint holds every method field there was when it was written, and one that lacks a field
# of today's is refused (training/checkpoint.py: load_checkpoint); the fields added or removed
# since, with the values older files trained with, live in the one script that converts such
# files: tools/convert_checkpoint.py (outside the package). Adding a field needs no new format.


def _env_params_schema(name: str = "EnvParams", unset: bool = False) -> type:
    """The env's parameter table (:class:`ResourceCollectionParams`: names, types, defaults) as a
    Hydra schema: ``env.params``; with ``unset`` every field is optional and None
    (``train.env_params``: None = as env.params)."""
    fields = [
        (f.name, Optional[f.type], dataclasses.field(default=None))
        if unset
        else (f.name, f.type, dataclasses.field(default=f.default))
        for f in dataclasses.fields(ResourceCollectionParams)
    ]
    schema = dataclasses.make_dataclass(name, fields)
    schema.__module__ = __name__  # pickled configs (submitit, Ray) refer to it here
    return schema


EnvParams = _env_params_schema()
EnvParams.__doc__ = (
    "``env.params``: ResourceCollectionEnv's parameters (each documented in its table, "
    "icco_torchrl.envs.params.ResourceCollectionParams)."
)
TrainEnvParams = _env_params_schema("TrainEnvParams", unset=True)
TrainEnvParams.__doc__ = (
    "``train.env_params``: env.params overrides for the training env only (None: as env.params)."
)


def set_env_params(params) -> dict:
    """The fields of a ``train.env_params`` node that are set (not None), as a plain dict."""
    params = (
        OmegaConf.to_container(params, resolve=True) if not isinstance(params, dict) else params
    )
    return {k: v for k, v in params.items() if v is not None}


@dataclass
class EnvConfig:
    """``env``: the task (``conf/env/resource_collection.yaml``); reward weights come from the
    ``reward`` presets."""

    # The task.
    name: str = "resource_collection"
    # Envs stepped together by the collector.
    num_envs: int = _field(32, gt=0)
    # ResourceCollectionEnv's keyword arguments (its defaults).
    params: EnvParams = field(default_factory=EnvParams)


@dataclass
class ShapingConfig:
    """``train.shaping``: potential-based reward shaping of the training env only,
    ``F = gamma * Phi(s') - Phi(s)`` (Ng et al. 1999), so it cannot change which policies are
    optimal. ``Phi`` is ``weight`` times the sum of the named potentials
    (:mod:`icco_torchrl.envs.shaping`)."""

    # Potentials to sum: collect (a robot's distance left in its delivery cycle) | defend (a free
    # robot's distance to the nearest active invader). []: no shaping. collect at 0.3 is screened
    # in experiments/sequence_replay (more team and task reward; picks unchanged).
    potentials: list[str] = _field(["collect"])
    # Scale of Phi, in reward units per metre.
    weight: float = _field(0.3, ge=0)


@dataclass
class TrainConfig:
    """``train``: budget and optimisation (presets ``conf/experiment/``: default (these), smoke,
    paper, repro_cpu, inst_only). Each lever was measured (``experiments/recipe/README.md``)."""

    # Env steps (one step of one env) to collect.
    total_frames: int = _field(1_000_000, gt=0)
    # Collector steps per env per batch (frames_per_batch = num_envs * this).
    steps_per_batch: int = _field(16, gt=0)
    # Length L of a replayed sequence, a multiple of method.period (L = period: one broadcast).
    sequence_length: int = _field(16, gt=0)
    # Leading steps of each sequence that only warm up the GRU from its stored state (no loss).
    burn_in: int = _field(LOSS_DEFAULTS.burn_in, ge=0)
    # Replay capacity in sequences of `sequence_length` steps (80k transitions).
    buffer_segments: int = _field(5_000, gt=0)
    # Sequences per gradient update: 512 transitions (COPA: 512 sequences of 4 steps).
    batch_segments: int = _field(32, gt=0)
    # Gradient updates per collector batch (~8 replayed transitions per new one).
    updates_per_batch: int = _field(8, ge=1)
    # The replay ratio this recipe states, checked: replayed transitions per collected one,
    # updates_per_batch x batch_segments x sequence_length / (env.num_envs x steps_per_batch).
    # A value that no whole number of updates gives, or that updates_per_batch does not give, is
    # refused naming the field. null: not checked.
    replay_ratio: Optional[float] = _field(None, gt=0)
    # No updates until the buffer holds this many sequences.
    warmup_segments: int = _field(128, ge=0)
    # Learning rate (COPA: RMSprop 3e-4; Adam 1e-3 learns the task ~2x faster here).
    lr: float = _field(1e-3, gt=0)
    # adam | rmsprop (alpha 0.99, eps 1e-5, COPA).
    optimizer: str = _field("adam", choices=("adam", "rmsprop"))
    # Global grad-norm clip (0 disables).
    grad_clip: float = _field(10.0, ge=0)
    # Discount. This and the loss's other settings below default to the loss's own defaults
    # (objectives/defaults.py): ICCOLoss() with no keyword arguments is what this trains.
    gamma: float = _field(LOSS_DEFAULTS.gamma, ge=0, le=1)
    # Lambda of the lambda-return over each replayed sequence (0: one-step targets; pymarl2: 0.6).
    td_lambda: float = _field(LOSS_DEFAULTS.td_lambda, ge=0, le=1)
    # Bootstrap with the online argmax (pymarl) instead of the target's.
    double_q: bool = LOSS_DEFAULTS.double_q
    # COPA's clamps of the consistency term (method.ce_coef, method.entropy_coef): each
    # dimension's log q_xi to [-1000, 0] and each dimension's entropy of z to [0, 10] before the
    # sums, so a sharper posterior or a narrower z than that earns nothing (the entropy term is off
    # below logvar -2.84). A training setting like td_lambda (no network changes, so checkpoints
    # written before it load unchanged, at false). Screened in experiments/consistency.
    ce_clamp: bool = LOSS_DEFAULTS.ce_clamp
    # hard (copy every interval updates, COPA) | soft (Polyak, tau).
    target_update: str = _field("hard", choices=("hard", "soft"))
    # Updates between hard copies (COPA: 200).
    target_update_interval: int = _field(50, gt=0)
    # Polyak rate of soft updates.
    tau: float = _field(0.005, gt=0, le=1)
    # Epsilon-greedy start.
    eps_init: float = _field(1.0, ge=0, le=1)
    # Epsilon-greedy floor.
    eps_end: float = _field(0.05, ge=0, le=1)
    # Exponential decay from eps_init to eps_end over these frames.
    eps_decay_frames: int = _field(300_000, ge=0)
    # Frames between greedy evaluations (0: only at the end).
    eval_interval: int = _field(100_000, ge=0)
    # Evaluation episodes (parallel envs), the same ones every time.
    eval_envs: int = _field(16, gt=0)
    # Also keep the policy weights of every evaluation, policies/<frames>.pt in the run folder
    # (~0.6 MB each): a learning curve any protocol can score later (benchmarks/time_to_skill.py).
    policy_snapshots: bool = False
    # Frames between checkpoints (0: only at the end).
    checkpoint_interval: int = _field(100_000, ge=0)
    # Also save the replay buffer (replay/, ~22 KB per 4 steps) so resume keeps it.
    checkpoint_buffer: bool = True
    # torch CPU threads (1 is the stable choice on shared machines).
    threads: int = _field(1, gt=0)
    # Where the env steps and the policy acts: inline (in the learner's process, collect then
    # learn, in turn) | process (a second process collects beside the learner, so a run uses two
    # cores; training/collector_process.py). The learner paces it: the same updates_per_batch per
    # collected batch, the collector at most one batch ahead, acting with weights one batch of
    # updates older than inline's (epsilon follows the same schedule). Needs 2 cores and the CPU.
    collector: str = _field("inline", choices=("inline", "process"))
    # Compile the update (torch.compile of the loss, fused Adam; icco_torchrl/training/update.py):
    # the same loss and gradients in far fewer ops (benchmarks/README.md). The first run compiles
    # for minutes on a CPU, later ones load the cache (~/.cache/icco_torchrl/inductor).
    compile: bool = False
    # torch.compile mode (null: its default; e.g. max-autotune-no-cudagraphs).
    compile_mode: Optional[str] = None
    # Capture the whole update in one CUDA graph (tensordict's CudaGraphModule); CUDA only.
    cudagraphs: bool = False
    # Exploratory actions from this reference policy instead of uniform draws (experiments/recipe).
    explore_guide: Optional[str] = _field(None, choices=(None, *REFERENCE_POLICIES))
    # env.params overrides for the training env only (e.g. train.env_params.collect_reward=3.5):
    # the evaluations during training, `icco eval` and every restore use env.params, so they never
    # change what is scored. May change at resume (a curriculum); replayed data keeps old rewards.
    env_params: TrainEnvParams = field(default_factory=TrainEnvParams)
    # Team sizes of the training env, one drawn per env at each reset (e.g. [2,3,4]; each at most
    # its n_agents, robots 0..k-1 present). null: every env holds all n_agents robots, as before.
    team_sizes: Optional[list[int]] = None
    # Potential-based shaping of the training env only (never in an evaluation).
    shaping: ShapingConfig = field(default_factory=ShapingConfig)


@dataclass
class WandbConfig:
    """``logger.wandb``: optional; never needs a network or an account for ``offline``."""

    # disabled | offline (./wandb, syncable) | online
    mode: str = _field("disabled", choices=("disabled", "offline", "online"))
    # wandb project name.
    project: str = "icco-torchrl"
    # wandb entity (team/user); null: the default.
    entity: Optional[str] = None
    # wandb group (e.g. a sweep name); null: the method name.
    group: Optional[str] = None


@dataclass
class LoggerConfig:
    """``logger``: CSV files always, the progress bar and wandb on request."""

    # tqdm progress bar with SPS, team reward and event counts.
    progress: bool = True
    # A train.csv row every this many collector batches.
    log_interval: int = _field(1, gt=0)
    wandb: WandbConfig = field(default_factory=WandbConfig)


@dataclass
class CoordinationConfig:
    """``eval.coordination``: what ``icco eval`` measures of a team with a coordinator beside its
    rewards (icco_torchrl/evaluation/consistency.py; docs/consistency.md): the mutual-information
    lower bound of the consistency term, with a posterior fitted after training, and swap
    consistency. About 5 s a checkpoint on a quiet core at these defaults; none for QMIX."""

    # Measure them (false: skip; the columns then read n/a).
    enabled: bool = True
    # Rollouts of one episode each on the training distribution (random-walk instructions): z
    # sampled from the coordinator's Gaussian, actions greedy.
    episodes: int = _field(32, gt=1)
    # Share of those episodes held out from the posterior's fit; the bound is scored on them.
    heldout: float = _field(0.25, gt=0, le=0.9)
    # Adam steps of the fresh posterior (minibatches of 128 broadcast windows, lr 1e-3).
    fit_steps: int = _field(300, ge=0)


@dataclass
class EvalConfig:
    """``eval``: ``icco eval`` and ``icco instruct`` (protocols, trials, outputs, references)."""

    # Training distribution | paper Fig. 4/5a.
    protocol: str = _field("random_walk", choices=("random_walk", "quadrants"))
    # Evaluation episodes run in parallel (one env each).
    trials: int = _field(20, gt=0)
    # Repeats of the batch of trials.
    episodes: int = _field(1, gt=0)
    # Write a GIF of trial 0.
    gif: bool = False
    # Where results go; null: next to the checkpoint(s).
    out_dir: Optional[str] = None
    # More checkpoints (paths or globs) to compare; one row per method.
    checkpoints: list[str] = _field([])
    # Steps per segment (each quadrant, each `;`-separated instruction).
    steps: int = _field(145, gt=0)
    # `icco instruct`: how each robot's plan reaches it: served (a training-like walk from where
    # it is along its route, at every waypoint refresh; icco_torchrl/instructions/serving.py) or
    # fixed (the planner's waypoints written once: a comparison only). The planner is asked once
    # per instruction and episode either way.
    plan: str = _field("served", choices=PLAN_INTERFACES)
    # Scripted reference rows beside the checkpoints ([]: none).
    references: list[str] = _field(list(EVAL_REFERENCES))
    # Radius (m) of the blend reference: task within r, follow otherwise.
    blend_radius: float = _field(1.75, ge=0)
    # Robots in the evaluation env (references too); null: the checkpoints' n_agents. Another size
    # needs acting networks that read any team (the default encoders; docs/method.md).
    team_size: Optional[int] = _field(None, ge=1)
    # The coordinator's broadcast threshold (beta) for this evaluation; null: each checkpoint's.
    broadcast_threshold: Optional[float] = _field(None, ge=0)
    # `icco eval`: the coordination measures of teams with a coordinator.
    coordination: CoordinationConfig = field(default_factory=CoordinationConfig)


@dataclass
class LLMConfig:
    """``llm``: the language backend of ``icco instruct`` (presets ``conf/llm/``: offline (these),
    openai, ollama).

    Consumed by :meth:`icco_torchrl.instructions.LLMPlanner.from_config`. API keys come only from
    environment variables, never from a config.
    """

    # offline | openai | ollama | any litellm model string.
    backend: str = "offline"
    # litellm model string; null: the backend's default model.
    model: Optional[str] = "offline/rule-planner"
    # Provider URL; null: the provider's default.
    api_base: Optional[str] = None
    # Sampling temperature sent with the request.
    temperature: float = _field(0.0, ge=0)
    # Seconds per request before it counts as a failed attempt.
    timeout_s: float = _field(10.0, ge=0)
    # Seconds for a whole plan (every attempt and pause).
    deadline_s: float = _field(30.0, ge=0)
    # false: no reply at all stops the run in one line; true: plan with fallbacks.
    fallback_on_error: bool = False
    # Extra attempts after a bad reply or a provider error.
    max_retries: int = _field(2, ge=0)
    # Pause after a provider error, doubled per attempt.
    backoff_s: float = _field(0.5, ge=0)
    # Cached replies (one JSON file per request); null disables.
    cache_dir: Optional[str] = None
    # The paper's prompt | task-aligned (QMIX-TAP).
    prompt: str = _field("plain", choices=("plain", "tap"))
    # K waypoints per agent; must equal env.params.n_waypoints.
    n_waypoints: int = _field(4, gt=0)


@dataclass
class LiveConfig:
    """``live``: ``icco live`` (a team on a web page) and ``icco bridge`` (robots over
    JSON-over-UDP); see ``icco_torchrl/live/``."""

    # Address the page and the bridge listen on (anything but loopback lets other machines steer).
    host: str = "127.0.0.1"
    # A secret every channel that steers must carry: the page's requests (open
    # http://HOST:PORT/?token=...) and the bridge's UDP states and instructions ("token" field;
    # docs/live.md). Set one for any host but loopback. null: none (the page still answers only
    # its own origin).
    token: Optional[str] = None
    # UDP port of the bridge (0 = any free port).
    port: int = _field(8765, ge=0, le=65535)
    # HTTP/WebSocket port of the live page (0 = any free port).
    web_port: int = _field(8000, ge=0, le=65535)
    # `icco bridge`: also serve the live page (watch the fleet, type instructions).
    web: bool = False
    # Ticks per second (10 = real time at dt 0.1 s); the page's speed control scales it.
    rate_hz: float = _field(10.0, gt=0)
    # A robot without a pose for this long (s) is sent a stop command and leaves the team (the
    # bridge); it joins again when it reports again.
    timeout_s: float = _field(0.5, gt=0)
    # The most robots the team may hold (the page's "Add robot", robots joining the bridge);
    # null: the checkpoint's team. The agents and the coordinator read any team.
    max_robots: Optional[int] = _field(None, ge=1, le=32)
    # Also run the simulated fleet (unicycles with noise and latency) in this process.
    fleet: bool = False
    # The yardstick beside the page's running mean: the best scripted team plays this many
    # episodes of the checkpoint's training env (its length, its own instructions) at start, a
    # second or two; 0: none.
    reference_episodes: int = _field(16, ge=0, le=256)
    # Stop after this many seconds (the page then shows "run ended"); null: until Ctrl-C / SIGTERM.
    seconds: Optional[float] = _field(None, gt=0)
    # Robot limits for the DWA controller (a small indoor robot, TurtleBot-like; also the
    # defaults of icco_torchrl/live/dwa.py's RobotLimits): forward speed, m/s.
    max_speed: float = _field(0.5, gt=0)
    # Turn rate, rad/s.
    max_turn: float = _field(2.0, gt=0)
    # Forward acceleration, m/s^2.
    max_accel: float = _field(1.0, gt=0)
    # Turn acceleration, rad/s^2.
    max_turn_accel: float = _field(4.0, gt=0)
    # Robot radius, m (the env's robot radius): robots keep twice this apart.
    robot_radius: float = _field(0.15, gt=0)


@dataclass
class Config:
    """The root: ``icco train|eval|instruct|live|bridge`` compose ``conf/config.yaml``'s presets
    onto it."""

    # Seeds torch, the env generators and the replay sampler.
    seed: int = 0
    # auto (cuda if present) | cpu | cuda | cuda:1 ...
    device: str = "auto"
    # A checkpoint (.pt) to continue training from.
    resume: Optional[str] = None
    # A checkpoint to evaluate (`icco eval`, `icco instruct`, `icco live`).
    checkpoint: Optional[str] = None
    method: MethodConfig = field(default_factory=MethodConfig)
    env: EnvConfig = field(default_factory=EnvConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    live: LiveConfig = field(default_factory=LiveConfig)
    llm: LLMConfig = field(default_factory=LLMConfig)


# Schema name -> dataclass in Hydra's ConfigStore; conf/config.yaml starts from "base_config" and
# each group's presets from "base_<group>" (for a group, the preset's fields are merged over it).
SCHEMAS = {
    "base_config": (None, Config),
    "base_method": ("method", MethodConfig),
    "base_env": ("env", EnvConfig),
    "base_llm": ("llm", LLMConfig),
}


def register_configs() -> None:
    """Register the schema in Hydra's ConfigStore (idempotent: one entry per name)."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for name, (group, node) in SCHEMAS.items():
        store.store(name=name, group=group, node=node)


register_configs()


def _field_error(err: OmegaConfBaseException) -> ConfigError:
    key = getattr(err, "full_key", None) or "?"
    message = str(err.msg if hasattr(err, "msg") else err).strip().splitlines()
    return ConfigError(f"config field '{key}': {message[0] if message else type(err).__name__}")


def _check_fields(node, schema, prefix: str = "") -> None:
    """Choices and ranges declared on the dataclass fields (``_field``), recursively."""
    for f in dataclasses.fields(schema):
        value, key = node[f.name], f"{prefix}{f.name}"
        if f.default_factory is not dataclasses.MISSING and dataclasses.is_dataclass(
            f.default_factory
        ):
            _check_fields(value, f.default_factory, f"{key}.")
            continue
        meta = f.metadata
        if "choices" in meta and value not in meta["choices"]:
            raise ConfigError(
                f"config field '{key}' must be one of {meta['choices']}, got {value!r}"
            )
        if value is None or isinstance(value, (str, bool)):
            continue
        for rule, ok, word in (
            ("gt", lambda v, b: v > b, ">"),
            ("ge", lambda v, b: v >= b, ">="),
            ("le", lambda v, b: v <= b, "<="),
        ):
            if rule in meta and not ok(value, meta[rule]):
                raise ConfigError(f"config field '{key}' must be {word} {meta[rule]}, got {value}")


def _check_shaping(shaping, params) -> None:
    """Known potentials, each computable from the env's state (what it needs is there)."""
    for name in shaping.potentials:
        if name not in POTENTIALS:
            raise ConfigError(
                f"config field 'train.shaping.potentials' has unknown potential {name!r}; "
                f"choose from {list(POTENTIALS)}"
            )
        lack = missing_for(name, n_resources=params.n_resources, n_invaders=params.n_invaders)
        if lack:
            raise ConfigError(
                f"config field 'train.shaping.potentials': {name!r} needs {lack} in the env's "
                f"state (env.params)"
            )


# ``eval`` fields that left the schema. A saved config (a checkpoint's, a run's) may still hold
# them; they chose how a command evaluated, never what a run trained, so they are dropped.
EVAL_FIELDS_REMOVED = ("replan_every",)  # served plans replaced re-prompting (eval.plan)


def _without_removed(cfg: DictConfig | dict) -> DictConfig | dict:
    evaluation = cfg.get("eval") if hasattr(cfg, "get") else None
    if not hasattr(evaluation, "keys") or not set(EVAL_FIELDS_REMOVED) & set(evaluation.keys()):
        return cfg
    plain = OmegaConf.to_container(cfg) if isinstance(cfg, DictConfig) else dict(cfg)
    plain["eval"] = {k: v for k, v in plain["eval"].items() if k not in EVAL_FIELDS_REMOVED}
    return plain


def validate(cfg: DictConfig | dict) -> DictConfig:
    """Merge ``cfg`` into the schema and check every field and the rules between fields; raises
    ``ConfigError`` naming the field. A config Hydra composed is already typed; a saved one (a
    checkpoint's) gets the current defaults for fields it lacks, and loses the evaluation fields
    that left the schema (:data:`EVAL_FIELDS_REMOVED`)."""
    cfg = _without_removed(cfg)
    try:
        merged = OmegaConf.merge(OmegaConf.structured(Config), cfg)
    except OmegaConfBaseException as err:
        raise _field_error(err) from None
    _check_fields(merged, Config)
    t = merged.train
    # Rules between fields.
    _check_method(merged.method)
    _check_segments(merged)
    _check_shaping(t.shaping, merged.env.params)
    if not t.eps_end <= t.eps_init:
        raise ConfigError(
            "config fields 'train.eps_init'/'train.eps_end' need 0 <= eps_end <= eps_init <= 1"
        )
    if merged.llm.n_waypoints != merged.env.params.n_waypoints:
        raise ConfigError(
            f"config field 'llm.n_waypoints' ({merged.llm.n_waypoints}) must equal "
            f"'env.params.n_waypoints' ({merged.env.params.n_waypoints})"
        )
    for name in merged.eval.references:
        try:
            parse_reference(name)
        except ValueError as err:
            raise ConfigError(f"config field 'eval.references': {err}") from None
    _check_replay_ratio(merged)
    _check_training_env(merged)
    device = resolve_device(merged.device)
    if t.cudagraphs and device.type != "cuda":
        raise ConfigError(
            f"config field 'train.cudagraphs' captures CUDA graphs: it needs a CUDA device, and "
            f"device is {merged.device!r} ({device.type})"
        )
    return merged


def _check_method(m) -> None:
    """The rules between the ``method`` fields."""
    if m.coordinator and m.z_dim < 1:
        raise ConfigError(
            "config field 'method.z_dim' must be >= 1 when method.coordinator is true"
        )
    if m.coordinator and m.full_state:
        raise ConfigError(
            "config fields 'method.coordinator' and 'method.full_state' are exclusive"
        )


def _check_segments(cfg) -> None:
    """The replayed segments fit the buffer and the broadcast period, with steps after burn-in."""
    m, t = cfg.method, cfg.train
    if t.batch_segments > t.buffer_segments:
        raise ConfigError(
            f"config field 'train.batch_segments' ({t.batch_segments}) exceeds "
            f"'train.buffer_segments' ({t.buffer_segments})"
        )
    if t.warmup_segments > t.buffer_segments:
        raise ConfigError(
            f"config field 'train.warmup_segments' ({t.warmup_segments}) exceeds "
            f"'train.buffer_segments' ({t.buffer_segments}): training would never start"
        )
    if t.sequence_length % m.period:
        raise ConfigError(
            f"config field 'train.sequence_length' ({t.sequence_length}) must be a multiple of "
            f"'method.period' ({m.period})"
        )
    if t.burn_in >= t.sequence_length:
        raise ConfigError(
            f"config field 'train.burn_in' ({t.burn_in}) must be less than "
            f"'train.sequence_length' ({t.sequence_length})"
        )


def _check_training_env(cfg) -> None:
    """``env.params``, and the training env's own parameters (``train.env_params``,
    ``train.team_sizes``) over them."""
    t = cfg.train
    _check_env_params(cfg.env.params)
    shaping = set_env_params(t.env_params)
    if shaping:
        _check_env_params(
            {**OmegaConf.to_container(cfg.env.params, resolve=True), **shaping},
            "train.env_params",
            only=list(shaping),
        )
    _check_team_sizes(t.team_sizes, shaping.get("n_agents", cfg.env.params.n_agents))


def _check_replay_ratio(cfg) -> None:
    """``train.replay_ratio``, when set: a whole number of updates replays it, and it is
    ``train.updates_per_batch``."""
    t = cfg.train
    if t.replay_ratio is None:
        return
    frames = cfg.env.num_envs * t.steps_per_batch
    update = t.batch_segments * t.sequence_length  # transitions one update replays
    budget = t.replay_ratio * frames  # transitions the ratio replays a batch
    updates = round(budget / update)
    if updates < 1 or abs(budget - updates * update) > 1e-6 * budget:
        raise ConfigError(
            f"config field 'train.replay_ratio' ({t.replay_ratio:g}) replays {budget:g} "
            f"transitions a batch of {frames} (env.num_envs x train.steps_per_batch), not a whole "
            f"number of updates of {update} (train.batch_segments x train.sequence_length)"
        )
    if updates != t.updates_per_batch:
        raise ConfigError(
            f"config field 'train.updates_per_batch' ({t.updates_per_batch}) gives a replay "
            f"ratio of {t.updates_per_batch * update / frames:g}, not train.replay_ratio "
            f"({t.replay_ratio:g}): set it to {updates}"
        )


def check_collector(cfg, cores: int | None = None) -> None:
    """What ``train.collector=process`` needs of this machine, checked before a run starts (not
    in :func:`validate`: a checkpoint trained so still restores anywhere): a core for the learner
    and one for the collector process (``cores``: those this process may use), and the CPU."""
    if cfg.train.collector != "process":
        return
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
        cores = cores or os.cpu_count() or 1
    if cores < 2:
        raise ConfigError(
            f"config field 'train.collector': process needs a core for the learner and one for "
            f"its collector process, and this run may use {cores}: use train.collector=inline"
        )
    device = resolve_device(cfg.device)
    if device.type != "cpu":
        raise ConfigError(
            f"config field 'train.collector': process collects on the CPU, and device is "
            f"{cfg.device!r} ({device.type}): use train.collector=inline"
        )


def _check_team_sizes(team_sizes, n_agents: int) -> None:
    """``train.team_sizes``: the env's own check (None, or a non-empty list of sizes in 1..the
    training n_agents), its error naming the field."""
    try:
        check_team_sizes(None if team_sizes is None else list(team_sizes), n_agents)
    except ValueError as err:
        raise ConfigError(f"config field 'train.team_sizes': {err}") from None


def _check_env_params(params, prefix: str = "env.params", only=None) -> None:
    """Env parameters through the env's own checks (its parameter table), named by field as
    ``prefix.key``; ``only`` limits the names an error may blame (``train.env_params``' own keys,
    checked merged over ``env.params``)."""
    params = (
        OmegaConf.to_container(params, resolve=True) if not isinstance(params, dict) else params
    )
    blame = list(params if only is None else only)
    known = {f.name for f in dataclasses.fields(EnvParams)}
    for key in blame:  # a key added with "+env.params.x=..." gets past the schema's struct flag
        if key not in known:
            raise ConfigError(
                f"config field '{prefix}.{key}' is not a parameter of ResourceCollectionEnv "
                f"(known: {', '.join(sorted(known))})"
            )
    if (
        params.get("spawn", "uniform") not in SPAWN_MODES
    ):  # before the env's checks, which name another field first
        raise ConfigError(
            f"config field '{prefix}.spawn' must be one of {SPAWN_MODES}, got {params['spawn']!r}"
        )
    try:
        ResourceCollectionParams(**params)
    except (ValueError, TypeError) as err:
        name = next((k for k in blame if str(err).startswith(k)), None)
        raise ConfigError(f"config field '{prefix}{'.' + name if name else ''}': {err}") from None


def compose_config(overrides: list[str] | None = None, config_name: str = "config") -> DictConfig:
    """The validated config from ``conf/`` with Hydra-style overrides (for scripts and tests)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose(config_name=config_name, overrides=list(overrides or []))
    return validate(cfg)


def check_command_line(overrides: list[str], config_name: str = "config") -> str | None:
    """The one-line error of the config an ``icco`` command line composes, or None when it is good.

    Hydra reports a bad override while composing (a wrong type, an unknown field) with a message
    of several lines and exit code 1; this composes first, the same way, and says it in one line
    naming the field. Hydra's own arguments are left out; a multirun list (``seed=0,1,2``) is
    checked value by value.
    """
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException

    plain = [
        o
        for o in overrides
        if ("=" in o or o.startswith("~"))
        and not o.startswith(("-", "hydra.", "hydra/", "+hydra", "~hydra"))
    ]
    sweeps = {}
    if any(o in ("-m", "--multirun") for o in overrides):
        for i, item in enumerate(plain):
            value = item.partition("=")[2]
            if "(" in value:  # range(), choice(), glob(): left to Hydra
                sweeps[i] = None
            elif "," in value and not value.startswith(("[", "{", "'", '"')):
                sweeps[i] = value.split(",")

    def pick(values: dict) -> list[str]:
        return [
            item if i not in sweeps else f"{item.partition('=')[0]}={values[i]}"
            for i, item in enumerate(plain)
            if not (i in sweeps and sweeps[i] is None)
        ]

    first = {i: options[0] for i, options in sweeps.items() if options}
    variants = [pick(first)] + [
        pick({**first, i: v}) for i, options in sweeps.items() if options for v in options[1:]
    ]
    for variant in variants:
        try:
            with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
                validate(compose(config_name=config_name, overrides=variant))
        except ConfigError as err:
            return str(err)
        except (HydraException, OmegaConfBaseException) as err:
            return compose_error(err)
    return None


def compose_error(err: BaseException) -> str:
    """One line from Hydra's composition error: the field and what is wrong with it."""
    cause = err
    while cause is not None and not isinstance(cause, OmegaConfBaseException):
        cause = cause.__cause__ or cause.__context__
    if cause is not None and getattr(cause, "full_key", None):
        return str(_field_error(cause))
    return " ".join(str(err).split())


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when present; an unavailable device fails fast naming the field."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise ConfigError(f"config field 'device': {err}") from None
    if device.type == "cuda" and (
        not torch.cuda.is_available() or (device.index or 0) >= torch.cuda.device_count()
    ):
        raise ConfigError(f"config field 'device' is {name!r} but no such CUDA device is available")
    if device.type not in ("cpu", "cuda"):
        raise ConfigError(f"config field 'device' must be auto, cpu or cuda[:i], got {name!r}")
    return device
