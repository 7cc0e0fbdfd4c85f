"""Training, in TorchRL's order: config -> env -> modules -> collector -> buffer -> loss -> loop -> eval.

Every method (ICCO, ICCO w/o CE, QMIX, QMIX (FULL)) runs this one loop; they differ only in
the ``method`` config group.
"""
from __future__ import annotations

import json
import logging
import math
import signal
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer

from icco_torchrl.envs.reference_policies import make_reference_policy, reference_label
from icco_torchrl.training.rollout import EVENT_KEYS, evaluate
from icco_torchrl.modules.policy import exploration_module, make_policy
from icco_torchrl.objectives import make_target_updater, total_loss
from icco_torchrl.training.build import VALIDATION_SEED_OFFSET, action_count, make_env, make_loss, make_modules
from icco_torchrl.training.checkpoint import (CheckpointError, check_compatible, load_checkpoint, load_replay,
                                              load_weights, save_checkpoint, save_replay)
from icco_torchrl.training.config import resolve_device
from icco_torchrl.training.logger import RunLogger
from icco_torchrl.training.segments import SegmentCutter

REPLAY_DIR = "replay"  # the replay buffer dump beside checkpoint.pt (train.checkpoint_buffer)
REFERENCES_FILE = "references.json"  # the reference policies' evaluation, beside eval.csv

# What the loss reads; everything else the collector records is left out of the replay buffer.
REPLAY_KEYS = [("agents", "observation"), "state", ("agents", "action"), ("agents", "prev_action"),
               ("agents", "rnn_hidden"), ("agents", "z"), ("agents", "z_noise"), "step_count", "mask",
               ("next", "agents", "observation"), ("next", "state"), ("next", "reward"), ("next", "done"),
               ("next", "terminated"), ("next", "step_count")]


def epsilon(frames: int, t: DictConfig) -> float:
    """COPA's exponential decay from eps_init to eps_end over ``eps_decay_frames``."""
    if t.eps_decay_frames == 0 or t.eps_init == 0:
        return t.eps_end
    frac = min(frames / t.eps_decay_frames, 1.0)
    return max(t.eps_init * (t.eps_end / t.eps_init) ** frac, t.eps_end) if t.eps_end > 0 else t.eps_init * (1 - frac)


class EpisodeTracker:
    """Running per-env totals of team reward and events; returns the episodes that ended."""

    def __init__(self, num_envs: int, device):
        self.sums = torch.zeros(num_envs, 1 + len(EVENT_KEYS), device=device)

    def update(self, batch) -> torch.Tensor:
        nxt = batch.get("next")
        step_values = torch.stack([nxt.get("reward").squeeze(-1)] + [nxt.get(("events", k)).float() for k in EVENT_KEYS], -1)
        done = nxt.get("done").squeeze(-1)                                       # [B, L]
        finished = []
        for t in range(batch.shape[1]):  # L is small (steps_per_batch); envs are vectorised
            self.sums += step_values[:, t]
            if done[:, t].any():
                finished.append(self.sums[done[:, t]].clone())
                self.sums[done[:, t]] = 0
        return torch.cat(finished) if finished else self.sums.new_zeros(0, self.sums.shape[1])


class GracefulInterrupt:
    """The first Ctrl-C (SIGINT) or SIGTERM (what Slurm, ``timeout``, docker and submitit send
    before a kill) asks the loop to stop after the current batch and save a checkpoint; a second
    one raises at once.

    Stopping between batches, not inside the collector or an update, keeps every object in a
    state that can be checkpointed.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.requested, self.signal_name = False, None
        self._previous = {}
        try:
            for sig in self.SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        except ValueError:  # not the main thread: keep Python's default behaviour
            self._previous = {}

    def _handle(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested, self.signal_name = True, signal.Signals(signum).name

    def restore(self) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        self._previous = {}


def _rng_state(env) -> dict:
    state = {"torch": torch.get_rng_state(), "env": env.base_env._rng.get_state(), "numpy": np.random.get_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict, env) -> None:
    torch.set_rng_state(state["torch"])
    env.base_env._rng.set_state(state["env"])
    np.random.set_state(state["numpy"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def train(cfg: DictConfig, run_dir: str | Path) -> dict:
    """Train ``cfg.method`` and return the final evaluation metrics. Writes CSVs, checkpoints, a PNG."""
    t = cfg.train
    run_dir = Path(run_dir)
    resume = load_checkpoint(cfg.resume) if cfg.resume else None
    if resume is not None and resume.get("policy_only"):
        raise CheckpointError(f"{cfg.resume} is an exported policy (no optimiser, targets or RNG state): "
                              f"resume from the run's own checkpoint.pt")
    if resume is not None:
        check_compatible(resume["cfg"], OmegaConf.to_container(cfg, resolve=True), cfg.resume)
        check_resume_overrides(resume["cfg"], OmegaConf.to_container(cfg, resolve=True), cfg.resume)
        run_dir = Path(cfg.resume).resolve().parent  # continue the same run folder
    torch.set_num_threads(t.threads)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    device = resolve_device(cfg.device)

    # Env (batched, on the configured device) and a separate evaluation env.
    env = make_env(cfg, device=device)
    eval_env = make_env(cfg, num_envs=t.eval_envs, seed=cfg.seed + VALIDATION_SEED_OFFSET, device=device)
    layout = env.base_env.layout

    # Modules, policy (coordinator -> agent -> greedy -> epsilon-greedy), loss, optimiser, targets.
    mods = make_modules(cfg, layout, device, n_actions=action_count(env))
    policy = make_policy(mods["agent"], env.full_action_spec_unbatched, mods["coordinator"],
                         eps_init=t.eps_init, eps_end=t.eps_end)
    explore = exploration_module(policy)
    loss = make_loss(cfg, mods)
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # its INFO lines (with colour codes) break the bar
    # foreach: one multi-tensor kernel per step instead of a loop over ~30 parameters (CPU too).
    if t.optimizer == "rmsprop":
        optim = torch.optim.RMSprop(loss.parameters(), lr=t.lr, alpha=0.99, eps=1e-5, foreach=True)
    else:
        optim = torch.optim.Adam(loss.parameters(), lr=t.lr, foreach=True)
    updater = make_target_updater(loss, t.target_update, interval=t.target_update_interval, tau=t.tau)

    frames, updates, batches = 0, 0, 0
    if resume is not None:
        load_weights(loss, resume["loss"], cfg.resume, cfg.method.name)
        optim.load_state_dict(resume["optimizer"])
        updater.load_state_dict(resume["updater"])
        frames, updates, batches = resume["frames"], resume["updates"], resume["batches"]
        _set_rng_state(resume["rng"], env)

    # Collector and segment replay.
    frames_per_batch = cfg.env.num_envs * t.steps_per_batch
    remaining = max(t.total_frames - frames, 0)
    remaining = math.ceil(remaining / frames_per_batch) * frames_per_batch
    cutter = SegmentCutter(length=cfg.method.period)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(t.buffer_segments, device=device),
                                    sampler=RandomSampler(), batch_size=t.batch_segments)
    explore.eps.fill_(epsilon(frames, t))  # a resumed run continues its schedule, not from eps_init
    # The bar ends where the collector does (the budget rounded up to whole batches); a resumed
    # run's CSVs lose the rows written after its checkpoint, so no frame is logged twice.
    logger = RunLogger(run_dir, cfg, total_frames=frames + remaining, initial_frames=frames,
                       truncate=resume is not None)
    if resume is None:  # a resumed run keeps the record of how it was started
        OmegaConf.save(cfg, run_dir / "config.yaml")
    if resume is not None and resume.get("replay_segments"):
        if load_replay(buffer, run_dir / REPLAY_DIR):
            logger.print(f"replay buffer restored: {len(buffer)} segments")
        else:
            logger.print(f"no replay buffer dump in {run_dir}: resuming with an empty buffer (warm-up again)")

    def checkpoint(name: str = "checkpoint.pt") -> Path:
        if t.checkpoint_buffer:  # first the data, then the checkpoint that refers to it
            save_replay(buffer, run_dir / REPLAY_DIR)
        return save_checkpoint(run_dir / name, {
            "cfg": OmegaConf.to_container(cfg, resolve=True), "layout": layout.__dict__, "frames": frames,
            "updates": updates, "batches": batches, "loss": loss.state_dict(), "optimizer": optim.state_dict(),
            "updater": updater.state_dict(), "rng": _rng_state(env), "epsilon": float(explore.eps),
            "replay_segments": len(buffer) if t.checkpoint_buffer else 0})

    eval_seed = cfg.seed + VALIDATION_SEED_OFFSET  # every evaluation faces the same initial configurations

    def run_eval() -> dict:
        start = time.perf_counter()
        metrics = evaluate(eval_env, policy, seed=eval_seed)
        timers["eval"] += time.perf_counter() - start
        logger.log("eval", {"frames": frames, **metrics})
        evaluated.append(metrics)
        logger.print(f"[eval] frames={frames} reward={metrics['reward']:.2f}±{metrics['reward_std']:.2f} "
                     f"task={metrics['task_reward']:.2f} pick={metrics['pick']:.2f} collect={metrics['collect']:.2f} "
                     f"defense={metrics['defense']:.2f} invasion={metrics['invasion']:.2f}")
        return metrics

    if resume is None:  # the yardsticks, on the very episodes every evaluation plays
        references = {}
        for name in cfg.eval.references:
            ref = make_reference_policy(name, eval_env, radius=cfg.eval.blend_radius, seed=cfg.seed)
            references[reference_label(name, cfg.eval.blend_radius)] = evaluate(eval_env, ref, seed=eval_seed)
        (run_dir / REFERENCES_FILE).write_text(json.dumps(references, indent=2))
        for label, m in references.items():
            logger.print(f"[eval] {label}: reward={m['reward']:.2f}±{m['reward_std']:.2f} task={m['task_reward']:.2f} "
                         f"pick={m['pick']:.2f} defense={m['defense']:.2f}")
    timers = {"collect": 0.0, "train": 0.0, "eval": 0.0}
    evaluated: list[dict] = []
    tracker = EpisodeTracker(cfg.env.num_envs, device)
    recent = []  # finished episodes since the last log row
    episode_stats = {k: float("nan") for k in ["episode_reward"] + [f"episode_{k}" for k in EVENT_KEYS]}
    last_eval = last_ckpt = frames
    final = {}
    collector = None
    stop = GracefulInterrupt()
    try:
        if remaining > 0:
            # No trajectory ids: segments are cut on step_count, and the ids cost a td update per step.
            collector = Collector(env, policy, frames_per_batch=frames_per_batch, total_frames=remaining,
                                  device=device, storing_device=device, auto_register_policy_transforms=False,
                                  track_traj_ids=False)
            start_wall, start_frames = time.perf_counter(), frames
            tick = time.perf_counter()
            for batch in collector:
                timers["collect"] += time.perf_counter() - tick
                frames += batch.numel()
                batches += 1
                explore.eps.fill_(epsilon(frames, t))
                recent.append(tracker.update(batch))
                buffer.extend(cutter(batch.select(*REPLAY_KEYS, strict=False)))  # cut only what is replayed

                tick = time.perf_counter()
                row = {}
                if len(buffer) >= max(t.warmup_segments, t.batch_segments):
                    for _ in range(t.updates_per_batch):
                        losses = loss(buffer.sample())
                        optim.zero_grad(set_to_none=True)
                        total_loss(losses).backward()
                        if t.grad_clip > 0:
                            losses["grad_norm"] = torch.nn.utils.clip_grad_norm_(loss.parameters(), t.grad_clip)
                        optim.step()
                        updater.step()
                        updates += 1
                    row = {k: v.item() for k, v in losses.items()}  # one host sync per batch, for logging
                timers["train"] += time.perf_counter() - tick

                if batches % cfg.logger.log_interval == 0:
                    episode_stats = _log_train(logger, frames, updates, float(explore.eps), row, recent, cfg) or episode_stats
                    recent = []
                sps = (frames - start_frames) / (time.perf_counter() - start_wall)
                logger.log("timing", {"frames": frames, "sps": sps, **{f"time_{k}": v for k, v in timers.items()}})
                # On a fixed grid of frames (every interval crossed), so a resumed run evaluates and
                # checkpoints at the same frames as an uninterrupted one.
                if t.eval_interval and frames // t.eval_interval > last_eval // t.eval_interval:
                    run_eval()
                    last_eval = frames
                if t.checkpoint_interval and frames // t.checkpoint_interval > last_ckpt // t.checkpoint_interval:
                    checkpoint()
                    last_ckpt = frames
                logger.progress(frames, **{"env-steps/s": sps, "epsilon": float(explore.eps),
                                           "episode reward": episode_stats["episode_reward"],
                                           "picks": episode_stats["episode_pick"],
                                           "deliveries": episode_stats["episode_collect"],
                                           "defenses": episode_stats["episode_defense"],
                                           "invasions": episode_stats["episode_invasion"]})
                if stop.requested:
                    break
                tick = time.perf_counter()
    except KeyboardInterrupt:  # a second Ctrl-C: stop at once
        stop.requested = True
    finally:
        stop.restore()
        if collector is not None:
            collector.shutdown()
    interrupted = stop.requested
    if interrupted:
        logger.print(f"interrupted by {stop.signal_name or 'a signal'} at {frames} frames: saving a checkpoint")
    path = checkpoint()
    if not interrupted and remaining > 0:  # a resumed run already at its budget has nothing new to evaluate
        final = run_eval() if last_eval != frames or not evaluated else evaluated[-1]
        plot_learning_curve(run_dir)
    logger.close()
    print(finish_message(run_dir, path, frames, interrupted, final), flush=True)
    return final


def check_resume_overrides(saved: dict, cfg: dict, path) -> None:
    """Refuse, by name, overrides that a resumed run cannot honour: its seed (the restored RNG
    streams belong to the old one), its env (the replay data came from it) and its exploration
    schedule (epsilon continues exactly). The budget and evaluation settings may change."""
    fixed = [("seed",), ("env",), ("train", "eps_init"), ("train", "eps_end"), ("train", "eps_decay_frames"),
             ("train", "steps_per_batch")]
    diffs = []
    for keys in fixed:
        a, b = saved, cfg
        for k in keys:
            a, b = (a or {}).get(k), (b or {}).get(k)
        if a != b:
            diffs.append(f"{'.'.join(keys)} (checkpoint {a!r}, now {b!r})")
    if diffs:
        raise CheckpointError(f"resume={path} cannot change " + "; ".join(diffs)
                              + ": drop these overrides, or start a new run without resume=")


def finish_message(run_dir: Path, checkpoint: Path, frames: int, interrupted: bool, final: dict) -> str:
    """What a newcomer needs at the end: what happened, where the results are, what to run next."""
    lines = [f"{'stopped' if interrupted else 'done'}: {frames:,} env steps; run folder {run_dir}"]
    if final:
        lines.append(f"  final greedy evaluation: team reward {final['reward']:.1f}, task reward "
                     f"{final['task_reward']:.1f}, picks {final['pick']:.1f}, defenses {final['defense']:.1f} "
                     f"(reference policies: {REFERENCES_FILE})")
    lines += [f"  metrics: train.csv, eval.csv, timing.csv; figure: learning_curve.png",
              f"  checkpoint: {checkpoint}"]
    if interrupted:
        lines.append(f"  continue: icco train resume={checkpoint}")
    else:
        lines.append(f"  next: icco eval checkpoint={checkpoint} eval.protocol=quadrants")
    return "\n".join(lines)


def _log_train(logger: RunLogger, frames: int, updates: int, eps: float, row: dict, recent: list, cfg) -> dict | None:
    """One ``train.csv`` row; returns the mean of the episodes that ended since the last row."""
    episodes = torch.cat(recent) if recent else torch.zeros(0, 1 + len(EVENT_KEYS))
    names = ["episode_reward"] + [f"episode_{k}" for k in EVENT_KEYS]
    stats = {n: (episodes[:, i].mean().item() if len(episodes) else float("nan")) for i, n in enumerate(names)}
    loss_keys = ["loss_td", "q_taken", "q_tot", "td_error", "grad_norm"]
    if cfg.method.coordinator and (cfg.method.ce_coef > 0 or cfg.method.entropy_coef > 0):
        loss_keys += ["loss_ce", "ce_neg_entropy", "entropy"] + (["ce_nll", "log_q"] if cfg.method.ce_coef > 0 else [])
    losses = {k: row.get(k, float("nan")) for k in loss_keys}
    logger.log("train", {"frames": frames, "updates": updates, "epsilon": eps, "episodes": len(episodes),
                         **stats, **losses})
    return stats if len(episodes) else None


def plot_learning_curve(run_dir: Path) -> Path | None:
    """``learning_curve.png``: greedy evaluation (team reward and task reward) against frames,
    with the reference policies of ``references.json`` as horizontal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from icco_torchrl.training.logger import read_column

    evaluation = read_column(run_dir, "eval", "reward")
    if evaluation is None:
        return None
    refs_file = run_dir / REFERENCES_FILE
    refs = json.loads(refs_file.read_text()) if refs_file.exists() else {}
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, key, title in ((axes[0], "reward", "team reward (task + instruction)"),
                           (axes[1], "task_reward", "task reward (picks, deliveries, defenses, invasions)")):
        column = read_column(run_dir, "eval", key)
        if column is None:
            continue
        (x, y), (_, s) = column, read_column(run_dir, "eval", f"{key}_std")
        line, = ax.plot(x, y, marker="o", color="C0", label="trained policy, greedy")
        ax.fill_between(x, y - s, y + s, color=line.get_color(), alpha=0.2, label="± std over episodes")
        for i, (label, m) in enumerate(refs.items()):
            if key in m:
                ax.axhline(m[key], color=f"C{i + 1}", ls="--", lw=1, label=label)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("env steps")
        ax.set_ylabel("per 145-step episode (team total)")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8, loc="best")
    fig.tight_layout()
    out = run_dir / "learning_curve.png"
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out
