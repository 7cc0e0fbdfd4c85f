"""Checkpoints and replay dumps that lose nothing: weights-only loads, checked dumps, no temps."""

from __future__ import annotations

import json
import os
import pickle

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer

from icco_torchrl.training.checkpoint import (
    FORMAT_VERSION,
    CheckpointError,
    load_checkpoint,
    load_replay,
    save_checkpoint,
    save_replay,
)

pytestmark = pytest.mark.fault  # the fault suite: crafted, damaged and stale files

torch.set_num_threads(1)


# ---------------------------------------------------------------- checkpoints
class _Payload:
    """Unpickling this creates ``target``: what a crafted checkpoint could do with pickle."""

    def __init__(self, target):
        self.target = str(target)

    def __reduce__(self):
        return (open, (self.target, "w"))


@pytest.mark.parametrize("writer", ["torch.save", "pickle.dump"])
def test_a_crafted_checkpoint_runs_no_code(tmp_path, writer):
    target, path = tmp_path / "pwned", tmp_path / "evil.pt"
    payload = {"format_version": FORMAT_VERSION, "loss": {}, "x": _Payload(target)}
    if writer == "torch.save":
        torch.save(payload, path)
    else:
        with open(path, "wb") as handle:
            pickle.dump(payload, handle)
    assert not target.exists()
    with pytest.raises(CheckpointError, match=str(path)) as info:
        load_checkpoint(path)
    assert not target.exists(), "loading the checkpoint ran code from the file"
    assert "\n" not in str(info.value)


def _optimizer_state() -> dict:
    net = torch.nn.Linear(3, 2)
    optim = torch.optim.Adam(net.parameters(), lr=1e-3)
    net(torch.randn(4, 3)).sum().backward()
    optim.step()
    return optim.state_dict()


def test_a_checkpoint_round_trips_and_loads_weights_only(tmp_path):
    np.random.seed(5)
    torch.manual_seed(5)
    gen = torch.Generator().manual_seed(11)
    rng = {"torch": torch.get_rng_state(), "env": gen.get_state(), "numpy": np.random.get_state()}
    expected = (
        np.random.rand(4),
        torch.rand(4),
        torch.rand(4, generator=gen),
    )  # what the states produce
    payload = {
        "cfg": {
            "method": {"name": "icco", "hidden": 64},
            "eval": {"references": ["random"], "x": None},
        },
        "frames": 2048,
        "epsilon": 0.25,
        "optimizer": _optimizer_state(),
        "rng": rng,
        "scalars": [np.float64(1.5), np.int64(3)],
        "loss": {"w": torch.arange(6.0).view(2, 3)},
    }
    path = save_checkpoint(tmp_path / "checkpoint.pt", payload)
    torch.load(path, weights_only=True)  # no numpy object left in the file

    loaded = load_checkpoint(path)
    assert loaded["format_version"] == FORMAT_VERSION
    # method fields added after the checkpoint was written come back with the value it was trained
    # with
    from icco_torchrl.training.config import METHOD_FIELDS_ADDED

    assert loaded["cfg"] == {
        **payload["cfg"],
        "method": {**payload["cfg"]["method"], **METHOD_FIELDS_ADDED},
    }
    assert (
        loaded["cfg"]["method"]["waypoint_features"] is False
        and "z_input" not in loaded["cfg"]["method"]  # a removed option, at its one value
    )
    assert loaded["frames"] == 2048 and loaded["epsilon"] == 0.25
    assert loaded["scalars"] == [1.5, 3]
    assert torch.equal(loaded["loss"]["w"], payload["loss"]["w"])
    assert torch.equal(
        loaded["optimizer"]["state"][0]["exp_avg"], payload["optimizer"]["state"][0]["exp_avg"]
    )
    assert loaded["optimizer"]["param_groups"] == payload["optimizer"]["param_groups"]
    # The RNG states restore the very same streams (after the generators moved on).
    np.random.seed(0)
    torch.manual_seed(0)
    state = loaded["rng"]
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    gen.set_state(state["env"])
    assert isinstance(state["numpy"], tuple) and state["numpy"][1].dtype == np.uint32
    np.testing.assert_array_equal(np.random.rand(4), expected[0])
    assert torch.equal(torch.rand(4), expected[1]) and torch.equal(
        torch.rand(4, generator=gen), expected[2]
    )


def test_a_method_field_the_checkpoint_has_is_kept(tmp_path):
    payload = {"cfg": {"method": {"name": "icco", "waypoint_features": True}}, "loss": {}}
    loaded = load_checkpoint(save_checkpoint(tmp_path / "checkpoint.pt", payload))
    assert loaded["cfg"]["method"] == {"name": "icco", "waypoint_features": True}


def test_a_checkpoint_written_before_weights_only_loading_still_loads(tmp_path):
    path = tmp_path / "old.pt"
    state = np.random.get_state()
    torch.save(
        {"format_version": FORMAT_VERSION, "rng": {"numpy": state}}, path
    )  # the previous writer
    loaded = load_checkpoint(path)
    np.testing.assert_array_equal(loaded["rng"]["numpy"][1], state[1])


def test_stale_checkpoint_temp_files_are_removed(tmp_path):
    stale = tmp_path / ".checkpoint.pt.ab12cd_9.tmp"
    other = tmp_path / ".other.pt.ab12cd_9.tmp"
    stale.write_bytes(b"half a checkpoint")
    other.write_bytes(b"not ours")
    save_checkpoint(tmp_path / "checkpoint.pt", {"frames": 1})
    assert not stale.exists() and other.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [".other.pt.ab12cd_9.tmp", "checkpoint.pt"]


# ---------------------------------------------------------------- replay dumps
T, OBS = 4, 30  # segment length, observation features


def make_buffer(capacity: int) -> TensorDictReplayBuffer:
    return TensorDictReplayBuffer(
        storage=LazyTensorStorage(capacity), sampler=RandomSampler(), batch_size=4
    )


def segments(n: int, start: int = 0) -> TensorDict:
    """``n`` distinguishable segments: every entry of segment ``i`` encodes ``start + i``."""
    ids = torch.arange(start, start + n, dtype=torch.float32).view(n, 1, 1, 1)
    return TensorDict(
        {
            ("agents", "observation"): ids.expand(n, T, 3, OBS).clone(),
            ("agents", "z"): ids.expand(n, T, 3, 8).clone(),
            "step_count": ids.view(n, 1, 1).expand(n, T, 1).long().clone(),
        },
        [n, T],
    )


def dump_bytes(path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*.memmap"))


def test_a_replay_dump_is_sized_by_what_it_holds(tmp_path):
    small, full = make_buffer(1000), make_buffer(1000)
    small.extend(segments(10))
    full.extend(segments(1000))
    save_replay(small, tmp_path / "small")
    save_replay(full, tmp_path / "full")
    per_segment = dump_bytes(tmp_path / "full") / 1000
    assert dump_bytes(tmp_path / "small") == 10 * per_segment
    total = sum(f.stat().st_size for f in (tmp_path / "small").rglob("*") if f.is_file())
    assert total < 10 * per_segment + 20_000  # the rest is small JSON metadata


@pytest.mark.parametrize("written", [6, 13])  # part filled; wrapped around (cursor in the middle)
def test_a_replay_dump_restores_items_length_and_next_write_position(tmp_path, written):
    buffer = make_buffer(8)
    for start in range(0, written, 3):
        buffer.extend(segments(min(3, written - start), start))
    save_replay(buffer, tmp_path / "replay")
    restored = make_buffer(8)
    assert load_replay(restored, tmp_path / "replay")
    assert len(restored) == len(buffer) == min(written, 8)
    assert (restored.writer._cursor, restored.writer._write_count) == (
        buffer.writer._cursor,
        written,
    )
    n = len(buffer)
    assert (restored.storage._storage[:n] == buffer.storage._storage[:n]).all()
    # Further writes land in the same slots, and sampling draws the same segments.
    buffer.extend(segments(2, 100))
    restored.extend(segments(2, 100))
    assert (
        restored.storage._storage[: len(buffer)] == buffer.storage._storage[: len(buffer)]
    ).all()
    torch.manual_seed(0)
    a = buffer.sample()
    torch.manual_seed(0)
    b = restored.sample()
    assert torch.equal(a["agents", "observation"], b["agents", "observation"])


def test_a_smaller_buffer_keeps_the_newest_segments_in_order(tmp_path):
    buffer = make_buffer(8)
    for start in range(0, 13, 3):
        buffer.extend(
            segments(min(3, 13 - start), start)
        )  # holds segments 5..12, oldest at the cursor
    save_replay(buffer, tmp_path / "replay")
    smaller = make_buffer(5)
    load_replay(smaller, tmp_path / "replay")
    ids = smaller.storage._storage["step_count"][:, 0, 0].tolist()
    assert ids == [8, 9, 10, 11, 12] and smaller.writer._cursor == 0
    smaller.extend(segments(1, 13))
    assert smaller.storage._storage["step_count"][:, 0, 0].tolist() == [13, 9, 10, 11, 12]


def _truncate(path):
    file = path / "storage" / "agents" / "observation.memmap"
    with open(file, "r+b") as handle:
        handle.truncate(1000)
    return "storage/agents/observation.memmap"


def _delete(path):
    (path / "storage" / "agents" / "z.memmap").unlink()
    return "storage/agents/z.memmap"


def _flip_a_byte(path):
    file = path / "storage" / "step_count.memmap"
    data = bytearray(file.read_bytes())
    data[len(data) // 2] ^= 0xFF
    file.write_bytes(bytes(data))
    return "storage/step_count.memmap"


def _drop_manifest(path):
    (path / "manifest.json").unlink()
    return "manifest.json"


@pytest.mark.parametrize("damage", [_truncate, _delete, _flip_a_byte, _drop_manifest])
def test_a_damaged_replay_dump_is_refused_in_one_line_naming_the_file(tmp_path, damage):
    buffer = make_buffer(64)
    buffer.extend(segments(20))
    path = save_replay(buffer, tmp_path / "replay")
    name = damage(path)
    restored = make_buffer(64)
    with pytest.raises(CheckpointError) as info:
        load_replay(restored, path)
    message = str(info.value)
    assert "\n" not in message and name in message and f"delete {path}" in message
    assert len(restored) == 0


def test_no_replay_dump_is_not_an_error(tmp_path):
    assert load_replay(make_buffer(4), tmp_path / "replay") is False


def test_stale_replay_temp_folders_are_removed(tmp_path):
    def stale():
        folder = tmp_path / ".replay.k1ll3d_x.tmp"
        (folder / "storage").mkdir(parents=True)
        (folder / "storage" / "state.memmap").write_bytes(b"\0" * 100)
        return folder

    mine, theirs, other = stale(), tmp_path / ".replays.k1ll3d_x.tmp", tmp_path / ".replay.old.tmp"
    theirs.mkdir()
    other.mkdir()
    buffer = make_buffer(4)
    buffer.extend(segments(2))
    save_replay(buffer, tmp_path / "replay")
    assert not mine.exists() and theirs.exists() and other.exists()
    mine = stale()
    assert load_replay(make_buffer(4), tmp_path / "replay")
    assert not mine.exists() and theirs.exists() and other.exists()
    assert sorted(os.listdir(tmp_path)) == [".replay.old.tmp", ".replays.k1ll3d_x.tmp", "replay"]
    assert json.loads((tmp_path / "replay" / "manifest.json").read_text())["segments"] == 2
