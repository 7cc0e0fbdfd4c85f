"""Training, in TorchRL's order: config -> env -> modules -> collector -> buffer -> loss -> loop ->
eval.

Every method (a preset of ``conf/method/``, :mod:`icco_torchrl.methods`) runs this one loop;
they differ only in the ``method`` config group.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import shlex
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from icco_torchrl.envs import EVENT_KEYS
from icco_torchrl.envs.reference_policies import (
    BEST_SCRIPTED_LABEL,
    make_reference_policy,
    reference_label,
)
from icco_torchrl.evaluation.rollout import evaluate
from icco_torchrl.modules.policy import exploration_module
from icco_torchrl.training import checkpoint
from icco_torchrl.training.build import VALIDATION_SEED_OFFSET, Run, build
from icco_torchrl.training.checkpoint import RunState, load_weights
from icco_torchrl.training.collector_process import CollectorError, make_collector
from icco_torchrl.training.config import check_collector
from icco_torchrl.training.interrupt import (
    GracefulInterrupt,
    Interrupted,
    StopAtOnce,
    UpdateAbandoned,
)
from icco_torchrl.training.logger import RunLogger, last_evaluation
from icco_torchrl.training.run_folder import (
    CHECKPOINT,
    REFERENCES_FILE,
    SNAPSHOTS,
    RunFolderLock,
    fresh_outputs,
)
from icco_torchrl.training.update import metrics_row

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
        """The totals ``[E, 1 + events]`` of the episodes that ended in ``batch [B, L]``, in the
        order they ended (step, then env), in one pass over the batch (one host sync)."""
        nxt = batch.get("next")
        step_values = torch.stack(
            [nxt.get("reward").squeeze(-1)] + [nxt.get(("events", k)).float() for k in EVENT_KEYS],
            -1,
        )  # [B, L, K]
        done = nxt.get("done").squeeze(-1)  # [B, L]
        B, L, K = step_values.shape
        # Episode slot of each step: how many of its env's episodes ended before it.
        ended = done.long().cumsum(1)
        slot = ended - done.long()
        bins = torch.zeros(B, L + 1, K, dtype=self.sums.dtype, device=self.sums.device)
        bins[:, 0] = self.sums  # the episode running at the batch's start
        bins.scatter_add_(1, slot.unsqueeze(-1).expand(B, L, K), step_values)  # in step order
        t, b = done.t().nonzero(as_tuple=True)
        finished = bins[b, slot[b, t]]
        self.sums = bins[torch.arange(B, device=bins.device), ended[:, -1]]
        return finished


@dataclass
class Progress:
    """Where a run stands: env steps collected, gradient updates, collector batches."""

    frames: int = 0
    updates: int = 0
    batches: int = 0


def train(
    cfg: DictConfig,
    run_dir: str | Path,
    on_start: Callable[[], None] | None = None,
    saved: RunState | None = None,
) -> dict:
    """Train ``cfg.method`` (a config :func:`~icco_torchrl.training.config.validate` checked) and
    return the final evaluation metrics; writes CSVs, checkpoints and ``learning_curve.png`` to
    ``run_dir`` (with ``resume=``, to the checkpoint's folder; ``saved``: its state, when the
    command line has read it already). ``on_start`` runs once the folder is locked and the run
    started or its resume checked (the command's record of the run), so a refused run writes
    nothing."""
    check_collector(cfg)  # what train.collector needs of this machine, before any work
    run_dir = Path(cfg.resume).resolve().parent if cfg.resume else Path(run_dir)
    # One writer per run folder; a signal before the loop stops at once (nothing to save yet).
    with RunFolderLock(run_dir), StopAtOnce() as stop:
        try:
            seed_process(cfg)
            training = TrainingRun(build(cfg, for_training=True), cfg, run_dir)
            if cfg.resume:
                training.resume(cfg.resume, saved)
            else:
                training.start()
            if on_start is not None:
                with stop.held():
                    on_start()
        except Interrupted as err:
            again = (
                f"continue: {shlex.join(['icco', 'train', f'resume={cfg.resume}'])}"
                if cfg.resume
                else "start it again"
            )
            print(f"stopped by {err.signal_name} before training began: {again}", flush=True)
            return {}
        try:
            interrupted = training.loop(training.remaining)
        except Interrupted:  # a signal as the loop handed the signals back
            interrupted = True
        except CollectorError as err:  # between batches: the learner's state is whole
            training.logger.print(
                f"{err}: saving a checkpoint at {training.progress.frames} frames"
            )
            training.finish(True, stop)
            raise
        return training.finish(interrupted, stop)


def seed_process(cfg: DictConfig) -> None:
    """Threads and the global seeds, before anything is built."""
    torch.set_num_threads(cfg.train.threads)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # its INFO lines break the bar


def _rng_state(env, collector_torch=None) -> dict:
    """The random streams a run draws from (``RunState.rng``): torch (and CUDA), numpy, the
    env's own generator (``env.base_env._rng``) and, with ``train.collector=process``, the
    collector process's torch stream ``collector_torch``: a resumed run continues them exactly."""
    state = {
        "torch": torch.get_rng_state(),
        "env": env.base_env._rng.get_state(),
        "numpy": np.random.get_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    if collector_torch is not None:
        state["collector_torch"] = collector_torch
    return state


def _set_rng_state(state: dict, env):
    """Put back the streams of :func:`_rng_state`; returns the collector process's (or None)."""
    torch.set_rng_state(state["torch"])
    env.base_env._rng.set_state(state["env"])
    np.random.set_state(state["numpy"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
    return state.get("collector_torch")


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
        eps = epsilon(0, cfg.train)
        self.explore = exploration_module(run.policy)
        self.explore.eps.fill_(eps)
        # Every evaluation faces the same initial configurations.
        self.eval_seed = cfg.seed + VALIDATION_SEED_OFFSET
        self.timers = {"collect": 0.0, "train": 0.0, "eval": 0.0}
        self.evaluated: list[dict] = []
        self.logger: RunLogger | None = None
        self.remaining = 0  # frames this process trains (set by start or resume)
        self.outputs = fresh_outputs()  # final evaluation and curve of the last frame, written?
        self.replay_id: str | None = None  # the replay dump the last checkpoint names
        self.replay_segments = 0  # and the segments it holds
        self.collector_torch = None  # train.collector=process: its torch stream, as of the batch

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

    def resume(self, path: str | Path, state: RunState | None = None) -> None:
        """Continue the run saved at ``path`` (``state``: its state, when the command line has
        read it already): :func:`checkpoint.resume <icco_torchrl.training.checkpoint.resume>`
        reads and checks it and refills the replay buffer, in one call; :meth:`load_state_dict`
        takes it. The run keeps its ``config.yaml``."""
        state = checkpoint.resume(
            path, self.cfg, layout=self.run.layout, buffer=self.run.buffer, state=state
        )
        self.load_state_dict(state, origin=path)
        self.replay_segments = len(self.run.buffer)  # 0 when its dump was missing
        self._open_logs(state.frames, resumed=True)

    def _open_logs(self, start: int, resumed: bool) -> None:
        """The logger, its bar ending where the collector will; a resumed run's CSVs lose the rows
        written after its checkpoint, so no frame is logged twice, and the evaluation of its last
        frame, when ``eval.csv`` has it, counts as done."""
        self.remaining = _remaining_frames(self.cfg, start)
        self.logger = RunLogger(
            self.run_dir,
            self.cfg,
            total_frames=start + self.remaining,
            initial_frames=start,
            truncate=resumed,
        )
        logged = last_evaluation(self.run_dir, start) if resumed else None
        if logged is not None:
            self.evaluated.append((start, logged))

    # ------------------------------------------------------------------ state
    def state_dict(self) -> RunState:
        """Everything a resume needs, as the checkpoint holds it (:class:`RunState`): the config
        and env layout the state fits, the counters, the weights (targets included), the
        optimiser, the target updater, the RNG streams, the final outputs written, and the replay
        dump it names (none without ``train.checkpoint_buffer``). The tensors are the run's own,
        not copies."""
        run, p = self.run, self.progress
        return RunState(
            cfg=OmegaConf.to_container(self.cfg, resolve=True),
            layout=dict(vars(run.layout)),
            frames=p.frames,
            updates=p.updates,
            batches=p.batches,
            loss=run.loss.state_dict(),
            optimizer=run.optim.state_dict(),
            updater=run.updater.state_dict(),
            rng=_rng_state(run.env, self.collector_torch),
            outputs=dict(self.outputs),
            replay_id=self.replay_id,
            replay_segments=self.replay_segments if self.cfg.train.checkpoint_buffer else 0,
        )

    def load_state_dict(self, state: RunState, *, origin: str | Path = "the state dict") -> None:
        """Restore a :meth:`state_dict` (its ``cfg`` and ``layout`` are checked by
        ``checkpoint.resume``, not restored). Networks that do not match are one line naming
        ``origin``. The replay buffer is not touched."""
        run = self.run
        load_weights(run.loss, state.loss, origin, self.cfg.method.name)
        self.collector_torch = _set_rng_state(state.rng, run.env)
        run.optim.load_state_dict(state.optimizer)
        run.updater.load_state_dict(state.updater)
        self.progress = Progress(state.frames, state.updates, state.batches)
        # The schedule continues.
        self.explore.eps.fill_(epsilon(self.progress.frames, self.cfg.train))
        self.outputs = dict(state.outputs)
        self.replay_id, self.replay_segments = state.replay_id, state.replay_segments

    # ------------------------------------------------------------------ loop
    def loop(self, remaining: int) -> bool:
        """Collect and learn ``remaining`` more frames; True when a signal stopped it."""
        if remaining <= 0:
            return False
        run, t, p = self.run, self.cfg.train, self.progress
        collector = self._make_collector(remaining)
        tracker = EpisodeTracker(self.cfg.env.num_envs, run.env.device)
        recent = []  # episodes since the last row
        episode_stats = {k: float("nan") for k in EPISODE_COLUMNS}
        last_eval = last_ckpt = p.frames
        start_wall, start_frames = time.perf_counter(), p.frames
        stop = GracefulInterrupt()
        try:
            tick = time.perf_counter()
            for batch in collector:
                self.timers["collect"] += time.perf_counter() - tick
                self.collector_torch = getattr(collector, "torch_rng", None)
                recent.append(self._take_batch(batch, tracker))
                row = self._timed_learn()
                if p.batches % self.cfg.logger.log_interval == 0:
                    episode_stats = self.log_train(row, recent) or episode_stats
                    recent = []
                sps = self._log_timing(start_wall, start_frames)
                # On a fixed grid of frames (every interval crossed), so a resumed run evaluates and
                # checkpoints at the same frames as an uninterrupted one.
                if self._crossed(t.eval_interval, last_eval):
                    self.evaluate()
                    last_eval = p.frames
                if self._crossed(t.checkpoint_interval, last_ckpt):
                    self.save()
                    last_ckpt = p.frames
                self._show_progress(sps, episode_stats)
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

    def _make_collector(self, remaining: int):
        """The collector of ``remaining`` frames from the run's progress and RNG streams."""
        t = self.cfg.train
        # train.collector: inline, or a process that starts with the loop (collector_process.py).
        return make_collector(
            self.run,
            self.cfg,
            remaining,
            frames=self.progress.frames,
            epsilon=lambda frames: epsilon(frames, t),
            streams=self.collector_torch,
        )

    def _take_batch(self, batch, tracker: EpisodeTracker) -> torch.Tensor:
        """Count a collected batch, advance the exploration schedule and replay what the loss
        reads; returns the episodes that ended in it."""
        run, p = self.run, self.progress
        p.frames += batch.numel()
        p.batches += 1
        self.explore.eps.fill_(epsilon(p.frames, self.cfg.train))
        finished = tracker.update(batch)
        # Only what the loss reads is replayed.
        replayed = batch.select(*run.loss.in_keys, strict=False)
        items = run.cutter(replayed)
        if items.shape[0]:  # items longer than a batch complete in a later one
            run.buffer.extend(items)
        return finished

    def _timed_learn(self) -> dict:
        """:meth:`learn`, its time added to the ``train`` timer."""
        tick = time.perf_counter()
        try:
            row = self.learn()
        except UpdateAbandoned:  # a stop cut an update's compile short: not applied
            row = {}
        self.timers["train"] += time.perf_counter() - tick
        return row

    def _log_timing(self, start_wall: float, start_frames: int) -> float:
        """One ``timing.csv`` row; returns the env steps per second since the loop started."""
        p = self.progress
        sps = (p.frames - start_frames) / (time.perf_counter() - start_wall)
        self.logger.log(
            "timing",
            {
                "frames": p.frames,
                "sps": sps,
                **{f"time_{k}": v for k, v in self.timers.items()},
            },
        )
        return sps

    def _crossed(self, interval: int, last: int) -> bool:
        """Whether the frames since ``last`` crossed a multiple of ``interval`` (0: never)."""
        return bool(interval) and self.progress.frames // interval > last // interval

    def _show_progress(self, sps: float, episode_stats: dict) -> None:
        """The progress bar at the current frame, with the last logged episodes' means."""
        self.logger.progress(
            self.progress.frames,
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

    def learn(self) -> dict:
        """``train.updates_per_batch`` updates once the buffer holds the warm-up; the last update's
        metrics (one host sync per batch), or ``{}`` before the warm-up ends."""
        run, t = self.run, self.cfg.train
        if len(run.buffer) < max(t.warmup_segments, t.batch_segments):
            return {}
        for _ in range(t.updates_per_batch):
            metrics = run.update(run.buffer.sample())
            run.updater.step()
            self.progress.updates += 1
        return metrics_row(metrics)

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
    def evaluate(self, stop: StopAtOnce | None = None) -> dict:
        """A greedy evaluation on the evaluation env, logged to ``eval.csv`` (outside ``stop``'s
        reach: a signal cuts the evaluation, never the row)."""
        start, frames = time.perf_counter(), self.progress.frames
        metrics = evaluate(self.run.eval_env, self.run.policy, seed=self.eval_seed)
        self.timers["eval"] += time.perf_counter() - start
        with stop.held() if stop is not None else contextlib.nullcontext():
            if self.cfg.train.policy_snapshots:  # before its row: a logged mark has its weights
                checkpoint.save_checkpoint(
                    self.run_dir / SNAPSHOTS / f"{frames:09d}.pt",
                    checkpoint.policy_of(self.state_dict()),
                )
            self.logger.log("eval", {"frames": frames, **metrics})
            self.evaluated.append((frames, metrics))
            if stop is not None:  # the final evaluation: recorded with its row
                self.record(final_evaluation=True, final_metrics=metrics)
        self.logger.print(
            f"[eval] frames={frames} reward={metrics['reward']:.2f}±{metrics['reward_std']:.2f} "
            f"task={metrics['task_reward']:.2f} pick={metrics['pick']:.2f} "
            f"collect={metrics['collect']:.2f} defense={metrics['defense']:.2f} "
            f"invasion={metrics['invasion']:.2f}"
        )
        return metrics

    def final_evaluation(self, stop: StopAtOnce) -> dict:
        """The evaluation at the last frame (the loop's own, or the logged one of a stopped run,
        when there is one), recorded in the checkpoint."""
        frames = self.progress.frames
        if self.evaluated and self.evaluated[-1][0] == frames:
            with stop.held():
                self.record(final_evaluation=True, final_metrics=self.evaluated[-1][1])
            return self.evaluated[-1][1]
        self.logger.print(f"[eval] final evaluation at {frames} frames")
        return self.evaluate(stop)

    def finish(self, interrupted: bool, stop: StopAtOnce) -> dict:
        """A last checkpoint; unless the run was stopped, the final evaluation and the learning
        curve, each recorded in the checkpoint once written (a resume writes what a stop left
        out); then the closing message, naming only files that exist. Returns the final metrics.

        A signal here stops at once (no batch to finish), but never inside a checkpoint write."""
        pending = False  # stopped while writing the final outputs
        try:
            with stop.held():
                self.save(dump=self.remaining > 0)
            if not interrupted:
                if not self.outputs["final_evaluation"]:
                    self.final_evaluation(stop)
                if not self.outputs["learning_curve"]:
                    # matplotlib is imported only for the figure (not by a command refused early)
                    from icco_torchrl.evaluation.plots import plot_learning_curve

                    refs_file = self.run_dir / REFERENCES_FILE
                    refs = json.loads(refs_file.read_text()) if refs_file.exists() else {}
                    plot_learning_curve(self.run_dir, refs)
                    with stop.held():
                        self.record(learning_curve=True)
        except Interrupted as err:
            interrupted = pending = True
            self.logger.print(
                f"interrupted by {err.signal_name} during the final evaluation at "
                f"{self.progress.frames} frames: the checkpoint records what is still to write"
            )
        path = self.run_dir / CHECKPOINT
        self.logger.close()
        final = self.outputs["final_metrics"] if not interrupted else {}
        message = finish_message(
            self.run_dir, path, self.progress.frames, interrupted, final, self.outputs, pending
        )
        print(message, flush=True)
        return final

    def record(self, **outputs) -> None:
        """Note final outputs as written, in the checkpoint too (the replay dump is unchanged)."""
        self.outputs.update(outputs)
        self.save(dump=False)

    def save(self, dump: bool = True) -> None:
        """The checkpoint (with ``train.checkpoint_buffer`` and ``dump``, the replay dump it names,
        first; without ``dump`` it names the dump on disk)."""
        buffer = self.run.buffer if self.cfg.train.checkpoint_buffer and dump else None
        saved = checkpoint.save(self.run_dir, self.state_dict(), buffer)
        self.replay_id, self.replay_segments = saved.replay_id, saved.replay_segments


def best_scripted_share(run_dir: Path, reward: float) -> tuple[float, float] | None:
    """``(share, its reward)``: ``reward`` over the best scripted team's on the run's evaluation
    episodes (its ``references.json``); None without that row or with a reward <= 0."""
    path = Path(run_dir) / REFERENCES_FILE
    try:
        rows = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    best = next((v for k, v in rows.items() if k.startswith(BEST_SCRIPTED_LABEL)), None)
    if not isinstance(best, dict) or not best.get("reward", 0) > 0:
        return None
    return reward / best["reward"], float(best["reward"])


def finish_message(
    run_dir: Path,
    checkpoint: Path,
    frames: int,
    interrupted: bool,
    final: dict,
    outputs: dict | None = None,
    pending: bool = False,
) -> str:
    """What a newcomer needs at the end: what happened, where the results are (the files that
    exist, and the learning curve once ``outputs`` records it), what to run next (and, when the
    final outputs are ``pending``, which of them a resume writes)."""
    run_dir = Path(run_dir)
    lines = [f"{'stopped' if interrupted else 'done'}: {frames:,} env steps; run folder {run_dir}"]
    if final:
        lines.append(
            f"  final greedy evaluation: team reward {final['reward']:.1f}, task reward "
            f"{final['task_reward']:.1f}, picks {final['pick']:.1f}, defenses "
            f"{final['defense']:.1f} (reference policies: {REFERENCES_FILE})"
        )
        share = best_scripted_share(run_dir, final["reward"])
        if share is not None:
            lines.append(
                f"  {100 * share[0]:.0f} % of the best scripted team's reward on the same episodes "
                f"({share[1]:.1f}); the reports' yardstick is four quadrants: run next:"
            )
    metrics = [n for n in ("train.csv", "eval.csv", "timing.csv") if (run_dir / n).is_file()]
    curve = (outputs or {}).get("learning_curve", True) and (
        run_dir / "learning_curve.png"
    ).is_file()
    written = ([f"metrics: {', '.join(metrics)} (columns: docs/metrics.md)"] if metrics else []) + (
        ["figure: learning_curve.png"] if curve else []
    )
    if written:
        lines.append("  " + "; ".join(written))
    if Path(checkpoint).is_file():
        lines.append(f"  checkpoint: {checkpoint}")
    if interrupted:
        missing = [
            what
            for what, key in (
                ("the final evaluation", "final_evaluation"),
                ("the learning curve", "learning_curve"),
            )
            if pending and not (outputs or {}).get(key)
        ]
        todo = f" (writes {' and '.join(missing)})" if missing else ""
        lines.append(f"  continue: {shlex.join(['icco', 'train', f'resume={checkpoint}'])}{todo}")
    else:
        next_ = ["icco", "eval", f"checkpoint={checkpoint}", "eval.protocol=quadrants"]
        lines.append(f"  next: {shlex.join(next_)}")
    return "\n".join(lines)
