"""Everything about checkpoints, in one place: writing and reading them, the run folder they live
in, what a resume may change, and the upgrades of older files.

- **Files.** A checkpoint holds only tensors and plain Python data and is read with
  ``torch.load(weights_only=True)``: a crafted file cannot run code. It is written atomically
  (temp file + rename). Any file that is not a readable checkpoint (empty, text, a crafted or
  foreign pickle, a dict without the fields a checkpoint has) is one :class:`CheckpointError`
  line naming the path; so is a write that fails (a full disk, a read-only folder), which leaves
  no temp file.
- **Replay dumps.** The filled part of the replay buffer as raw arrays (no pickle, no memory
  mapping while writing, so a full disk is an error, not a SIGBUS) with a checksummed manifest,
  so a damaged dump is refused instead of resuming on garbage.
- **The run folder.** ``icco train`` holds a lock on it (:class:`RunFolderLock`, a file opened
  without following links): a second writer is refused in one line. :func:`save_run` writes the
  dump, then the checkpoint naming the dump's id, and only then drops the previous dump, so a
  stop between the two writes leaves a dump that matches the checkpoint; :func:`restore_replay`
  picks it (and says so) or refuses a foreign one. The checkpoint also records whether the final
  evaluation and the learning curve were written (:func:`outputs_of`), so a resume writes what a
  stopped run left out.
- **Resume rules.** :func:`check_resumable`: what a resumed run cannot change, and whether the
  networks and env layout fit (:func:`check_compatible`, :func:`load_weights`).
- **Upgrades.** Fields added or removed since older checkpoints were written
  (:data:`METHOD_FIELDS_ADDED` ...), filled in by :func:`load_checkpoint`.
"""

from __future__ import annotations

import csv
import errno
import fcntl
import io
import json
import math
import os
import pickle
import re
import shutil
import stat
import tempfile
import uuid
import warnings
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from icco_torchrl.training.config import set_env_params, validate


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable, or does not match the requested config; or a run folder
    cannot be written."""


class RunFolderBusy(CheckpointError):
    """Another ``icco train`` holds the run folder's lock, or its lock file is not one this project
    may open (a link): the folder is left as it is."""


# 2: agent embeds the previous action with nn.Embedding, attention keys have no bias.
FORMAT_VERSION = 2
CHECKPOINT = "checkpoint.pt"  # a run's checkpoint, in its run folder
REPLAY_DIR = "replay"  # the replay buffer dump beside it (train.checkpoint_buffer)
LOCK_FILE = ".train.lock"  # held by the icco train writing the folder
REFERENCES_FILE = "references.json"  # the reference policies' evaluation, beside eval.csv

# What an exported policy keeps (:func:`export_policy`); with ``loss``, what every checkpoint has.
POLICY_KEYS = ("format_version", "cfg", "layout", "frames", "updates")
# What a resume needs beyond that.
TRAINING_KEYS = ("optimizer", "updater", "batches", "rng")

# numpy arrays (the RNG state of ``np.random.get_state()``) are stored as tensors under this tag.
_NDARRAY = "__ndarray__"

# ---------------------------------------------------------------- upgrades of older checkpoints
# Method fields added after checkpoints had been written, with the value those older checkpoints
# were trained with (not today's default, which may differ): load_checkpoint fills them in, so an
# older checkpoint (the demo policy, a committed result) restores the networks it was trained with.
METHOD_FIELDS_ADDED = {
    "waypoint_features": False,
    "mixer": "qmix",
    "posterior_input": "flat",
    "broadcast_threshold": 0.0,
}
# Options measured and dropped from the library, with the only value it still builds: a checkpoint
# trained with another value is refused in one line naming the commit that can load it.
METHOD_FIELDS_REMOVED = {"instruction_head": False, "z_input": "head"}
# Train fields added after checkpoints had been written, with the value those runs trained with:
# a resumed older run keeps its recipe (4-step items, no shaping) instead of today's defaults.
TRAIN_FIELDS_ADDED = {
    "sequence_length": 4,
    "burn_in": 0,
    "shaping": {"potentials": [], "weight": 0.3},
}
REMOVED_AT = "396580d"


def _upgrade(payload: dict, path: Path) -> dict:
    """``payload``'s config with the fields added since it was written (at the values it was
    trained with); an option removed since is refused in one line."""
    train = payload.get("cfg", {}).get("train")
    if isinstance(train, dict):
        for key, value in TRAIN_FIELDS_ADDED.items():  # added later: it trained the old way
            train.setdefault(key, value)
    method = payload.get("cfg", {}).get("method")
    if isinstance(method, dict):
        for key, value in METHOD_FIELDS_ADDED.items():  # added later: it had the old behaviour
            method.setdefault(key, value)
        for key, value in METHOD_FIELDS_REMOVED.items():  # dropped options: only one value loads
            if method.pop(key, value) != value:
                raise CheckpointError(
                    f"{path} was trained with method.{key}, an option removed from icco-torchrl; "
                    f"evaluate it at commit {REMOVED_AT}"
                )
    return payload


# ---------------------------------------------------------------- writing files
def _temp_pattern(name: str) -> re.Pattern:
    """Names of the temp files/folders made by
    ``tempfile.mk*temp(prefix=f".{name}.", suffix=".tmp")``."""
    return re.compile(rf"\.{re.escape(name)}\.[a-z0-9_]{{8}}\.tmp")


def _remove_stale_temps(path: Path) -> None:
    """Delete temp files/folders of ``path`` left by a process killed while writing it."""
    pattern = _temp_pattern(path.name)
    if not path.parent.is_dir():
        return
    for entry in path.parent.iterdir():
        if pattern.fullmatch(entry.name):
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)


def _write_all(fd: int, data) -> None:
    """Write every byte of ``data`` to ``fd`` (plain ``write`` calls: a full disk raises ENOSPC)."""
    view = memoryview(data).cast("B")
    while view:
        view = view[os.write(fd, view[: 1 << 24]) :]


def _free_bytes(folder: Path) -> int:
    """Free space in ``folder`` for this user."""
    return shutil.disk_usage(folder).free


def _cannot_write(what: str, path: Path, err: OSError) -> CheckpointError:
    """One line for a failed write: a full disk, a read-only folder, no permission."""
    reason = err.strerror or str(err) or type(err).__name__
    hint = {
        errno.ENOSPC: "free some space and run again",
        errno.EDQUOT: "free some space and run again",
        errno.EROFS: "write the run to a writable folder",
        errno.EACCES: "write the run to a folder you may write",
        errno.EPERM: "write the run to a folder you may write",
    }.get(err.errno, "check the folder and run again")
    return CheckpointError(f"cannot write {what} {path}: {reason}; {hint}")


def _to_plain(obj):
    """``obj`` with numpy arrays and scalars as tensors and Python scalars (weights-only)."""
    if isinstance(obj, dict):
        return {k: _to_plain(v) for k, v in obj.items()}
    if type(obj) in (
        list,
        tuple,
    ):  # not namedtuples: they are classes, which a checkpoint never holds
        return type(obj)(_to_plain(v) for v in obj)
    if isinstance(obj, np.ndarray):
        return {_NDARRAY: torch.from_numpy(np.array(obj, copy=True))}
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _from_plain(obj):
    """Inverse of :func:`_to_plain`: tagged tensors back to numpy arrays."""
    if isinstance(obj, dict):
        if set(obj) == {_NDARRAY} and isinstance(obj[_NDARRAY], torch.Tensor):
            return obj[_NDARRAY].numpy()
        return {k: _from_plain(v) for k, v in obj.items()}
    if type(obj) in (
        list,
        tuple,
    ):  # not namedtuples: they are classes, which a checkpoint never holds
        return type(obj)(_from_plain(v) for v in obj)
    return obj


def save_checkpoint(path: str | Path, payload: dict[str, Any]) -> Path:
    """Write ``payload`` so that a crash never leaves a half-written file at ``path``.

    The file is serialised in memory first and written with plain writes, so a full disk or a
    read-only folder is one :class:`CheckpointError` line naming ``path``, and no temp file is
    left behind."""
    path = Path(path)
    buffer = io.BytesIO()
    torch.save(_to_plain({"format_version": FORMAT_VERSION, **payload}), buffer)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        _remove_stale_temps(path)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        try:
            _write_all(fd, buffer.getbuffer())
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError as err:
        raise _cannot_write("checkpoint", path, err) from None
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
    return path


# ---------------------------------------------------------------- reading files
def _one_line(err: Exception) -> str:
    """The informative line of an exception message (torch's weights-only errors span a page)."""
    text = str(err)
    marker = re.search(r"WeightsUnpickler error:?\s*(\S[^\n]*)", text)
    if marker:
        return marker.group(1).strip()
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return (lines or [type(err).__name__])[0][:200]


def _legacy_numpy_globals() -> list:
    """What checkpoints written before the weights-only format need: numpy's ndarray rebuild.

    ``_reconstruct`` builds an empty array of an allow-listed class and ``ndarray.__setstate__``
    fills it from raw bytes; nothing else is allowed, so these run no code of the file's choosing.
    """
    core = getattr(np, "_core", None) or np.core
    return [core.multiarray._reconstruct, np.ndarray, np.dtype, type(np.dtype(np.uint32))]


def _load_weights_only(path: Path, map_location) -> Any:
    """``torch.load(weights_only=True)``; files of the previous writer also need numpy's array
    rebuild (see :func:`_legacy_numpy_globals`), allowed for this call only. torch's warnings
    about a file's pickle protocol are not the user's business: the error, if any, is."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return torch.load(path, map_location=map_location, weights_only=True)
        except Exception as err:
            if "numpy" not in str(err) or "GLOBAL" not in str(err):
                raise
        with torch.serialization.safe_globals(_legacy_numpy_globals()):
            return torch.load(path, map_location=map_location, weights_only=True)


def _refused_by_the_unpickler(err: Exception) -> bool:
    """The weights-only unpickler rejected the file's content (a global, an opcode, a class),
    whatever torch's wording of the day: the file is a pickle, but not one of tensors and plain
    data."""
    text = str(err)
    return isinstance(err, pickle.UnpicklingError) or bool(
        re.search(r"weights.only|WeightsUnpickler|Unsupported (global|operand|class)", text, re.I)
    )


def _read_error(path: Path, err: Exception) -> CheckpointError:
    """One plain line for a file ``torch.load`` could not read."""
    with open(path, "rb") as handle:
        head = handle.read(4)
    if head.startswith(b"PK\x03\x04") and not _refused_by_the_unpickler(err):
        return CheckpointError(
            f"checkpoint {path} is truncated or damaged ({type(err).__name__}: {_one_line(err)}): "
            "use an earlier copy, or train again"
        )
    if head.startswith(b"PK") or head[:1] == b"\x80":  # a zip archive of torch.save, or a pickle
        unsafe = re.search(r"GLOBAL (\S+)", str(err))
        what = (
            f"refers to {unsafe.group(1)}, which a checkpoint never holds"
            if unsafe
            else (f"holds something a checkpoint never holds ({_one_line(err)})")
        )
        return CheckpointError(
            f"checkpoint {path} {what}: refusing to load it (a crafted or foreign file)"
        )
    return CheckpointError(
        f"{path} is not a checkpoint: it is not a file torch.save writes (a text file, or another "
        "format); give the run's checkpoint.pt"
    )


def load_checkpoint(
    path: str | Path, map_location="cpu", *, require: tuple[str, ...] = ("cfg", "layout", "loss")
) -> dict[str, Any]:
    """The checkpoint at ``path``, upgraded to today's config fields (:func:`_upgrade`).

    Anything else (a missing, empty, truncated, text, crafted or foreign file, another format, a
    dict without the ``require``d fields) is one :class:`CheckpointError` line naming ``path``."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    if path.stat().st_size == 0:
        raise CheckpointError(f"checkpoint {path} is empty (a write that never finished)")
    try:
        payload = _load_weights_only(path, map_location)
    except Exception as err:  # torch raises several types for truncated/corrupt/crafted files
        raise _read_error(path, err) from None
    if not isinstance(payload, dict) or "format_version" not in payload:
        raise CheckpointError(f"{path} is not an icco-torchrl checkpoint")
    version = payload["format_version"]
    if type(version) is not int:  # "2" or 2.0: not a number this project ever wrote
        raise CheckpointError(
            f"{path} is not an icco-torchrl checkpoint: its format_version is {version!r}, a "
            f"{type(version).__name__}, where icco-torchrl writes an integer ({FORMAT_VERSION})"
        )
    if version != FORMAT_VERSION:
        raise CheckpointError(
            f"{path} has checkpoint format {payload['format_version']}; this version of "
            f"icco-torchrl reads format {FORMAT_VERSION} (the networks changed): retrain, or "
            "evaluate it with the release that wrote it"
        )
    missing = [key for key in require if key not in payload]
    if missing:
        raise CheckpointError(
            f"{path} is not a complete icco-torchrl checkpoint: it lacks {', '.join(missing)}"
        )
    cfg = payload.get("cfg")
    if "cfg" in require and not (
        isinstance(cfg, dict) and all(isinstance(cfg.get(k), dict) for k in ("method", "env"))
    ):
        raise CheckpointError(
            f"{path} is not a complete icco-torchrl checkpoint: its cfg has no method and env"
        )
    if "loss" in require and not isinstance(payload["loss"], dict):
        raise CheckpointError(f"{path} is not a complete icco-torchrl checkpoint: loss is no dict")
    return _upgrade(_from_plain(payload), path)


# ---------------------------------------------------------------- resume rules
def load_weights(loss, state_dict: dict, path: str | Path, method: str) -> None:
    """``loss.load_state_dict`` with a one-line error when the networks do not match.

    Names and shapes are compared first: ``TensorDictParams`` (TorchRL's functional parameters)
    silently skips missing entries in ``load_state_dict``, which would leave networks half loaded.
    """
    expected = {k: tuple(v.shape) for k, v in loss.state_dict().items()}
    given = {k: tuple(getattr(v, "shape", ())) for k, v in state_dict.items()}
    missing, unexpected = sorted(set(expected) - set(given)), sorted(set(given) - set(expected))
    reshaped = sorted(k for k in set(expected) & set(given) if expected[k] != given[k])
    if missing or unexpected or reshaped:
        raise CheckpointError(
            f"checkpoint {path} does not match the {method} networks: missing {missing[:4]}, "
            f"unexpected {unexpected[:4]}, other shapes {reshaped[:4]}"
        )
    try:
        loss.load_state_dict(state_dict)
    except (RuntimeError, KeyError) as err:
        raise CheckpointError(
            f"checkpoint {path} does not match the {method} networks: {err}"
        ) from None


def policy_weights(ckpt: dict, loss) -> dict:
    """The weights ``loss`` loads from ``ckpt``: an exported policy (:func:`export_policy`) has no
    target copies, so its online weights stand in for them."""
    weights = ckpt["loss"]
    if not ckpt.get("policy_only"):
        return weights
    targets = loss.state_dict()
    return {**weights, **{f"target_{k}": v for k, v in weights.items() if f"target_{k}" in targets}}


def export_policy(src: str | Path, dst: str | Path) -> Path:
    """A small weights-only checkpoint of ``src`` for acting, not for training: the networks without
    their target copies, the optimiser, the RNG state or the replay bookkeeping (about half the
    size). :func:`~icco_torchrl.training.restore.restore` loads it like any checkpoint;
    ``resume=`` cannot continue from it."""
    ckpt = load_checkpoint(src)
    slim = {k: ckpt[k] for k in POLICY_KEYS if k in ckpt}
    slim["loss"] = {k: v for k, v in ckpt["loss"].items() if not k.startswith("target_")}
    slim["policy_only"] = True
    return save_checkpoint(dst, slim)


def check_compatible(ckpt: dict[str, Any], cfg, layout, path: str | Path) -> None:
    """The one check that a checkpoint's weights fit what ``cfg`` builds for an env of ``layout``:
    the method's fields (its name and label aside: sizes, encoders, coordinator) and the observation
    layout (robot, resource, invader and waypoint counts) must be the checkpoint's. Used by
    ``resume=`` and by :func:`~icco_torchrl.training.restore.restore`; raises one
    ``CheckpointError`` naming every difference."""
    cfg = cfg if isinstance(cfg, dict) else OmegaConf.to_container(cfg, resolve=True)
    # ``ckpt`` comes from load_checkpoint, which filled in the method fields added since it was
    # written.
    saved_m, m = ckpt["cfg"]["method"], cfg["method"]
    method = [
        f"method.{key}: checkpoint {saved_m.get(key)!r} vs config {m.get(key)!r}"
        for key in sorted(set(saved_m) | set(m))
        if key not in ("name", "label") and saved_m.get(key) != m.get(key)
    ]
    saved_layout = ckpt.get("layout") or {}
    shape = [
        f"{key}: checkpoint {value} vs env {getattr(layout, key)}"
        for key, value in saved_layout.items()
        if value != getattr(layout, key)
    ]
    problems = (
        [f"was trained with an incompatible config: {'; '.join(method)}"] if method else []
    ) + ([f"was trained for another env layout: {'; '.join(shape)}"] if shape else [])
    if problems:
        raise CheckpointError(f"checkpoint {path} " + ", and ".join(problems))


def check_resumable(ckpt: dict, cfg: DictConfig, layout, path: str | Path) -> None:
    """Refuse, in one line, a checkpoint this config cannot continue: an exported policy, one
    without the training state, a command line that changes what a resumed run cannot honour
    (:func:`check_resume_overrides`) or networks and env layout that differ
    (:func:`check_compatible`). A new ``train.env_params`` is allowed (a shaping curriculum), and
    said: the replayed data keeps the old rewards."""
    if ckpt.get("policy_only"):
        raise CheckpointError(
            f"{path} is an exported policy (no optimiser, targets or RNG state): "
            f"resume from the run's own checkpoint.pt"
        )
    missing = [key for key in TRAINING_KEYS if key not in ckpt]
    if missing:
        raise CheckpointError(
            f"{path} cannot be resumed: it lacks the training state {', '.join(missing)}"
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


# ---------------------------------------------------------------- the run folder
class RunFolderLock:
    """An exclusive lock on a run folder (``flock`` on :data:`LOCK_FILE`), held while ``icco train``
    writes it: a second writer (two resumes of one checkpoint, two runs given one
    ``hydra.run.dir``) is refused in one line instead of both writing the same files. The lock
    goes with the process, however it ends; the file stays (deleting it would race).

    The lock file is opened without following links: in a run folder received from elsewhere a
    ``.train.lock`` that is a symbolic link (or no plain file) is refused in one line, and whatever
    it points to is left untouched."""

    def __init__(self, run_dir: str | Path):
        self.run_dir = Path(run_dir)
        self._fd: int | None = None

    def __enter__(self) -> RunFolderLock:
        path = self.run_dir / LOCK_FILE
        flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, flags, 0o644)
        except OSError as err:
            if err.errno == errno.ELOOP:  # O_NOFOLLOW met a link
                raise self._not_a_lock_file("a symbolic link") from None
            raise _cannot_write("the run folder", self.run_dir, err) from None
        if not stat.S_ISREG(os.fstat(fd).st_mode):  # a FIFO or a device: not ours to write
            os.close(fd)
            raise self._not_a_lock_file("no plain file")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise RunFolderBusy(
                f"run folder {self.run_dir} is in use by another icco train (pid {holder}): "
                "wait for it to end, or stop it first"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def _not_a_lock_file(self, what: str) -> RunFolderBusy:
        return RunFolderBusy(
            f"run folder {self.run_dir}: its {LOCK_FILE} is {what}, not a lock file; refusing to "
            f"open it: delete {self.run_dir / LOCK_FILE} and run again"
        )

    def __exit__(self, *exc) -> None:
        if self._fd is not None:
            os.close(self._fd)  # releases the lock
            self._fd = None


def fresh_outputs() -> dict:
    """What a run has written after its last frame: nothing yet."""
    return {"final_evaluation": False, "final_metrics": {}, "learning_curve": False}


def outputs_of(ckpt: dict, run_dir: str | Path) -> dict:
    """Whether the final evaluation (and its metrics) and the learning curve of the checkpoint's
    last frame were written. Checkpoints written before this was recorded count as complete when
    their learning curve exists."""
    if isinstance(ckpt.get("outputs"), dict):
        return {**fresh_outputs(), **ckpt["outputs"]}
    done = (Path(run_dir) / "learning_curve.png").is_file()
    return {**fresh_outputs(), "final_evaluation": done, "learning_curve": done}


def last_evaluation(run_dir: str | Path, frames: int) -> dict | None:
    """The metrics of ``eval.csv``'s last row when it is at ``frames`` (a stopped run's evaluation
    of its last frame), else None."""
    path = Path(run_dir) / "eval.csv"
    if not path.is_file():
        return None
    with path.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    if not rows or not rows[-1].get("frames") or float(rows[-1]["frames"]) != frames:
        return None
    out = {}
    for key, value in rows[-1].items():
        try:
            out[key] = float(value)
        except (TypeError, ValueError):
            out[key] = math.nan
    out.pop("frames", None)
    return out


def save_run(
    run_dir: str | Path, payload: dict, buffer=None, *, replay_id: str | None = None
) -> tuple[Path, str | None]:
    """The run's checkpoint, and with ``buffer`` a new replay dump first; returns the checkpoint's
    path and the dump's id. Without ``buffer`` the checkpoint names ``replay_id`` (the dump on
    disk, unchanged).

    The dump replaces the previous one but keeps it (``.replay.old``) until the checkpoint naming
    the new one is written: a stop between the two writes leaves the previous dump, which matches
    the checkpoint on disk (:func:`restore_replay`)."""
    run_dir = Path(run_dir)
    dump = run_dir / REPLAY_DIR
    segments = None
    if buffer is not None:
        replay_id = uuid.uuid4().hex[:16]
        save_replay(buffer, dump, dump_id=replay_id, keep_previous=True)
        segments = len(buffer)
    payload = {**payload, "replay_id": replay_id}
    if segments is not None:
        payload["replay_segments"] = segments
    payload.setdefault("replay_segments", 0)
    path = save_checkpoint(run_dir / CHECKPOINT, payload)
    if buffer is not None:
        shutil.rmtree(_previous(dump), ignore_errors=True)  # no checkpoint names it any more
    return path, replay_id


def restore_replay(buffer, run_dir: str | Path, ckpt: dict, path: str | Path) -> str | None:
    """Refill ``buffer`` from the dump that checkpoint ``ckpt`` (read from ``path``) was saved
    with, and return the line that says what happened (None when it saved no buffer).

    The dump and the checkpoint share an id. A dump written after the checkpoint (a stop between
    the two writes) is set aside for the previous one, which matches, and said; a dump matching
    neither is refused in one line."""
    if not ckpt.get("replay_segments"):
        return None
    dump = Path(run_dir) / REPLAY_DIR
    _remove_stale_temps(dump)
    expected = ckpt.get("replay_id")
    if expected is None:  # written before dumps had ids
        return _restored(buffer, dump, load_replay(buffer, dump), run_dir)
    previous = _previous(dump)
    if _dump_id(dump) == expected:
        return _restored(buffer, dump, load_replay(buffer, dump), run_dir)
    if _dump_id(previous) == expected:
        newer = dump.is_dir()
        shutil.rmtree(dump, ignore_errors=True)
        os.replace(previous, dump)
        load_replay(buffer, dump)
        note = (
            f"{dump} was newer than {path} (a stop between the dump and the checkpoint): "
            f"set aside for the previous dump, which matches"
            if newer
            else f"the dump matching {path} was being swapped in: completed"
        )
        return f"replay buffer restored: {len(buffer)} segments ({note})"
    if dump.is_dir() or previous.is_dir():
        found = dump if dump.is_dir() else previous
        raise CheckpointError(
            f"replay buffer dump {found} (id {_dump_id(found)}) is not the one {path} was saved "
            f"with (id {expected}): delete {found} to resume with an empty buffer"
        )
    return _restored(buffer, dump, None, run_dir)


def _restored(buffer, dump: Path, loaded: Path | None, run_dir) -> str:
    if loaded is None:
        return f"no replay buffer dump in {run_dir}: resuming with an empty buffer (warm-up again)"
    return f"replay buffer restored: {len(buffer)} segments"


def _previous(dump: Path) -> Path:
    """Where :func:`save_replay` keeps the previous dump while the new one is swapped in."""
    return dump.with_name(f".{dump.name}.old")


def _dump_id(dump: Path) -> str | None:
    """The id in a dump's manifest (None without one)."""
    try:
        manifest = json.loads((dump / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    return manifest.get("id") if isinstance(manifest, dict) else None


# ---------------------------------------------------------------- replay buffer dumps
# A dump is ``storage/`` (the filled segments: one raw C-order file per key, no pickle) and
# ``manifest.json`` (its id, segment count, writer position, every key's dtype and shape, and the
# size and CRC-32 of every file), written last: a dump without a valid manifest is never loaded.
# Format 1 (a memory-mapped TensorDict under ``storage/``) is still read.
REPLAY_FORMAT = 2
MANIFEST = "manifest.json"
STORAGE_DIR = "storage"
_DTYPES = {
    str(d): d
    for d in (
        torch.float16,
        torch.bfloat16,
        torch.float32,
        torch.float64,
        torch.uint8,
        torch.int8,
        torch.int16,
        torch.int32,
        torch.int64,
        torch.bool,
    )
}


def _file_digest(file: Path) -> dict:
    crc = 0
    with open(file, "rb") as handle:
        while chunk := handle.read(1 << 22):
            crc = zlib.crc32(chunk, crc)
    return {"bytes": file.stat().st_size, "crc32": crc}


def _leaves(data) -> list[tuple[str, torch.Tensor]]:
    """``(name, tensor)`` of every leaf of a TensorDict, nested keys joined by ``/``."""
    out = []
    for key, value in data.items(include_nested=True, leaves_only=True):
        out.append(("/".join(key) if isinstance(key, tuple) else key, value))
    return sorted(out)


def _dump_buffer(buffer, folder: Path, dump_id: str | None) -> None:
    """Write the filled part of ``buffer``'s storage and its writer position into ``folder``:
    plain writes of every key's bytes (a full disk raises ENOSPC there, never a SIGBUS of a memory
    map), after checking that the folder's disk has room for them."""
    storage, writer = buffer.storage, buffer.writer
    if storage.ndim != 1:
        raise ValueError(f"save_replay supports storages with ndim=1, got ndim={storage.ndim}")
    n = len(storage)
    data = storage._storage[:n] if n else None
    leaves = _leaves(data) if n else []
    needed = sum(t.numel() * t.element_size() for _, t in leaves)
    free = _free_bytes(folder)
    if needed + (1 << 20) > free:
        raise OSError(
            errno.ENOSPC,
            f"No space left on device (the dump needs {needed / 1e6:.1f} MB, "
            f"{free / 1e6:.1f} MB are free)",
        )
    tensors, files = {}, {}
    for name, tensor in leaves:  # only the filled slots: a dump is sized by what it holds
        rel = f"{STORAGE_DIR}/{name}.memmap"
        file = folder / rel
        file.parent.mkdir(parents=True, exist_ok=True)
        raw = tensor.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy()
        fd = os.open(file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            _write_all(fd, raw)
        finally:
            os.close(fd)
        tensors[name] = {"dtype": str(tensor.dtype), "shape": list(tensor.shape)}
        files[rel] = {"bytes": raw.nbytes, "crc32": zlib.crc32(raw)}
    manifest = {
        "format": REPLAY_FORMAT,
        "id": dump_id,
        "segments": n,
        "batch_size": list(data.batch_size) if n else [0],
        "capacity": storage.max_size,
        "cursor": int(writer._cursor),
        "write_count": int(writer._write_count),
        "tensors": tensors,
        "files": files,
    }
    fd = os.open(folder / MANIFEST, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        _write_all(fd, json.dumps(manifest, indent=1).encode())
        os.fsync(fd)
    finally:
        os.close(fd)


def save_replay(
    buffer, path: str | Path, *, dump_id: str | None = None, keep_previous: bool = False
) -> Path:
    """Dump a TorchRL replay buffer (its filled segments and writer position) into the directory
    ``path``, tagged with ``dump_id``.

    Written to a temporary directory first and swapped in, so an interrupted write leaves the
    previous dump (or ``.<name>.old`` during the swap) intact; temp directories of a writer that
    was killed are removed first. With ``keep_previous`` the previous dump stays as
    ``.<name>.old`` (:func:`save_run` drops it once the checkpoint names the new one). A full disk
    or a read-only folder is one :class:`CheckpointError` line naming ``path``, and leaves no temp
    folder."""
    path = Path(path)
    old = _previous(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        _remove_stale_temps(path)
        tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
        _dump_buffer(buffer, tmp, dump_id)
        shutil.rmtree(old, ignore_errors=True)
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
        if not keep_previous:
            shutil.rmtree(old, ignore_errors=True)
    except OSError as err:
        raise _cannot_write("the replay buffer dump", path, err) from None
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return path


def _damaged(path: Path, what: str) -> CheckpointError:
    return CheckpointError(
        f"replay buffer dump {path} is damaged: {what}; delete {path} to resume with an "
        "empty buffer (the checkpoint itself is intact)"
    )


def _read_manifest(path: Path) -> dict:
    """The manifest of the dump ``path``, after checking every file it lists (size, then CRC-32)."""
    try:
        manifest = json.loads((path / MANIFEST).read_text())
    except FileNotFoundError:
        raise _damaged(
            path,
            f"{MANIFEST} is missing (an interrupted dump, or one written by an older icco-torchrl)",
        ) from None
    except (OSError, ValueError) as err:
        raise _damaged(path, f"{MANIFEST} is unreadable ({type(err).__name__})") from None
    keys = {"format", "segments", "capacity", "cursor", "write_count", "files"}
    if (
        not isinstance(manifest, dict)
        or manifest.get("format") not in (1, REPLAY_FORMAT)
        or not keys <= set(manifest)
        or not isinstance(manifest["files"], dict)
        or (manifest["format"] == 2 and not isinstance(manifest.get("tensors"), dict))
    ):
        raise _damaged(path, f"{MANIFEST} is not a replay manifest of format 1 or {REPLAY_FORMAT}")
    root = path.resolve()
    for name, expected in manifest["files"].items():
        file = (path / name).resolve()
        if root not in file.parents:
            raise _damaged(path, f"{MANIFEST} lists {name}, outside the dump")
        if not isinstance(expected, dict) or set(expected) != {"bytes", "crc32"}:
            raise _damaged(path, f"{MANIFEST} has a malformed entry for {name}")
        if not file.is_file():
            raise _damaged(path, f"{name} is missing")
        size = file.stat().st_size
        if size != expected["bytes"]:
            raise _damaged(path, f"{name} has {size} bytes, expected {expected['bytes']}")
        if _file_digest(file)["crc32"] != expected["crc32"]:
            raise _damaged(path, f"{name} does not match its checksum")
    return manifest


def _read_dump(path: Path, manifest: dict):
    """The dumped segments of a format-2 dump as a TensorDict (its files were checked)."""
    from tensordict import TensorDict

    n = manifest["segments"]
    out = {}
    for name, meta in manifest["tensors"].items():
        rel = f"{STORAGE_DIR}/{name}.memmap"
        if rel not in manifest["files"] or meta.get("dtype") not in _DTYPES:
            raise _damaged(path, f"{MANIFEST} has a malformed entry for {name}")
        raw = torch.frombuffer(bytearray((path / rel).read_bytes()), dtype=torch.uint8)
        tensor = raw.view(_DTYPES[meta["dtype"]]).reshape(meta["shape"])
        out[tuple(name.split("/"))] = tensor
    batch = manifest.get("batch_size") or [n]
    if batch[0] != n:
        raise _damaged(path, f"{STORAGE_DIR} holds {batch[0]} segments, the manifest {n}")
    return TensorDict(out, batch_size=batch)


def _restore_buffer(buffer, path: Path, manifest: dict) -> None:
    """Write the dumped segments back into the slots they came from and restore the writer."""
    from tensordict import TensorDict

    n, cursor, count = manifest["segments"], manifest["cursor"], manifest["write_count"]
    if not n:
        return
    if manifest["format"] == 1:
        data = TensorDict.load_memmap(path / STORAGE_DIR, allow_pickle=False)
    else:
        data = _read_dump(path, manifest)
    if data.batch_size[0] != n:
        raise _damaged(path, f"{STORAGE_DIR} holds {data.batch_size[0]} segments, the manifest {n}")
    if isinstance(
        buffer.storage.device, torch.device
    ):  # indexed writes need data on the storage's device
        data = data.to(buffer.storage.device)
    capacity = buffer.storage.max_size
    if manifest["capacity"] != capacity:  # train.buffer_segments changed: keep the newest, in order
        if n == manifest["capacity"]:  # a full ring buffer: the oldest segment is at the cursor
            data = torch.cat([data[cursor:], data[:cursor]])
        data = data[-capacity:]
        n = data.batch_size[0]
        cursor = n % capacity
    buffer.storage.set(torch.arange(n), data)  # copies into the storage's own (lazily made) tensors
    buffer.writer._cursor, buffer.writer._write_count = cursor, count


def load_replay(buffer, path: str | Path) -> Path | None:
    """Fill ``buffer`` from a :func:`save_replay` dump; returns the dump read, or None when there
    is none to read.

    Every file is checked against the dump's manifest first: a truncated, missing or altered
    file is a one-line :class:`CheckpointError`, never a silently partial buffer.
    """
    path = Path(path)
    _remove_stale_temps(path)
    if not path.is_dir():
        path = _previous(path)  # a swap was interrupted
    if not path.is_dir():
        return None
    manifest = _read_manifest(path)
    try:
        _restore_buffer(buffer, path, manifest)
    except CheckpointError:
        raise
    except Exception as err:  # a foreign dump: one clear line, not a torch traceback
        raise CheckpointError(
            f"replay buffer dump {path} is unreadable ({type(err).__name__}: {_one_line(err)}); "
            "delete it to resume with an empty buffer"
        ) from None
    return path
