"""``train.collector``: where the env steps and the policy acts, inline or in a second process.

**inline** (the default): TorchRL's ``Collector`` in the learner's process; the trainer collects a
batch, then learns on it, in turn.

**process**: a collector process runs that same ``Collector`` beside the learner, so a run uses two
cores (:class:`ProcessCollector`).

- *Who does what.* The collector process builds the run from the same config and seed
  (:func:`~icco_torchrl.training.build.build`), so its env and policy (with any
  ``train.explore_guide``) are the learner's, and steps the env with it. The
  learner (the main process) cuts, stores and replays every batch, updates, evaluates and writes
  every file and checkpoint, exactly as inline.
- *Pacing: the replay ratio is inline's.* The collector collects the next batch while the learner
  updates on the current one, then waits: it never runs more than one batch ahead, and the learner
  does its ``train.updates_per_batch`` updates for every collected batch.
- *Weight sync and policy lag.* When the learner asks for batch k+1 (its updates on batch k done),
  it copies its policy weights into one shared-memory TensorDict and releases the collector, which
  loads them before it collects batch k+2. So batch k+1 is collected with the weights of the
  updates up to batch k-1: **one batch of updates older than inline's** (batches 1 and 2 both
  with the starting weights). Epsilon is not lagged: each release carries the value inline's
  schedule gives the batch the collector collects next.
- *Transfer.* Each batch is written into one shared-memory TensorDict, which the learner copies
  out before it releases the collector again.
- *Random streams.* The env's generator is the learner's at the start (the seed's, or the
  checkpoint's); the collector's torch stream is its own (``seed + COLLECTOR_SEED_OFFSET``, or the
  checkpoint's). Both come back with every batch, so a checkpoint holds them as of its last
  batch (``rng.env``, ``rng.collector_torch``) and a resume continues them.
- *Stops.* The collector process ignores SIGINT and SIGTERM (a terminal's Ctrl-C reaches both
  processes): the learner stops as inline does (its batch finished, a checkpoint saved) and then
  stops the collector, whose batch in flight is dropped and not counted. An error in the
  collector is raised in the learner as a one-line :class:`CollectorError` between batches (the
  trainer saves a checkpoint, then re-raises it); an error in the learner stops the collector on
  the way out. The collector also exits once the learner is gone (its pipe closed, or its parent
  changed).
- *A collector that hangs* (an env step that never returns) is not waited for without end: a batch
  that has not come :data:`FIRST_BATCH_WAIT_S` after the start (the process imports and builds the
  run), or later :data:`BATCH_WAIT_S` or :data:`BATCH_WAIT_FACTOR` times the slowest batch it
  collected (whichever is longer), is one :class:`CollectorError` line naming the process: the
  process is killed and the trainer saves a checkpoint of what the learner has. A stop (Ctrl-C,
  SIGTERM) while the learner waits for a batch is honoured at once: the wait changes nothing a
  checkpoint holds (:func:`~icco_torchrl.training.interrupt.abandonable`), and a collector still
  busy :data:`STOP_WAIT_S` after "stop" is killed (its batch would be dropped anyway).
"""

from __future__ import annotations

import atexit
import contextlib
import itertools
import logging
import os
import signal
import time
import traceback

import numpy as np
import torch
import torch.multiprocessing as mp
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector

from icco_torchrl.modules.policy import exploration_module
from icco_torchrl.training.build import build
from icco_torchrl.training.config import validate
from icco_torchrl.training.interrupt import abandonable

# The collector process's torch stream: cfg.seed + this (see build.VALIDATION_SEED_OFFSET).
COLLECTOR_SEED_OFFSET = 30_000
STOP_WAIT_S = 2.0  # a collector that has not exited this long after "stop" is killed
# How long the learner waits for a batch before it calls the collector stuck (see the module doc).
FIRST_BATCH_WAIT_S = 300.0  # the first: the process starts, imports torch and builds the run
BATCH_WAIT_S = 60.0  # any later one, at least
BATCH_WAIT_FACTOR = 20.0  # and at least this many times the slowest batch collected so far
_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class CollectorError(RuntimeError):
    """The collector process failed or exited: one line, what it raised and where."""


def inline_collector(env, policy, frames_per_batch: int, total_frames: int) -> Collector:
    """The trainer's TorchRL ``Collector`` (no trajectory ids: segments are cut on step_count, and
    the ids cost a td update per step)."""
    return Collector(
        env,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=total_frames,
        device=env.device,
        storing_device=env.device,
        auto_register_policy_transforms=False,
        track_traj_ids=False,
    )


def make_collector(run, cfg: DictConfig, total_frames: int, *, frames: int, epsilon, streams=None):
    """``train.collector``'s collector of ``total_frames`` for the built ``run``: inline, or a
    :class:`ProcessCollector` starting at ``frames``, exploring at ``epsilon(frames)``, with the
    collector's torch stream ``streams`` (a checkpoint's ``rng.collector_torch``; None: new)."""
    per_batch = cfg.env.num_envs * cfg.train.steps_per_batch
    if cfg.train.collector == "process":
        return ProcessCollector(
            cfg, run, per_batch, total_frames, frames=frames, epsilon=epsilon, torch_rng=streams
        )
    return inline_collector(run.env, run.policy, per_batch, total_frames)


@contextlib.contextmanager
def _signals_ignored():
    """SIGINT and SIGTERM ignored in a child started here (exec keeps an ignored disposition, and
    Python then installs no handler of its own), none of them lost here: they are blocked
    meanwhile and delivered to this process's own handlers after."""
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    previous = {}
    try:
        for sig in _SIGNALS:
            previous[sig] = signal.signal(sig, signal.SIG_IGN)
    except ValueError:  # not the main thread: the child ignores them as it starts
        pass
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


class ProcessCollector:
    """``train.collector=process``, seen from the learner: iterate it for the batches (``[envs,
    steps]``, as inline); :meth:`shutdown` stops the process. The process starts when iteration
    starts. After each batch, the learner's env generator holds the collector env's state and
    :attr:`torch_rng` the collector's torch stream (both as of that batch). ``epsilon(frames)``:
    the exploration rate of a batch collected from ``frames`` on (None: the policy's own)."""

    def __init__(
        self, cfg, run, frames_per_batch, total_frames, *, frames=0, epsilon=None, torch_rng=None
    ):
        self.cfg, self.run, self.per_batch = cfg, run, frames_per_batch
        # total_frames -1: endless, as TorchRL's Collector
        self.batches = total_frames // frames_per_batch if total_frames >= 0 else None
        self.total_frames, self.start_frames = total_frames, frames
        self.epsilon = epsilon or (lambda frames: float(exploration_module(run.policy).eps))
        self.released = 0  # releases sent: the collector holds (or collects) batch released + 1
        if torch_rng is None:
            torch_rng = torch.Generator().manual_seed(cfg.seed + COLLECTOR_SEED_OFFSET).get_state()
        self.torch_rng = torch_rng
        self.process = self.conn = self.weights = self.slot = None
        self.slowest = 0.0  # the longest a batch took the collector to collect, in seconds

    def __iter__(self):
        self._start()
        for _ in itertools.count() if self.batches is None else range(self.batches):
            self._release()
            yield self._receive()

    def _start(self) -> None:
        ctx = mp.get_context("spawn")  # fork is unsafe once torch has threads
        self.weights = TensorDict.from_module(self.run.policy).data.clone().share_memory_()
        config = OmegaConf.to_container(self.cfg, resolve=True)
        streams = {
            "env": self.run.env.base_env._rng.get_state().numpy(),
            "torch": self.torch_rng.numpy(),
            "epsilon": self.epsilon(self.start_frames),
        }
        self.conn, child = ctx.Pipe()
        self.process = ctx.Process(
            target=_collect,
            args=(config, self.weights, self.total_frames, streams),
            kwargs={"conn": child, "parent": os.getpid()},
            name="icco-collector",
            daemon=True,
        )
        with _signals_ignored():
            self.process.start()
        child.close()  # the child's end lives in the child only: its exit closes the pipe
        atexit.register(self.shutdown)

    def _release(self) -> None:
        """The learner's weights to the collector, which may then hand over its batch, and the
        exploration rate of the batch it collects next (inline's)."""
        self.weights.update_(TensorDict.from_module(self.run.policy).data)
        self.released += 1
        eps = self.epsilon(self.start_frames + self.released * self.per_batch)
        try:
            self.conn.send(("go", eps))
        except OSError:  # it is gone; _receive says why
            pass

    def _wait_limit(self) -> float:
        """How long the batch asked for may take before the collector is called stuck."""
        if self.slot is None:
            return FIRST_BATCH_WAIT_S
        return max(BATCH_WAIT_S, BATCH_WAIT_FACTOR * self.slowest)

    def _wait_for_batch(self) -> None:
        """Until the collector's next message is there (or it has exited). A stop signal cuts
        the wait short (nothing a checkpoint holds changes in it); a collector that sends nothing
        within :meth:`_wait_limit` is killed, and said in one line."""
        limit = self._wait_limit()
        deadline = time.monotonic() + limit
        with abandonable():
            while not self.conn.poll(0.2):
                if not self.process.is_alive():
                    return
                if time.monotonic() > deadline:
                    break
            else:
                return
        pid = self.process.pid
        self._kill()
        took = f"; its batches took at most {self.slowest:.1f} s" if self.slot is not None else ""
        raise CollectorError(
            f"the collector process icco-collector (pid {pid}) sent no batch for {limit:.0f} s "
            f"(batch {self.released}{took}): it is stuck, as in an env step that never returns; "
            "killed it"
        )

    def _receive(self) -> TensorDictBase:
        """The next batch (a copy), its random streams taken over."""
        try:
            self._wait_for_batch()
            message = self.conn.recv()
        except (EOFError, OSError):
            raise CollectorError(
                f"the collector process exited (code {self.process.exitcode}) without sending "
                f"its batch"
            ) from None
        if message[0] == "error":
            raise CollectorError(f"collector process failed: {message[1]}")
        _, slot, env_rng, torch_rng, seconds = message
        self.slowest = max(self.slowest, seconds)
        if slot is not None:
            self.slot = slot
        self.run.env.base_env._rng.set_state(torch.from_numpy(env_rng))
        self.torch_rng = torch.from_numpy(torch_rng)
        return self.slot.clone()

    def shutdown(self) -> None:
        """Stop the collector process (its batch in flight is dropped); kill it if it does not
        exit within ``STOP_WAIT_S``. Idempotent."""
        atexit.unregister(self.shutdown)
        process, self.process = self.process, None
        if process is None:
            return
        try:
            with contextlib.suppress(OSError):
                self.conn.send(("stop",))
            process.join(STOP_WAIT_S)
        finally:
            if process.is_alive():
                process.kill()
                process.join()
            self.conn.close()

    def _kill(self) -> None:
        """End the collector process now (a stuck one: its batch never comes)."""
        atexit.unregister(self.shutdown)
        process, self.process = self.process, None
        process.kill()
        process.join()
        self.conn.close()


# ---------------------------------------------------------------- the collector process
def _collect(config, weights, total_frames, streams, *, conn, parent) -> None:
    """The collector process's entry: :func:`_serve`, an error sent to the learner as one line
    (exit code 1, no traceback printed)."""
    for sig in _SIGNALS:  # the learner decides when this process stops
        signal.signal(sig, signal.SIG_IGN)
    try:
        _serve(config, weights, total_frames, streams, conn, parent)
    except BaseException as err:  # noqa: BLE001 - everything goes to the learner
        with contextlib.suppress(OSError):
            conn.send(("error", one_line(err)))
        raise SystemExit(1) from None
    finally:
        conn.close()


def _serve(config, weights, total_frames, streams, conn, parent) -> None:
    """Build, collect a batch ahead, and on each "go" load the weights and hand the batch over."""
    config["train"].update(compile=False, cudagraphs=False)  # this process never updates
    cfg = validate(OmegaConf.create(config))
    torch.set_num_threads(cfg.train.threads)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # as the learner's
    run = build(cfg, for_training=True)
    run.env.base_env._rng.set_state(torch.from_numpy(streams["env"]))
    torch.set_rng_state(torch.from_numpy(streams["torch"]))
    policy = TensorDict.from_module(run.policy).data
    explore = exploration_module(run.policy)
    policy.update_(weights)
    explore.eps.fill_(streams["epsilon"])
    per_batch = cfg.env.num_envs * cfg.train.steps_per_batch
    collector = inline_collector(run.env, run.policy, per_batch, total_frames)
    slot = None
    try:
        tick = time.perf_counter()
        for batch in collector:  # collected while the learner updates on the previous one
            seconds = time.perf_counter() - tick
            rng = (run.env.base_env._rng.get_state().numpy(), torch.get_rng_state().numpy())
            word, *eps = _wait(conn, parent)
            if word != "go":
                return
            policy.update_(weights)
            explore.eps.fill_(eps[0])  # for the next batch
            first = slot is None
            slot = batch.clone().share_memory_() if first else slot.update_(batch)
            conn.send(("batch", slot if first else None, *rng, seconds))
            tick = time.perf_counter()
    finally:
        collector.shutdown()


def _wait(conn, parent: int) -> tuple:
    """The learner's next message: ("go", epsilon) or ("stop",) (also once the learner is gone)."""
    while not conn.poll(1.0):
        if os.getppid() != parent:
            return ("stop",)
    try:
        return conn.recv()
    except (EOFError, OSError):
        return ("stop",)


def one_line(err: BaseException) -> str:
    """``Type: message (file:line)``, the innermost frame of the project (or the last), in one
    line."""
    frames = traceback.extract_tb(err.__traceback__)
    ours = [f for f in frames if "icco_torchrl" in f.filename] or frames
    where = f" ({os.path.basename(ours[-1].filename)}:{ours[-1].lineno})" if ours else ""
    message = " ".join(str(err).split()) or type(err).__name__
    return f"{type(err).__name__}: {message}{where}"
