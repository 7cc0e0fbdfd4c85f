"""Checkpoints and replay dumps that lose nothing: weights-only loads, checked dumps, no temps;
one plain line for every unreadable file, full disk, read-only folder, busy or mismatched run."""

from __future__ import annotations

import dataclasses
import errno
import importlib.util
import json
import os
import pickle
import subprocess
import sys
import tempfile

import numpy as np
import pytest
import torch
from conftest import ROOT
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer

from icco_torchrl.training import checkpoint, replay_dump, run_folder
from icco_torchrl.training.checkpoint import (
    FORMAT_VERSION,
    RunState,
    load_checkpoint,
    policy_of,
    restore_replay,
    save_checkpoint,
)
from icco_torchrl.training.config import MethodConfig
from icco_torchrl.training.replay_dump import load_replay, save_replay
from icco_torchrl.training.run_folder import (
    LOCK_FILE,
    CheckpointError,
    RunFolderBusy,
    RunFolderLock,
    fresh_outputs,
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
    assert "\n" not in str(info.value) and "a crafted or foreign file" in str(info.value)


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

    loaded = load_checkpoint(path, require=())
    assert loaded["format_version"] == FORMAT_VERSION
    assert loaded["cfg"] == payload["cfg"]  # as written: nothing is filled in on loading
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


def test_an_exported_policy_names_no_folder_of_the_machine_that_trained_it(tmp_path):
    """A resumed run's config holds the path it resumed from: the exported policy (shared, and
    committed beside the records) keeps the weights and every other field, and drops that path."""
    cfg = {
        "seed": 1,
        "resume": str(tmp_path / "run" / "checkpoint.pt"),
        "checkpoint": str(tmp_path / "other.pt"),
        "method": {"name": "icco", "hidden": 64},
    }
    state = {
        "cfg": cfg,
        "layout": {"n_agents": 3},
        "frames": 2048,
        "updates": 7,
        "optimizer": _optimizer_state(),
        "loss": {"w": torch.ones(2), "target_w": torch.zeros(2)},
    }
    path = save_checkpoint(tmp_path / "policy.pt", policy_of(state))  # what export_policy saves
    policy = load_checkpoint(path, require=())
    assert policy["cfg"] == {**cfg, "resume": None, "checkpoint": None}
    assert str(tmp_path) not in path.read_bytes().decode("latin-1")
    assert list(policy["loss"]) == ["w"] and "optimizer" not in policy and policy["policy_only"]
    assert state["cfg"]["resume"] == cfg["resume"]  # the run's own state keeps them


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
    assert load_replay(make_buffer(4), tmp_path / "replay") is None


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


# ---------------------------------------------------------------- unreadable checkpoints
def _text(path):
    path.write_text("epoch 1: loss 0.52\nepoch 2: loss 0.31\n")
    return "is not a checkpoint"


def _empty(path):
    path.write_bytes(b"")
    return "is empty"


def _only_a_format_version(path):
    torch.save({"format_version": FORMAT_VERSION}, path)
    return "lacks cfg, layout, loss"


def _a_dict_of_the_wrong_shape(path):
    torch.save({"format_version": FORMAT_VERSION, "cfg": 3, "layout": {}, "loss": {}}, path)
    return "its cfg has no method and env"


def _a_string_version(path):
    torch.save({"format_version": str(FORMAT_VERSION), "cfg": {}, "layout": {}, "loss": {}}, path)
    return f"its format_version is '{FORMAT_VERSION}', a str, where icco-torchrl writes an integer"


def _truncated(path):
    save_checkpoint(path, {"cfg": {}, "loss": {"w": torch.zeros(1000)}})
    path.write_bytes(path.read_bytes()[:700])
    return "truncated or damaged"


def _crafted_pickle(path):
    with open(path, "wb") as handle:
        pickle.dump(
            {"format_version": FORMAT_VERSION, "x": _Payload(path.with_suffix(".pwn"))}, handle
        )
    return "a crafted or foreign file"


def _crafted_torch_file(path):
    torch.save({"format_version": FORMAT_VERSION, "x": _Payload(path.with_suffix(".pwn"))}, path)
    return "a crafted or foreign file"


@pytest.mark.parametrize(
    "make",
    [
        _text,
        _empty,
        _only_a_format_version,
        _a_dict_of_the_wrong_shape,
        _a_string_version,
        _truncated,
        _crafted_pickle,
        _crafted_torch_file,
    ],
)
def test_every_unreadable_checkpoint_is_one_plain_line_naming_it(tmp_path, make, recwarn):
    path = tmp_path / "checkpoint.pt"
    said = make(path)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    message = str(info.value)
    assert said in message and str(path) in message and "\n" not in message, message
    assert "KeyError" not in message and "Weights only load failed" not in message
    assert not path.with_suffix(".pwn").exists()
    assert not [w for w in recwarn if "pickle protocol" in str(w.message)]


# ---------------------------------------------------------------- full disks, read-only folders
def _enospc_after(calls: int):
    """A ``write_all`` that writes ``calls`` times, then finds the disk full (half written)."""
    real, count = run_folder.write_all, [0]

    def write_all(fd, data):
        count[0] += 1
        if count[0] > calls:
            os.write(fd, memoryview(data).cast("B")[: max(1, len(memoryview(data)) // 2)])
            raise OSError(errno.ENOSPC, "No space left on device")
        real(fd, data)

    return write_all


def _temps(folder):
    return [p.name for p in folder.iterdir() if p.name.endswith(".tmp")]


def test_a_full_disk_in_the_checkpoint_write_is_one_line_and_keeps_the_old_one(
    tmp_path, monkeypatch
):
    path = save_checkpoint(tmp_path / "checkpoint.pt", {"frames": 1})
    monkeypatch.setattr(run_folder, "write_all", _enospc_after(0))
    with pytest.raises(CheckpointError) as info:
        save_checkpoint(path, {"frames": 2, "loss": {"w": torch.zeros(10_000)}})
    message = str(info.value)
    assert "\n" not in message and str(path) in message and "No space left" in message
    assert _temps(tmp_path) == []
    assert load_checkpoint(path, require=())["frames"] == 1


@pytest.mark.parametrize("where", ["mkstemp", "mkdtemp"])
def test_a_read_only_folder_is_one_line_naming_it(tmp_path, monkeypatch, where):
    def read_only(*args, dir=None, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system", str(dir))

    monkeypatch.setattr(tempfile, where, read_only)
    buffer = make_buffer(8)
    buffer.extend(segments(3))
    with pytest.raises(CheckpointError) as info:
        if where == "mkstemp":
            save_checkpoint(tmp_path / "checkpoint.pt", {"frames": 1})
        else:
            save_replay(buffer, tmp_path / "replay")
    message = str(info.value)
    assert "\n" not in message and str(tmp_path) in message and "Read-only" in message
    assert sorted(os.listdir(tmp_path)) == []


@pytest.mark.parametrize("how", ["checked first", "while writing"])
def test_a_full_disk_in_the_replay_dump_is_one_line_and_leaves_no_temp(tmp_path, monkeypatch, how):
    before = make_buffer(64)
    before.extend(segments(5))
    path = save_replay(before, tmp_path / "replay", dump_id="a")
    buffer = make_buffer(64)
    buffer.extend(segments(40))
    if how == "checked first":  # too little room for the dump: nothing is written
        monkeypatch.setattr(run_folder, "free_bytes", lambda folder: 1000)
    else:  # the disk fills up under the dump (plain writes: ENOSPC, never a SIGBUS)
        monkeypatch.setattr(run_folder, "write_all", _enospc_after(1))
    with pytest.raises(CheckpointError) as info:
        save_replay(buffer, path, dump_id="b")
    message = str(info.value)
    assert "\n" not in message and str(path) in message and "No space left" in message
    assert sorted(os.listdir(tmp_path)) == ["replay"]  # no temp folder, the previous dump kept
    restored = make_buffer(64)
    assert load_replay(restored, path) == path and len(restored) == 5


# ---------------------------------------------------------------- the run folder
def test_a_second_writer_of_a_run_folder_is_refused_in_one_line(tmp_path):
    with RunFolderLock(tmp_path):
        with pytest.raises(RunFolderBusy) as info:
            with RunFolderLock(tmp_path):
                pass
        message = str(info.value)
        assert "\n" not in message and str(tmp_path) in message
        assert f"pid {os.getpid()}" in message
    with RunFolderLock(tmp_path):  # released with its holder
        pass


@pytest.mark.parametrize("target", ["a file", "no file"])
def test_a_lock_file_that_is_a_link_is_refused_and_its_target_left_untouched(tmp_path, target):
    """A run folder received from elsewhere may hold a ``.train.lock`` that links anywhere: the
    lock is opened without following it (the target is neither truncated nor created)."""
    victim = tmp_path / "victim.txt"
    if target == "a file":
        victim.write_text("keep me\n")
    run = tmp_path / "run"
    run.mkdir()
    (run / LOCK_FILE).symlink_to(victim)
    with pytest.raises(RunFolderBusy) as info:
        with RunFolderLock(run):
            pass
    message = str(info.value)
    assert "\n" not in message and "is a symbolic link" in message and str(run) in message
    if target == "a file":
        assert victim.read_text() == "keep me\n"
    else:
        assert not victim.exists()
    assert (run / LOCK_FILE).is_symlink()
    fifo = tmp_path / "fifo"
    fifo.mkdir()
    os.mkfifo(fifo / LOCK_FILE)
    with pytest.raises(RunFolderBusy, match="is no plain file"):
        with RunFolderLock(fifo):
            pass


def _run_state(frames) -> RunState:
    """A run's state with a config of every method field of today's format, and no networks."""
    method = dataclasses.asdict(MethodConfig())
    return RunState(
        cfg={"method": method, "env": {}},
        layout={},
        frames=frames,
        updates=0,
        batches=1,
        loss={},
        optimizer={},
        updater={},
        rng={},
        outputs=fresh_outputs(),
        replay_id=None,
        replay_segments=0,
    )


def test_the_checkpoint_and_its_replay_dump_share_an_id(tmp_path):
    buffer = make_buffer(16)
    buffer.extend(segments(4))
    saved = checkpoint.save(tmp_path, _run_state(1), buffer)
    path = tmp_path / "checkpoint.pt"
    state = checkpoint.read(path)
    assert state == saved  # the state as written, field for field
    manifest = json.loads((tmp_path / "replay" / "manifest.json").read_text())
    assert state.replay_id == manifest["id"] and state.replay_segments == 4
    assert sorted(os.listdir(tmp_path)) == ["checkpoint.pt", "replay"]  # the previous dump dropped
    restored = make_buffer(16)
    said = restore_replay(restored, tmp_path, state, path)
    assert said == "replay buffer restored: 4 segments" and len(restored) == 4


def test_a_dump_newer_than_its_checkpoint_is_set_aside_for_the_matching_one(tmp_path):
    buffer = make_buffer(16)
    buffer.extend(segments(4))
    checkpoint.save(tmp_path, _run_state(1), buffer)
    path = tmp_path / "checkpoint.pt"
    buffer.extend(segments(6, 100))
    # What save writes before the checkpoint, then a kill before the checkpoint.
    save_replay(buffer, tmp_path / "replay", dump_id="newer", keep_previous=True)
    restored = make_buffer(16)
    said = restore_replay(restored, tmp_path, checkpoint.read(path), path)
    assert "\n" not in said and "replay buffer restored: 4 segments" in said
    assert "newer than" in said and "matches" in said
    assert len(restored) == 4 and restored.storage._storage["step_count"][:4, 0, 0].tolist() == [
        0,
        1,
        2,
        3,
    ]
    # Reconciled on disk: the matching dump is the run's replay/ again.
    assert sorted(os.listdir(tmp_path)) == ["checkpoint.pt", "replay"]
    assert (
        json.loads((tmp_path / "replay" / "manifest.json").read_text())["id"]
        == checkpoint.read(path).replay_id
    )


def test_a_dump_of_another_checkpoint_is_refused_in_one_line(tmp_path):
    buffer = make_buffer(16)
    buffer.extend(segments(4))
    checkpoint.save(tmp_path, _run_state(1), buffer)
    path = tmp_path / "checkpoint.pt"
    save_replay(buffer, tmp_path / "replay", dump_id="someone-else")  # e.g. copied from a run
    with pytest.raises(CheckpointError) as info:
        restore_replay(make_buffer(16), tmp_path, checkpoint.read(path), path)
    message = str(info.value)
    assert "\n" not in message and "someone-else" in message and str(path) in message
    assert f"delete {tmp_path / 'replay'}" in message


def test_a_checkpoint_without_a_field_of_the_run_state_is_refused_naming_the_converter(tmp_path):
    """A run's state is read whole: the record of its final outputs completes with what was not
    written; a file without a field of :class:`RunState` (written before it existed) is one line
    naming the converter, one without a training state (or an exported policy) one line too."""
    path, fields = tmp_path / "checkpoint.pt", _run_state(1).checkpoint()
    save_checkpoint(path, {**fields, "outputs": {"final_evaluation": True}})
    assert checkpoint.read(path).outputs == {**fresh_outputs(), "final_evaluation": True}
    without = {key: {k: v for k, v in fields.items() if k != key} for key in fields}
    for payload, said in (
        ({**fields, "outputs": None}, "its outputs record is no dict"),
        (without["outputs"], "before the run state's outputs existed: convert it with"),
        (without["replay_id"], f"{CONVERT} --in-place {path}"),
        (without["optimizer"], "cannot be resumed: it lacks the training state optimizer"),
        ({**fields, "policy_only": True}, "is an exported policy"),
    ):
        save_checkpoint(path, payload)
        with pytest.raises(CheckpointError, match=said) as info:
            checkpoint.read(path)
        assert "\n" not in str(info.value) and str(path) in str(info.value)


# ---------------------------------------------------------------- older formats: the converter
CONVERT = "python tools/convert_checkpoint.py"


def converter():
    """tools/convert_checkpoint.py as a module (a script outside the package)."""
    spec = importlib.util.spec_from_file_location(
        "convert_checkpoint", ROOT / "tools" / "convert_checkpoint.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _format_2(path, payload):
    """``payload`` as the writer of format 2 saved it (numpy arrays pickled as such)."""
    torch.save({"format_version": 2, **payload}, path)
    return path


@pytest.mark.parametrize("name", ["checkpoint.pt", "demo_icco.pt"])
def test_a_checkpoint_of_an_older_format_is_refused_in_one_line_naming_the_converter(
    tmp_path, name
):
    path = _format_2(tmp_path / name, {"cfg": {"method": {}, "env": {}}, "layout": {}, "loss": {}})
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    message = str(info.value)
    new = path.with_name(f"{path.stem}_v{FORMAT_VERSION}.pt")
    assert "\n" not in message and message.startswith(f"{path} has checkpoint format 2;")
    assert f"reads only format {FORMAT_VERSION}: convert it with {CONVERT} {path} {new}" in message
    assert (f"{CONVERT} --in-place {path}" in message) == (name == "checkpoint.pt")
    # the writer before weights-only files (numpy arrays pickled): named by what it refers to
    _format_2(path, {"rng": {"numpy": np.random.get_state()}})
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path, require=())
    message = str(info.value)
    assert "\n" not in message and "numpy" in message and f"{CONVERT} {path} {new}" in message
    torch.save({"format_version": FORMAT_VERSION + 1, "loss": {}}, path)
    with pytest.raises(CheckpointError, match="newer than the format .*: use the icco-torchrl"):
        load_checkpoint(path)


def _trained_with(tmp_path, **removed):
    """A format-2 checkpoint of real networks, written before the fields of the converter's tables
    were added (its config lacks them; its networks have no waypoint features and no LayerNorm, as
    then), with the ``removed`` options it was trained with; and the networks' state."""
    from icco_torchrl.training.build import build, compose_config

    tables = converter()
    cfg = compose_config(
        ["method=icco", "method.waypoint_features=false", "method.layer_norm=false"]
    )
    run = build(cfg, num_envs=2)
    old = OmegaConf.to_container(cfg, resolve=True)
    for key in tables.METHOD_FIELDS_ADDED:
        old["method"].pop(key, None)
    for key in tables.TRAIN_FIELDS_ADDED:
        old["train"].pop(key, None)
    old["method"].update(removed)
    state = {k: v.clone() for k, v in run.loss.state_dict().items()}
    payload = {"cfg": old, "layout": dict(run.layout.__dict__), "loss": state, "frames": 512}
    payload["rng"] = {"numpy": np.random.get_state()}  # a numpy array, pickled as such
    return _format_2(tmp_path / "old.pt", payload), state


def test_the_converter_fills_added_fields_drops_a_removed_option_and_keeps_the_networks(
    tmp_path, capsys
):
    from icco_torchrl.training.restore import restore

    tables = converter()
    old, state = _trained_with(tmp_path, z_input="head", reward_channels="team")
    before = old.read_bytes()
    new = tmp_path / "new.pt"
    assert tables.main([str(old), str(new)]) == 0
    said = capsys.readouterr().out
    assert f"{old} (format 2) -> {new} (format {FORMAT_VERSION})" in said
    assert "method.mixer='qmix'" in said and "method.z_input dropped" in said
    assert old.read_bytes() == before  # the source is left as it was
    ckpt = load_checkpoint(new)
    method, train = ckpt["cfg"]["method"], ckpt["cfg"]["train"]
    for added, fields in ((tables.METHOD_FIELDS_ADDED, method), (tables.TRAIN_FIELDS_ADDED, train)):
        assert {k: fields.get(k, v) for k, v in added.items()} == added  # at the old values
    assert method["waypoint_features"] is False and train["sequence_length"] == 4
    assert not set(tables.METHOD_FIELDS_REMOVED) & set(method)
    assert isinstance(ckpt["rng"]["numpy"][1], np.ndarray)  # stored as a tensor, read back
    torch.load(new, weights_only=True)  # no numpy object left in the file
    run = restore(new, num_envs=2)  # the same networks, every weight as trained
    restored = run.loss.state_dict()
    assert set(restored) == set(state) and all(torch.equal(restored[k], state[k]) for k in state)


def _policy_written_with(tmp_path, cfg, written: dict):
    """A policy of today's format with ``cfg``'s networks and the config ``written``; returns its
    path, its weights and, for each reader (load_checkpoint, restore), its one-line refusal."""
    from icco_torchrl.training.build import build
    from icco_torchrl.training.restore import restore

    run = build(cfg, num_envs=2)
    state = {k: v.clone() for k, v in run.loss.state_dict().items()}
    old = tmp_path / "policy.pt"
    payload = {"cfg": written, "layout": dict(run.layout.__dict__), "loss": state, "frames": 512}
    save_checkpoint(old, payload)
    messages = []
    for read in (load_checkpoint, lambda path: restore(path, num_envs=2)):
        with pytest.raises(CheckpointError) as info:
            read(old)
        messages.append(str(info.value))
        assert "\n" not in messages[-1] and f"{CONVERT} {old}" in messages[-1]
    return old, state, messages


def test_a_checkpoint_written_before_a_method_option_is_refused_then_converted_as_it_is(tmp_path):
    """A new method option needs no new format: a file of today's format whose config lacks the
    option (written before it existed) is refused in one line naming the converter, never read at
    today's default; the converter fills it at the value it trained with (its table's row)."""
    from icco_torchrl.training.build import compose_config
    from icco_torchrl.training.restore import restore

    cfg = compose_config(["method=icco", "method.layer_norm=false"])
    before = OmegaConf.to_container(cfg, resolve=True)
    del before["method"]["layer_norm"]  # as when layer_norm did not exist yet
    old, state, messages = _policy_written_with(tmp_path, cfg, before)
    for message in messages:
        assert f"{old} was written before method.layer_norm existed" in message
    new = tmp_path / "new.pt"
    assert converter().main([str(old), str(new)]) == 0
    ckpt = load_checkpoint(new)
    assert ckpt["format_version"] == FORMAT_VERSION and ckpt["cfg"]["method"]["layer_norm"] is False
    restored = restore(new, num_envs=2).loss.state_dict()  # the networks it was trained with
    assert set(restored) == set(state) and all(torch.equal(restored[k], state[k]) for k in state)


def test_a_checkpoint_with_a_removed_train_option_is_refused_then_converted_when_it_was_off(
    tmp_path, capsys
):
    """A file of today's format written while ``train.teacher`` existed (the demo policy's kind)
    is refused in one line naming the converter; converted, the option's fields are dropped when
    it was off, and a run that used it is refused naming the last commit that loads it."""
    from icco_torchrl.training.build import compose_config
    from icco_torchrl.training.restore import restore

    tables = converter()
    cfg = compose_config(["method=icco"])
    written = OmegaConf.to_container(cfg, resolve=True)
    written["train"].update(teacher=None, teacher_envs=8, teacher_share=0.25)
    old, state, messages = _policy_written_with(tmp_path, cfg, written)
    for message in messages:
        assert "train.teacher, train.teacher_envs, train.teacher_share" in message
    new = tmp_path / "new.pt"
    assert tables.main([str(old), str(new)]) == 0
    assert "train.teacher dropped (it was None, as today)" in capsys.readouterr().out
    assert not set(tables.TRAIN_FIELDS_REMOVED) & set(load_checkpoint(new)["cfg"]["train"])
    restored = restore(new, num_envs=2).loss.state_dict()
    assert set(restored) == set(state) and all(torch.equal(restored[k], state[k]) for k in state)

    written["train"]["teacher"] = "blend(defend=1.75)"
    old, _, _ = _policy_written_with(tmp_path, cfg, written)
    assert tables.main([str(old), str(tmp_path / "taught.pt")]) == 2
    err = capsys.readouterr().err.strip()
    commit = tables.TRAIN_FIELDS_REMOVED["teacher"][1]
    assert len(err.splitlines()) == 1 and "train.teacher='blend(defend=1.75)'" in err
    assert f"evaluate it at commit {commit}" in err and not (tmp_path / "taught.pt").exists()


def test_a_removed_env_parameter_is_refused_then_dropped_at_the_value_left(tmp_path, capsys):
    """``env.params.inst_reward`` (measured and not kept): a policy written with it is refused in
    one line naming the converter; converted, ``"cosine"`` (the one value left) is dropped from
    the env's and the training env's parameters; ``"progress"`` is refused naming the commit."""
    from icco_torchrl.training.build import compose_config
    from icco_torchrl.training.restore import restore

    tables = converter()
    cfg = compose_config(["method=icco"])
    written = OmegaConf.to_container(cfg, resolve=True)
    written["env"]["params"]["inst_reward"] = "cosine"
    written["train"]["env_params"]["inst_reward"] = None  # unset: the env's own
    old, state, messages = _policy_written_with(tmp_path, cfg, written)
    for message in messages:
        assert "env.params.inst_reward, train.env_params.inst_reward" in message
    new = tmp_path / "new.pt"
    assert tables.main([str(old), str(new)]) == 0
    said = capsys.readouterr().out
    assert "env.params.inst_reward dropped (it was 'cosine', as today)" in said
    ckpt = load_checkpoint(new)["cfg"]
    assert "inst_reward" not in ckpt["env"]["params"]
    assert "inst_reward" not in ckpt["train"]["env_params"]
    restored = restore(new, num_envs=2).loss.state_dict()
    assert set(restored) == set(state) and all(torch.equal(restored[k], state[k]) for k in state)

    written["train"]["env_params"]["inst_reward"] = "progress"
    old, _, _ = _policy_written_with(tmp_path, cfg, written)
    assert tables.main([str(old), str(tmp_path / "progress.pt")]) == 2
    err = capsys.readouterr().err.strip()
    commit = tables.ENV_FIELDS_REMOVED["inst_reward"][1]
    assert len(err.splitlines()) == 1 and "train.env_params.inst_reward='progress'" in err
    assert f"evaluate it at commit {commit}" in err and not (tmp_path / "progress.pt").exists()


@pytest.mark.parametrize(
    "option, value, commit",
    [("z_input", "mlp", "396580d"), ("reward_channels", "per_robot", "6ecb567")],
)
def test_the_converter_refuses_a_removed_option_at_another_value_in_one_line(
    tmp_path, capsys, option, value, commit
):
    tables = converter()
    old, _ = _trained_with(tmp_path, **{option: value})
    new = tmp_path / "new.pt"
    assert tables.main([str(old), str(new)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("convert_checkpoint: ")
    assert f"{old} was trained with method.{option}={value!r}" in err and commit in err
    assert not new.exists() and not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_the_converter_run_as_a_script_refuses_in_one_line_without_a_traceback(tmp_path):
    old = _format_2(tmp_path / "old.pt", {"cfg": {"method": {"z_input": "mlp"}}, "loss": {}})
    missing = tmp_path / "missing.pt"
    for args in ([old, tmp_path / "new.pt"], [missing, tmp_path / "x.pt"]):
        proc = subprocess.run(
            [sys.executable, "tools/convert_checkpoint.py", *map(str, args)],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1 and str(args[0]) in proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.pt"]


def test_a_run_converted_in_place_resumes_with_its_replay_dump(tmp_path):
    """A run of format 2 (its checkpoint written before the final outputs were recorded, its dump
    of replay format 2): loading either is one line naming the converter; converted in place, the
    checkpoint records its outputs (its learning curve exists) and the dump restores."""
    buffer = make_buffer(16)
    buffer.extend(segments(4))
    dump_id = checkpoint.save(tmp_path, _run_state(8), buffer).replay_id
    path = tmp_path / "checkpoint.pt"
    raw = torch.load(path, weights_only=True)
    raw.pop("outputs", None)
    torch.save({**raw, "format_version": 2}, path)
    manifest = tmp_path / "replay" / "manifest.json"
    manifest.write_text(json.dumps({**json.loads(manifest.read_text()), "format": 2}))
    (tmp_path / "learning_curve.png").write_bytes(b"png")
    with pytest.raises(CheckpointError, match=f"{CONVERT} --in-place {path}"):
        load_checkpoint(path)
    with pytest.raises(CheckpointError) as info:
        load_replay(make_buffer(16), tmp_path / "replay")
    message = str(info.value)
    assert "\n" not in message and "has format 2; this icco-torchrl reads only format" in message
    assert f"{CONVERT} --in-place {tmp_path}" in message
    assert f"delete {tmp_path / 'replay'}" in message

    assert converter().main(["--in-place", str(tmp_path)]) == 0
    state = checkpoint.read(path)
    assert state.outputs["learning_curve"] is True and state.replay_id == dump_id
    assert json.loads(manifest.read_text())["format"] == replay_dump.REPLAY_FORMAT
    restored = make_buffer(16)
    assert restore_replay(restored, tmp_path, state, path) == "replay buffer restored: 4 segments"
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        LOCK_FILE,
        "checkpoint.pt",
        "learning_curve.png",
        "replay",
    ]


def test_nothing_in_the_package_mentions_the_upgrade_tables():
    """The upgrade of older checkpoints lives in tools/convert_checkpoint.py only."""
    tables = (
        "METHOD_FIELDS_ADDED",
        "METHOD_FIELDS_REMOVED",
        "TRAIN_FIELDS_ADDED",
        "TRAIN_FIELDS_REMOVED",
        "ENV_FIELDS_REMOVED",
    )
    names = (*tables, "_upgrade", "legacy_numpy_globals", "safe_globals")
    found = [
        f"{path.relative_to(ROOT)}: {name}"
        for path in sorted((ROOT / "icco_torchrl").rglob("*.py"))
        for name in names
        if name in path.read_text()
    ]
    assert not found, found
    tool = (ROOT / "tools" / "convert_checkpoint.py").read_text()
    assert all(f"\n{name} = " in tool for name in tables)
