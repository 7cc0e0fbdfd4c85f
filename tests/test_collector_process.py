"""``train.collector=process``: the env and the acting policy in a second process beside the
learner (icco_torchrl/training/collector_process.py).

What is equal to inline, and tested so: with a greedy policy, the process collector's batches are
inline's exactly (same env stream, same weights), once the weights the learner sends are applied
one batch later than inline applies them (the stated lag); a training run has inline's frames,
batches, updates and CSV rows. Its data after the first batches is not inline's (the lag, and the
collector's own torch stream), so that is not compared.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from conftest import run_cli

from icco_torchrl.trainer import train
from icco_torchrl.training import collector_process, config
from icco_torchrl.training.build import build
from icco_torchrl.training.checkpoint import load_checkpoint
from icco_torchrl.training.collector_process import (
    CollectorError,
    ProcessCollector,
    inline_collector,
)
from icco_torchrl.training.config import ConfigError, check_collector, compose_config
from icco_torchrl.training.replay_dump import load_replay

# Seconds-long runs: no reference or periodic evaluations, 8 envs x 16 steps = 128 frames a batch.
FAST = (
    "experiment=smoke",
    "logger.progress=false",
    "eval.references=[]",
    "train.eval_interval=0",
    "train.checkpoint_interval=0",
    "device=cpu",
)
PER_BATCH = 8 * 16


def _children(pid: int) -> dict[int, str]:
    """Live (not zombie) children of ``pid`` and their command lines, multiprocessing's resource
    tracker left out (it exits with the last process that holds its pipe)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        state, ppid = stat.rsplit(")", 1)[1].split()[:2]
        if int(ppid) == pid and state != "Z" and "resource_tracker" not in cmdline:
            found[int(entry.name)] = cmdline
    return found


def _gone(pids, timeout: float = 15.0) -> bool:
    """Every pid in ``pids`` ended (or a zombie) within ``timeout`` seconds."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        alive = [p for p in pids if _running(p)]
        if not alive:
            return True
        time.sleep(0.2)
    return False


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _nudged(run) -> None:
    """Other weights: every parameter of the acting networks moved."""
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in run.policy.parameters():
            p.add_(torch.randn(p.shape, generator=gen))


def test_greedy_batches_are_inline_ones_with_the_weights_one_batch_later():
    """The lag, exactly: weights changed after batch 1 act from batch 3 on in the process (from
    batch 2 inline); with that shift every batch and the env's stream are inline's."""
    greedy = ["method=qmix", "train.eps_init=0", "train.eps_end=0"]
    cfg = compose_config([*FAST, *greedy])
    torch.manual_seed(0)
    inline = build(cfg, for_training=True)
    torch.manual_seed(0)
    process = build(cfg, for_training=True)
    expected, streams = [], []
    collector = inline_collector(inline.env, inline.policy, PER_BATCH, 3 * PER_BATCH)
    for k, batch in enumerate(collector):
        expected.append(batch)
        streams.append(inline.env.base_env._rng.get_state())
        if k == 1:
            _nudged(inline)  # inline: batch 3 with the new weights
    collector.shutdown()
    asked = []  # the frames whose exploration rate the learner sends: those before each batch
    epsilon = lambda frames: asked.append(frames) or 0.0  # noqa: E731
    collector = ProcessCollector(cfg, process, PER_BATCH, 3 * PER_BATCH, epsilon=epsilon)
    try:
        got = []
        for k, batch in enumerate(collector):
            got.append(batch)
            assert torch.equal(process.env.base_env._rng.get_state(), streams[k])
            if k == 0:
                _nudged(process)  # sent with the release of batch 2: it acts in batch 3
    finally:
        collector.shutdown()
    assert collector.process is None and not _children(os.getpid())
    assert asked[:3] == [0, PER_BATCH, 2 * PER_BATCH]
    assert len(got) == 3
    for want, have in zip(expected, got):
        assert have.batch_size == want.batch_size == torch.Size([8, 16])
        assert set(have.keys(True, True)) == set(want.keys(True, True))
        assert (have == want).all()
    # The new weights did change what the policy does.
    assert not torch.equal(expected[2]["agents", "action"], got[0]["agents", "action"])


def test_cli_smoke_run_has_the_frames_batches_updates_and_rows_of_inline(tmp_path):
    """``icco train ... train.collector=process`` against the same run inline (in this process)."""
    budget = ["train.total_frames=1024", "seed=5"]
    proc = run_cli("train", *FAST, *budget, "train.collector=process", f"hydra.run.dir={tmp_path}")
    assert "done: 1,024 env steps" in proc.stdout
    train(compose_config([*FAST, *budget]), tmp_path / "inline")
    a = load_checkpoint(tmp_path / "inline" / "checkpoint.pt")
    b = load_checkpoint(tmp_path / "checkpoint.pt")
    assert (a["frames"], a["batches"], a["updates"]) == (b["frames"], b["batches"], b["updates"])
    assert b["frames"] == 1024 and b["updates"] > 0
    assert "collector_torch" in b["rng"] and "collector_torch" not in a["rng"]
    for name in ("train.csv", "timing.csv"):
        rows = [(d / name).read_text().splitlines() for d in (tmp_path / "inline", tmp_path)]
        assert [r.split(",")[0] for r in rows[0]] == [r.split(",")[0] for r in rows[1]], name


LONG = (*FAST, "train.collector=process")


@pytest.mark.fault
@pytest.mark.parametrize("sig, group", [(signal.SIGINT, True), (signal.SIGTERM, False)])
def test_a_signal_stops_both_processes_and_the_checkpoint_resumes(tmp_path, capsys, sig, group):
    """Ctrl-C reaches the whole process group (as from a terminal), SIGTERM the learner alone
    (timeout, docker): either way the learner saves its last batch and the collector exits."""
    cmd = [sys.executable, "-m", "icco_torchrl", "train", *LONG, "train.total_frames=10000000"]
    cmd.append(f"hydra.run.dir={tmp_path}")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        process_group=0,
    )  # fmt: skip
    try:
        deadline = time.time() + 120
        while time.time() < deadline and len(_rows(tmp_path / "train.csv")) < 3:
            time.sleep(0.2)
        children = _children(proc.pid)
        assert any("multiprocessing" in c for c in children.values()), children
        (os.killpg if group else os.kill)(proc.pid, sig)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, err[-2000:]
    assert f"interrupted by {signal.Signals(sig).name}" in out and "Traceback" not in err
    assert _gone(children), f"left running: {children}"
    ckpt = load_checkpoint(tmp_path / "checkpoint.pt")
    frames = ckpt["frames"]
    assert frames == ckpt["batches"] * PER_BATCH and frames >= 3 * PER_BATCH
    assert ckpt["replay_segments"] == load_replay_count(tmp_path)
    # Resume (in this process) to two batches past the stop: every frame counted once.
    cfg = compose_config(
        [*LONG, f"train.total_frames={frames + 2 * PER_BATCH}", f"resume={tmp_path}/checkpoint.pt"]
    )
    train(cfg, tmp_path)
    said = capsys.readouterr().out
    assert f"replay buffer restored: {ckpt['replay_segments']} segments" in said
    assert load_checkpoint(tmp_path / "checkpoint.pt")["frames"] == frames + 2 * PER_BATCH
    assert not _children(os.getpid())


def _rows(path: Path) -> list[str]:
    return path.read_text().splitlines()[1:] if path.exists() else []


def load_replay_count(run_dir: Path) -> int:
    """Segments in the run's replay dump."""
    cfg = compose_config(list(FAST))
    buffer = build(cfg, for_training=True).buffer
    load_replay(buffer, run_dir / "replay")
    return len(buffer)


class _FailsAtTheThirdBatch:
    """A collector whose third batch raises (in the collector process)."""

    def __init__(self, collector):
        self.collector = collector

    def __iter__(self):
        for k, batch in enumerate(self.collector):
            if k == 2:
                raise RuntimeError("injected collector failure")
            yield batch

    def shutdown(self):
        self.collector.shutdown()


def _failing_collect(*args, **kwargs):
    """The collector process's entry, with its collector failing at the third batch."""
    made = collector_process.inline_collector
    collector_process.inline_collector = lambda *a, **k: _FailsAtTheThirdBatch(made(*a, **k))
    collector_process._collect(*args, **kwargs)


def test_an_error_in_the_collector_is_one_line_and_the_checkpoint_resumes(tmp_path, monkeypatch):
    monkeypatch.setattr(collector_process, "_collect", _failing_collect)
    cfg = compose_config([*FAST, "train.total_frames=1024", "train.collector=process"])
    with pytest.raises(CollectorError) as err:
        train(cfg, tmp_path)
    message = str(err.value)
    assert "RuntimeError: injected collector failure" in message and "\n" not in message
    assert not _children(os.getpid())
    ckpt = load_checkpoint(tmp_path / "checkpoint.pt")
    assert ckpt["frames"] == 2 * PER_BATCH  # the two batches it delivered, learned from
    monkeypatch.undo()
    resumed = compose_config([*FAST, "train.total_frames=1024", f"resume={tmp_path}/checkpoint.pt"])
    train(resumed, tmp_path)
    assert load_checkpoint(tmp_path / "checkpoint.pt")["frames"] == 1024


# ---------------------------------------------------------------- bad input, before any work
def test_a_collector_process_on_one_core_is_refused_naming_the_field(tmp_path, monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})
    cfg = compose_config([*FAST, "train.collector=process"])
    with pytest.raises(ConfigError, match=r"^config field 'train.collector': .* may use 1") as err:
        train(cfg, tmp_path / "run")
    assert "\n" not in str(err.value) and not (tmp_path / "run").exists()
    check_collector(compose_config(list(FAST)), cores=1)  # inline needs one core


def test_a_collector_process_on_a_gpu_is_refused_naming_the_field(monkeypatch):
    monkeypatch.setattr(config, "resolve_device", lambda name: torch.device("cuda"))
    with pytest.raises(ConfigError, match=r"^config field 'train.collector': .* on the CPU"):
        check_collector(compose_config([*FAST, "train.collector=process"]), cores=2)


def test_the_collector_is_a_choice():
    with pytest.raises(ConfigError, match=r"^config field 'train.collector' must be one of"):
        compose_config([*FAST, "train.collector=thread"])


@pytest.mark.parametrize(
    "ratio, field",
    [(0.5, None), (1, "'train.updates_per_batch' (1) gives a replay ratio of 0.5"),
     (0.3, "'train.replay_ratio' (0.3) replays 38.4 transitions a batch of 128")],
)  # fmt: skip
def test_a_stated_replay_ratio_is_checked_naming_the_field(ratio, field):
    # smoke: 1 update of 4 x 16 transitions per 8 x 16 new ones, a replay ratio of 0.5.
    overrides = [*FAST, f"train.replay_ratio={ratio}"]
    if field is None:
        assert compose_config(overrides).train.replay_ratio == ratio
        return
    with pytest.raises(ConfigError) as err:
        compose_config(overrides)
    assert str(err.value).startswith(f"config field {field}") and "\n" not in str(err.value)
    assert compose_config(["train.replay_ratio=8"]).train.updates_per_batch == 8  # the default
