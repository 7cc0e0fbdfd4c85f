"""A training run's state in one place, as BenchMARL's ``Experiment`` has it: ``state_dict()`` is
a :class:`RunState`, everything a resume needs and exactly the checkpoint's fields (the checkpoint
is written from it), and ``load_state_dict()`` into a fresh run gives the same state and the same
next update."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

from icco_torchrl.trainer import TrainingRun
from icco_torchrl.training import checkpoint
from icco_torchrl.training.build import build
from icco_torchrl.training.checkpoint import FORMAT_VERSION, RunState, load_checkpoint
from icco_torchrl.training.config import compose_config
from icco_torchrl.training.logger import RunLogger
from icco_torchrl.training.replay_dump import load_replay
from icco_torchrl.training.run_folder import CheckpointError

torch.set_num_threads(1)
# No evaluation in the loop: the run collects, learns and checkpoints only.
SMOKE = ["experiment=smoke", "logger.progress=false", "train.eval_interval=0"]


def _training(run_dir, torch_seed: int) -> TrainingRun:
    """A run of the smoke config whose networks start from ``torch_seed``."""
    cfg = compose_config(SMOKE)
    torch.manual_seed(torch_seed)
    training = TrainingRun(build(cfg, for_training=True), cfg, run_dir)
    training.logger = RunLogger(run_dir, cfg, total_frames=cfg.train.total_frames)
    return training


def assert_same(a, b, where="state"):
    """``a`` and ``b`` hold equal values: tensors and arrays element for element."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype, where
        assert torch.equal(a, b), where
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and np.array_equal(a, b), where
    elif isinstance(a, RunState):
        assert isinstance(b, RunState), where
        assert_same(a.checkpoint(), b.checkpoint(), where)
    elif isinstance(a, dict):
        assert isinstance(b, dict) and sorted(a, key=str) == sorted(b, key=str), where
        for key in a:
            assert_same(a[key], b[key], f"{where}[{key!r}]")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def test_a_state_dict_loaded_into_a_fresh_run_gives_its_state_and_its_next_update(tmp_path):
    first = _training(tmp_path / "first", torch_seed=0)
    assert not first.loop(512)  # collected, stored and learned: every part of the state moved
    first.save()  # the checkpoint and the replay dump it names
    state = copy.deepcopy(first.state_dict())
    assert state.frames == 512 and state.updates > 0 and state.replay_segments > 0
    with pytest.raises(dataclasses.FrozenInstanceError):
        state.frames = 0
    # The checkpoint on disk is the state, field for field (and the format's version), and
    # reads back as it.
    ckpt = load_checkpoint(tmp_path / "first" / "checkpoint.pt")
    assert ckpt.pop("format_version") == FORMAT_VERSION
    assert_same(ckpt, state.checkpoint(), "checkpoint")
    assert_same(checkpoint.read(tmp_path / "first" / "checkpoint.pt"), state, "read")
    row = first.learn()  # the next update from the saved state
    after = copy.deepcopy(first.run.loss.state_dict())

    fresh = _training(tmp_path / "fresh", torch_seed=1)
    assert not all(torch.equal(v, after[k]) for k, v in fresh.run.loss.state_dict().items())
    load_replay(fresh.run.buffer, tmp_path / "first" / "replay")
    fresh.load_state_dict(state)
    assert_same(fresh.state_dict(), state)
    assert float(fresh.explore.eps) == pytest.approx(float(first.explore.eps))
    assert fresh.learn() == row  # the same next update: its metrics and the weights it leaves
    assert_same(fresh.run.loss.state_dict(), after, "weights after the update")


def test_a_state_of_other_networks_is_refused_in_one_line_naming_its_origin(tmp_path):
    training = _training(tmp_path, torch_seed=0)
    state = training.state_dict()
    state = dataclasses.replace(
        state, loss={k: v for k, v in state.loss.items() if "mixer" not in k}
    )
    with pytest.raises(CheckpointError) as info:
        training.load_state_dict(state, origin="run A's state")
    message = str(info.value)
    assert "\n" not in message and "run A's state" in message and "missing" in message
