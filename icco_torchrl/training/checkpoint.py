"""Atomic checkpoints (temp file + rename) and clear errors for bad ones.

Checkpoints hold only tensors and plain Python data, and are read with
``torch.load(weights_only=True)``: a crafted file cannot run code. Replay buffer dumps hold the
filled part of the buffer as memory-mapped tensors (no pickle) with a checksummed manifest, so
a damaged dump is refused instead of resuming on garbage.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import torch


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable, or does not match the requested config."""


# 2: agent embeds the previous action with nn.Embedding, attention keys have no bias.
FORMAT_VERSION = 2

# numpy arrays (the RNG state of ``np.random.get_state()``) are stored as tensors under this tag.
_NDARRAY = "__ndarray__"


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


def _one_line(err: Exception) -> str:
    """The informative line of an exception message (torch's weights-only errors span a page)."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    detail = [line for line in lines if line.startswith("WeightsUnpickler error")]
    return (detail or lines or [""])[0]


def _legacy_numpy_globals() -> list:
    """What checkpoints written before the weights-only format need: numpy's ndarray rebuild.

    ``_reconstruct`` builds an empty array of an allow-listed class and ``ndarray.__setstate__``
    fills it from raw bytes; nothing else is allowed, so these run no code of the file's choosing.
    """
    core = getattr(np, "_core", None) or np.core
    return [core.multiarray._reconstruct, np.ndarray, np.dtype, type(np.dtype(np.uint32))]


def save_checkpoint(path: str | Path, payload: dict[str, Any]) -> Path:
    """Write ``payload`` so that a crash never leaves a half-written file at ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temps(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            torch.save(_to_plain({"format_version": FORMAT_VERSION, **payload}), handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def _load_weights_only(path: Path, map_location) -> Any:
    """``torch.load(weights_only=True)``; files of the previous writer also need numpy's array
    rebuild (see :func:`_legacy_numpy_globals`), allowed for this call only."""
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:
        if "Unsupported global" not in str(err):
            raise
    with torch.serialization.safe_globals(_legacy_numpy_globals()):
        return torch.load(path, map_location=map_location, weights_only=True)


def load_checkpoint(path: str | Path, map_location="cpu") -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        payload = _load_weights_only(path, map_location)
    except Exception as err:  # torch raises several types for truncated/corrupt files
        unsafe = re.search(r"Unsupported global: GLOBAL (\S+)", str(err))
        if unsafe:  # torch's message is a page long; one line says what matters
            raise CheckpointError(
                f"checkpoint {path} refers to {unsafe.group(1)}, which a checkpoint never holds: "
                "refusing to load it (a crafted or foreign file)"
            ) from None
        raise CheckpointError(
            f"checkpoint {path} is truncated or not a checkpoint ({type(err).__name__}: "
            f"{_one_line(err)})"
        ) from None
    if not isinstance(payload, dict) or "format_version" not in payload:
        raise CheckpointError(f"{path} is not an icco-torchrl checkpoint")
    if payload["format_version"] != FORMAT_VERSION:
        raise CheckpointError(
            f"{path} has checkpoint format {payload['format_version']}; this version of "
            f"icco-torchrl reads format {FORMAT_VERSION} (the networks changed): retrain, or "
            "evaluate it with the release that wrote it"
        )
    payload = _from_plain(payload)
    from icco_torchrl.training.config import (
        METHOD_FIELDS_ADDED,
        METHOD_FIELDS_REMOVED,
        REMOVED_AT,
        TRAIN_FIELDS_ADDED,
    )

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


def check_compatible(ckpt: dict[str, Any], cfg, layout, path: str | Path) -> None:
    """The one check that a checkpoint's weights fit what ``cfg`` builds for an env of ``layout``:
    the method's fields (its name and label aside: sizes, encoders, coordinator) and the observation
    layout (robot, resource, invader and waypoint counts) must be the checkpoint's. Used by
    ``resume=`` and by :func:`~icco_torchrl.training.restore.restore`; raises one
    ``CheckpointError`` naming every difference."""
    from omegaconf import OmegaConf

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


# ---------------------------------------------------------------- replay buffer dumps
# A dump is ``storage/`` (the filled segments as a memory-mapped TensorDict: one raw file per
# key, no pickle) and ``manifest.json`` (segment count, writer position, and the size and CRC-32
# of every file), written last: a dump without a valid manifest is never loaded.
REPLAY_FORMAT = 1
MANIFEST = "manifest.json"
STORAGE_DIR = "storage"


def _file_digest(file: Path) -> dict:
    crc = 0
    with open(file, "rb") as handle:
        while chunk := handle.read(1 << 22):
            crc = zlib.crc32(chunk, crc)
    return {"bytes": file.stat().st_size, "crc32": crc}


def _dump_buffer(buffer, folder: Path) -> None:
    """Write the filled part of ``buffer``'s storage and its writer position into ``folder``."""
    storage, writer = buffer.storage, buffer.writer
    if storage.ndim != 1:
        raise ValueError(f"save_replay supports storages with ndim=1, got ndim={storage.ndim}")
    n = len(storage)
    if n:  # only the filled slots: a dump is sized by what it holds, not by the capacity
        storage._storage[:n].cpu().memmap(
            prefix=folder / STORAGE_DIR
        )  # CPU: loadable on any machine
    files = sorted(f for f in folder.rglob("*") if f.is_file())
    manifest = {
        "format": REPLAY_FORMAT,
        "segments": n,
        "capacity": storage.max_size,
        "cursor": int(writer._cursor),
        "write_count": int(writer._write_count),
        "files": {f.relative_to(folder).as_posix(): _file_digest(f) for f in files},
    }
    (folder / MANIFEST).write_text(json.dumps(manifest, indent=1))


def save_replay(buffer, path: str | Path) -> Path:
    """Dump a TorchRL replay buffer (its filled segments and writer position) into the directory
    ``path``.

    Written to a temporary directory first and swapped in, so an interrupted write leaves the
    previous dump (or ``.<name>.old`` during the swap) intact; temp directories of a writer
    that was killed are removed first.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temps(path)
    old = path.with_name(f".{path.name}.old")
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    try:
        _dump_buffer(buffer, tmp)
        shutil.rmtree(old, ignore_errors=True)
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)
    finally:
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
        or manifest.get("format") != REPLAY_FORMAT
        or not keys <= set(manifest)
        or not isinstance(manifest["files"], dict)
    ):
        raise _damaged(path, f"{MANIFEST} is not a format-{REPLAY_FORMAT} replay manifest")
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


def _restore_buffer(buffer, path: Path, manifest: dict) -> None:
    """Write the dumped segments back into the slots they came from and restore the writer."""
    from tensordict import TensorDict

    n, cursor, count = manifest["segments"], manifest["cursor"], manifest["write_count"]
    if not n:
        return
    data = TensorDict.load_memmap(path / STORAGE_DIR, allow_pickle=False)
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


def load_replay(buffer, path: str | Path) -> bool:
    """Fill ``buffer`` from a :func:`save_replay` dump; False when there is none to read.

    Every file is checked against the dump's manifest first: a truncated, missing or altered
    file is a one-line :class:`CheckpointError`, never a silently partial buffer.
    """
    path = Path(path)
    _remove_stale_temps(path)
    if not path.is_dir():
        path = path.with_name(f".{path.name}.old")  # a swap was interrupted
    if not path.is_dir():
        return False
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
    return True
