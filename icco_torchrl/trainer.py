"""Training, in TorchRL's order: config -> env -> modules -> collector -> buffer -> loss -> loop ->
eval.

Every method (a preset of ``conf/method/``, :mod:`icco_torchrl.methods`) runs this one loop;
they differ only in the ``method`` config group.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.collectors import Collector

from icco_torchrl.envs import EVENT_KEYS
from icco_torchrl.envs.reference_policies import make_reference_policy, reference_label
from icco_torchrl.evaluation.plots import plot_learning_curve
from icco_torchrl.evaluation.rollout import evaluate
from icco_torchrl.modules.policy import exploration_module
from icco_torchrl.objectives import total_loss
from icco_torchrl.training.build import VALIDATION_SEED_OFFSET, Run, build
from icco_torchrl.training.checkpoint import (
    CheckpointError,
    check_compatible,
    load_checkpoint,
    load_replay,
    load_weights,
    save_checkpoint,
    save_replay,
)
from icco_torchrl.training.config import set_env_params, validate
from icco_torchrl.training.interrupt import GracefulInterrupt
from icco_torchrl.training.logger import RunLogger
from icco_torchrl.training.rng import rng_state, set_rng_state

REPLAY_DIR = "replay"  # the replay buffer dump beside checkpoint.pt (train.checkpoint_buffer)
REFERENCES_FILE = "references.json"  # the reference policies' evaluation, beside eval.csv

# What the loss reads; everything else the collector records is left out of the replay buffer.
REPLAY_KEYS = [
    ("agents", "observation"),
    "state",
    ("agents", "action"),
    ("agents", "prev_action"),
    ("agents", "rnn_hidden"),
    ("agents", "z"),
    ("agents", "z_noise"),
    "step_count",
    "mask",
    ("next", "agents", "observation"),
    ("next", "state"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "step_count"),
]
EPISODE_COLUMNS = ["episode_reward"] + [
    f"episode_{k}" for k in EVENT_KEYS
]  # train.csv: per finished episode


def epsilon(frames: int, t: DictConfig) -> float:
    """COPA's exponential decay from eps_init to eps_end over ``eps_decay_frames``."""
    if t.eps_decay_frames == 0 or t.eps_init == 0:
        return t.eps_end
    frac = min(frames / t.eps_decay_frames, 1.0)
    return (
        max(t.eps_init * (t.eps_end / t.eps_init) ** frac, t.eps_end)
        if t.eps_end > 0
        else t.eps_init * (1 - frac)
    )


class EpisodeTracker:
    """Running per-env totals of team reward and events; returns the episodes that ended."""

    def __init__(self, num_envs: int, device):
        self.sums = torch.zeros(num_envs, 1 + len(EVENT_KEYS), device=device)

    def update(self, batch) -> torch.Tensor:
        nxt = batch.get("next")
        step_values = torch.stack(
            [nxt.get("reward").squeeze(-1)] + [nxt.get(("events", k)).float() for k in EVENT_KEYS],
            -1,
        )
        done = nxt.get("done").squeeze(-1)  # [B, L]
        finished = []
        for t in range(batch.shape[1]):  # L is small (steps_per_batch); envs are vectorised
            self.sums += step_values[:, t]
            if done[:, t].any():
                finished.append(self.sums[done[:, t]].clone())
                self.sums[done[:, t]] = 0
        return torch.cat(finished) if finished else self.sums.new_zeros(0, self.sums.shape[1])


@dataclass
class Progress:
    """Where a run stands: env steps collected, gradient updates, collector batches."""

    frames: int = 0
    updates: int = 0
    batches: int = 0


def train(cfg: DictConfig, run_dir: str | Path) -> dict:
    """Train ``cfg.method`` (a config :func:`~icco_torchrl.training.config.validate` checked) and
    return the final evaluation metrics; writes CSVs, checkpoints and ``learning_curve.png`` to
    ``run_dir`` (with ``resume=``, to the checkpoint's folder)."""
    run_dir = Path(cfg.resume).resolve().parent if cfg.resume else Path(run_dir)
    seed_process(cfg)
    training = TrainingRun(build(cfg, for_training=True), cfg, run_dir)
    if cfg.resume:
        training.resume(cfg.resume)
    else:
        training.start()
    interrupted = training.loop(training.remaining)
    return training.finish(interrupted)


def seed_process(cfg: DictConfig) -> None:
    """Threads and the global seeds, before anything is built."""
    torch.set_num_threads(cfg.train.threads)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # its INFO lines break the bar


def _remaining_frames(cfg: DictConfig, frames: int) -> int:
    """The budget left after ``frames``, rounded up to whole collector batches."""
    per_batch = cfg.env.num_envs * cfg.train.steps_per_batch
    return math.ceil(max(cfg.train.total_frames - frames, 0) / per_batch) * per_batch


class TrainingRun:
    """One training run's moving parts around the assembled
    :class:`~icco_torchrl.training.build.Run`: progress counters, timers, the logger, the
    evaluations and the checkpoints."""

    def __init__(self, run: Run, cfg: DictConfig, run_dir: Path):
        self.run, self.cfg, self.run_dir = run, cfg, run_dir
        self.progress = Progress()
        self.explore = exploration_module(run.policy)
        self.explore.eps.fill_(epsilon(0, cfg.train))
        # Every evaluation faces the same initial configurations.
        self.eval_seed = cfg.seed + VALIDATION_SEED_OFFSET
        self.timers = {"collect": 0.0, "train": 0.0, "eval": 0.0}
        self.evaluated: list[dict] = []
        self.logger: RunLogger | None = None
        self.remaining = 0  # frames this process trains (set by start or resume)

    # ------------------------------------------------------------------ start / resume
    def start(self) -> None:
        """A new run: its config, its logs, and the reference policies on the very episodes every
        evaluation plays."""
        self._open_logs(0, resumed=False)
        OmegaConf.save(self.cfg, self.run_dir / "config.yaml")
        references = {}
        for name in self.cfg.eval.references:
            ref = make_reference_policy(
                name, self.run.eval_env, radius=self.cfg.eval.blend_radius, seed=self.cfg.seed
            )
            references[reference_label(name, self.cfg.eval.blend_radius)] = evaluate(
                self.run.eval_env, ref, seed=self.eval_seed
            )
        (self.run_dir / REFERENCES_FILE).write_text(json.dumps(references, indent=2))
        for label, m in references.items():
            self.logger.print(
                f"[eval] {label}: reward={m['reward']:.2f}±{m['reward_std']:.2f} "
                f"task={m['task_reward']:.2f} pick={m['pick']:.2f} defense={m['defense']:.2f}"
            )

    def resume(self, path: str | Path) -> None:
        """Continue the run saved at ``path``, in one step: load the checkpoint, check that this
        config can continue it (:func:`check_resumable`), restore everything it holds. The run
        keeps its ``config.yaml``."""
        ckpt = load_checkpoint(path)
        check_resumable(ckpt, self.cfg, self.run.layout, path)
        self._open_logs(ckpt["frames"], resumed=True)
        self._restore(ckpt, path)

    def _open_logs(self, start: int, resumed: bool) -> None:
        """The logger, its bar ending where the collector will; a resumed run's CSVs lose the rows
        written after its checkpoint, so no frame is logged twice."""
        self.remaining = _remaining_frames(self.cfg, start)
        self.logger = RunLogger(
            self.run_dir,
            self.cfg,
            total_frames=start + self.remaining,
            initial_frames=start,
            truncate=resumed,
        )

    def _restore(self, ckpt: dict, path: str | Path) -> None:
        """Weights, optimiser, target updater, counters, exploration rate, RNG streams and the
        replay buffer of a checked checkpoint."""
        run = self.run
        load_weights(run.loss, ckpt["loss"], path, self.cfg.method.name)
        run.optim.load_state_dict(ckpt["optimizer"])
        run.updater.load_state_dict(ckpt["updater"])
        self.progress = Progress(ckpt["frames"], ckpt["updates"], ckpt["batches"])
        # The schedule continues.
        self.explore.eps.fill_(epsilon(self.progress.frames, self.cfg.train))
        set_rng_state(ckpt["rng"], run.env)
        if ckpt.get("replay_segments"):
            if load_replay(run.buffer, self.run_dir / REPLAY_DIR):
                self.logger.print(f"replay buffer restored: {len(run.buffer)} segments")
            else:
                self.logger.print(
                    f"no replay buffer dump in {self.run_dir}: resuming with an empty buffer "
                    f"(warm-up again)"
                )

    # ------------------------------------------------------------------ loop
    def loop(self, remaining: int) -> bool:
        """Collect and learn ``remaining`` more frames; True when a signal stopped it."""
        if remaining <= 0:
            return False
        run, t, p = self.run, self.cfg.train, self.progress
        # No trajectory ids: segments are cut on step_count, and the ids cost a td update per step.
        collector = Collector(
            run.env,
            run.policy,
            frames_per_batch=self.cfg.env.num_envs * t.steps_per_batch,
            total_frames=remaining,
            device=run.env.device,
            storing_device=run.env.device,
            auto_register_policy_transforms=False,
            track_traj_ids=False,
        )
        tracker = EpisodeTracker(self.cfg.env.num_envs, run.env.device)
        recent, episode_stats = (
            [],
            {k: float("nan") for k in EPISODE_COLUMNS},
        )  # episodes since the last row
        last_eval = last_ckpt = p.frames
        start_wall, start_frames = time.perf_counter(), p.frames
        stop = GracefulInterrupt()
        try:
            tick = time.perf_counter()
            for batch in collector:
                self.timers["collect"] += time.perf_counter() - tick
                p.frames += batch.numel()
                p.batches += 1
                self.explore.eps.fill_(epsilon(p.frames, t))
                recent.append(tracker.update(batch))
                items = run.cutter(
                    batch.select(*REPLAY_KEYS, strict=False)
                )  # only what is replayed
                if items.shape[0]:  # items longer than a batch complete in a later one
                    run.buffer.extend(items)
                tick = time.perf_counter()
                row = self.learn()
                self.timers["train"] += time.perf_counter() - tick
                if p.batches % self.cfg.logger.log_interval == 0:
                    episode_stats = self.log_train(row, recent) or episode_stats
                    recent = []
                sps = (p.frames - start_frames) / (time.perf_counter() - start_wall)
                self.logger.log(
                    "timing",
                    {
                        "frames": p.frames,
                        "sps": sps,
                        **{f"time_{k}": v for k, v in self.timers.items()},
                    },
                )
                # On a fixed grid of frames (every interval crossed), so a resumed run evaluates and
                # checkpoints at the same frames as an uninterrupted one.
                if t.eval_interval and p.frames // t.eval_interval > last_eval // t.eval_interval:
                    self.evaluate()
                    last_eval = p.frames
                if (
                    t.checkpoint_interval
                    and p.frames // t.checkpoint_interval > last_ckpt // t.checkpoint_interval
                ):
                    self.save()
                    last_ckpt = p.frames
                self.logger.progress(
                    p.frames,
                    **{
                        "env-steps/s": sps,
                        "epsilon": float(self.explore.eps),
                        "episode reward": episode_stats["episode_reward"],
                        "picks": episode_stats["episode_pick"],
                        "deliveries": episode_stats["episode_collect"],
                        "defenses": episode_stats["episode_defense"],
                        "invasions": episode_stats["episode_invasion"],
                    },
                )
                if stop.requested:
                    break
                tick = time.perf_counter()
        except KeyboardInterrupt:  # a second Ctrl-C: stop at once
            stop.requested = True
        finally:
            stop.restore()
            collector.shutdown()
        if stop.requested:
            self.logger.print(
                f"interrupted by {stop.signal_name or 'a signal'} at {p.frames} frames: "
                f"saving a checkpoint"
            )
        return stop.requested

    def learn(self) -> dict:
        """``train.updates_per_batch`` updates once the buffer holds the warm-up; the last update's
        metrics (one host sync per batch), or ``{}`` before the warm-up ends."""
        run, t = self.run, self.cfg.train
        if len(run.buffer) < max(t.warmup_segments, t.batch_segments):
            return {}
        for _ in range(t.updates_per_batch):
            losses = run.loss(run.buffer.sample())
            run.optim.zero_grad(set_to_none=True)
            total_loss(losses).backward()
            if t.grad_clip > 0:
                losses["grad_norm"] = torch.nn.utils.clip_grad_norm_(
                    run.loss.parameters(), t.grad_clip
                )
            run.optim.step()
            run.updater.step()
            self.progress.updates += 1
        return {k: v.item() for k, v in losses.items()}

    def log_train(self, row: dict, recent: list) -> dict | None:
        """One ``train.csv`` row: the loss's own metrics (``loss.metric_keys``, NaN before the first
        update) and the episodes that ended since the last row; returns their means."""
        p = self.progress
        episodes = torch.cat(recent) if recent else torch.zeros(0, len(EPISODE_COLUMNS))
        stats = {
            n: (episodes[:, i].mean().item() if len(episodes) else float("nan"))
            for i, n in enumerate(EPISODE_COLUMNS)
        }
        metrics = {k: row.get(k, float("nan")) for k in (*self.run.loss.metric_keys, "grad_norm")}
        self.logger.log(
            "train",
            {
                "frames": p.frames,
                "updates": p.updates,
                "epsilon": float(self.explore.eps),
                "episodes": len(episodes),
                **stats,
                **metrics,
            },
        )
        return stats if len(episodes) else None

    # ------------------------------------------------------------------ evaluation and checkpoints
    def evaluate(self) -> dict:
        """A greedy evaluation on the evaluation env, logged to ``eval.csv``."""
        start, frames = time.perf_counter(), self.progress.frames
        metrics = evaluate(self.run.eval_env, self.run.policy, seed=self.eval_seed)
        self.timers["eval"] += time.perf_counter() - start
        self.logger.log("eval", {"frames": frames, **metrics})
        self.evaluated.append((frames, metrics))
        self.logger.print(
            f"[eval] frames={frames} reward={metrics['reward']:.2f}±{metrics['reward_std']:.2f} "
            f"task={metrics['task_reward']:.2f} pick={metrics['pick']:.2f} "
            f"collect={metrics['collect']:.2f} defense={metrics['defense']:.2f} "
            f"invasion={metrics['invasion']:.2f}"
        )
        return metrics

    def final_evaluation(self) -> dict:
        """The evaluation at the last frame (the loop's own when it ran there)."""
        if self.evaluated and self.evaluated[-1][0] == self.progress.frames:
            return self.evaluated[-1][1]
        return self.evaluate()

    def finish(self, interrupted: bool) -> dict:
        """A last checkpoint; unless the run was stopped or had nothing left to train, the final
        evaluation and the learning curve; then the closing message. Returns the final metrics."""
        path = self.save()
        final = {}
        if not interrupted and self.remaining > 0:
            final = self.final_evaluation()
            refs_file = self.run_dir / REFERENCES_FILE
            refs = json.loads(refs_file.read_text()) if refs_file.exists() else {}
            plot_learning_curve(self.run_dir, refs)
        self.logger.close()
        message = finish_message(self.run_dir, path, self.progress.frames, interrupted, final)
        print(message, flush=True)
        return final

    def save(self, name: str = "checkpoint.pt") -> Path:
        """The checkpoint (with ``train.checkpoint_buffer``, the replay dump it names, first)."""
        run, t, p = self.run, self.cfg.train, self.progress
        if t.checkpoint_buffer:
            save_replay(run.buffer, self.run_dir / REPLAY_DIR)
        return save_checkpoint(
            self.run_dir / name,
            {
                "cfg": OmegaConf.to_container(self.cfg, resolve=True),
                "layout": run.layout.__dict__,
                "frames": p.frames,
                "updates": p.updates,
                "batches": p.batches,
                "loss": run.loss.state_dict(),
                "optimizer": run.optim.state_dict(),
                "updater": run.updater.state_dict(),
                "rng": rng_state(run.env),
                "epsilon": float(self.explore.eps),
                "replay_segments": len(run.buffer) if t.checkpoint_buffer else 0,
            },
        )


def check_resumable(ckpt: dict, cfg: DictConfig, layout, path: str | Path) -> None:
    """Refuse, in one line, a checkpoint this config cannot continue: an exported policy, a
    command line that changes what a resumed run cannot honour (:func:`check_resume_overrides`)
    or networks and env layout that differ (``check_compatible``). A new ``train.env_params`` is
    allowed (a shaping curriculum), and said: the replayed data keeps the old rewards."""
    if ckpt.get("policy_only"):
        raise CheckpointError(
            f"{path} is an exported policy (no optimiser, targets or RNG state): "
            f"resume from the run's own checkpoint.pt"
        )
    # The saved config through today's schema, so fields added since it was written compare as
    # defaults.
    saved = OmegaConf.to_container(validate(OmegaConf.create(ckpt["cfg"])), resolve=True)
    check_resume_overrides(saved, OmegaConf.to_container(cfg, resolve=True), path)
    check_compatible(ckpt, cfg, layout, path)
    before, now = set_env_params(saved["train"]["env_params"]), set_env_params(cfg.train.env_params)
    if before != now:
        print(
            f"note: resume={path} trains on train.env_params {now} instead of {before}; "
            f"replayed transitions keep the rewards they were collected with",
            flush=True,
        )


def check_resume_overrides(saved: dict, cfg: dict, path) -> None:
    """Refuse, by name, overrides that a resumed run cannot honour: its seed (the restored RNG
    streams belong to the old one), its env (the replay data came from it) and its exploration
    schedule (epsilon continues exactly). The budget, evaluation settings and the training-only
    ``train.env_params`` (a shaping curriculum) may change."""
    fixed = [
        ("seed",),
        ("env",),
        ("train", "eps_init"),
        ("train", "eps_end"),
        ("train", "eps_decay_frames"),
        ("train", "steps_per_batch"),
    ]
    diffs = []
    for keys in fixed:
        a, b = saved, cfg
        for k in keys:
            a, b = (a or {}).get(k), (b or {}).get(k)
        if a != b:
            diffs.append(f"{'.'.join(keys)} (checkpoint {a!r}, now {b!r})")
    if diffs:
        raise CheckpointError(
            f"resume={path} cannot change "
            + "; ".join(diffs)
            + ": drop these overrides, or start a new run without resume="
        )


def finish_message(
    run_dir: Path, checkpoint: Path, frames: int, interrupted: bool, final: dict
) -> str:
    """What a newcomer needs at the end: what happened, where the results are, what to run next."""
    lines = [f"{'stopped' if interrupted else 'done'}: {frames:,} env steps; run folder {run_dir}"]
    if final:
        lines.append(
            f"  final greedy evaluation: team reward {final['reward']:.1f}, task reward "
            f"{final['task_reward']:.1f}, picks {final['pick']:.1f}, defenses "
            f"{final['defense']:.1f} (reference policies: {REFERENCES_FILE})"
        )
    lines += [
        "  metrics: train.csv, eval.csv, timing.csv; figure: learning_curve.png",
        f"  checkpoint: {checkpoint}",
    ]
    if interrupted:
        lines.append(f"  continue: icco train resume={checkpoint}")
    else:
        lines.append(f"  next: icco eval checkpoint={checkpoint} eval.protocol=quadrants")
    return "\n".join(lines)
