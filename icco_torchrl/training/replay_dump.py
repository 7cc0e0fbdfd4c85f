"""Replay buffer dumps: the filled part of a TorchRL replay buffer as raw arrays (no pickle, no
memory mapping while writing, so a full disk is an error, not a SIGBUS) with a checksummed
manifest, so a damaged dump is refused instead of resuming on garbage.

A dump is swapped in whole (:func:`save_replay`): an interrupted write leaves the previous dump
(or :func:`previous_dump` during the swap). Which dump a checkpoint names, and which one a
resume takes, is :mod:`.checkpoint`'s (``save``, ``restore_replay``).
"""

from __future__ import annotations

import json
import shlex
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from icco_torchrl.training.run_folder import (
    CheckpointError,
    one_line,
    remove_stale_temps,
    write_folder_atomically,
)

# ---------------------------------------------------------------- replay buffer dumps
# A dump is ``storage/`` (the filled segments: one raw C-order file per key, no pickle) and
# ``manifest.json`` (its id, segment count, writer position, every key's dtype and shape, and the
# size and CRC-32 of every file), written last: a dump without a valid manifest is never loaded.
# Only this format is read; a dump of another is refused in one line naming the command that
# converts its run (a format-2 dump: the same files, tools/convert_checkpoint.py --in-place).
REPLAY_FORMAT = 3
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


def _dump_files(storage, data, leaves, writer, dump_id: str | None) -> Iterator[tuple[str, Any]]:
    """The files of a dump, in the order they are written: one raw C-order file of every key's
    filled slots (no pickle; a dump is sized by what it holds), then the manifest with their
    checksums and the writer's position."""
    tensors, files = {}, {}
    for name, tensor in leaves:
        rel = f"{STORAGE_DIR}/{name}.memmap"
        raw = tensor.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy()
        tensors[name] = {"dtype": str(tensor.dtype), "shape": list(tensor.shape)}
        files[rel] = {"bytes": raw.nbytes, "crc32": zlib.crc32(raw)}
        yield rel, raw
    manifest = {
        "format": REPLAY_FORMAT,
        "id": dump_id,
        "segments": len(storage),
        "batch_size": list(data.batch_size) if leaves else [0],
        "capacity": storage.max_size,
        "cursor": int(writer._cursor),
        "write_count": int(writer._write_count),
        "tensors": tensors,
        "files": files,
    }
    yield MANIFEST, json.dumps(manifest, indent=1).encode()


def save_replay(
    buffer, path: str | Path, *, dump_id: str | None = None, keep_previous: bool = False
) -> Path:
    """Dump a TorchRL replay buffer (its filled segments and writer position) into the directory
    ``path``, tagged with ``dump_id``: its files (:func:`_dump_files`) written through
    :func:`~icco_torchrl.training.run_folder.write_folder_atomically`.

    Written to a temporary directory first and swapped in, so an interrupted write leaves the
    previous dump (or ``.<name>.old`` during the swap) intact; temp directories of a writer that
    was killed are removed first. With ``keep_previous`` the previous dump stays as
    ``.<name>.old`` (:func:`~icco_torchrl.training.checkpoint.save` drops it once the
    checkpoint names the new one). A full disk (checked first, or met while writing: plain
    writes, never a SIGBUS of a memory map) or a read-only folder is one
    :class:`CheckpointError` line naming ``path``, and leaves no temp folder."""
    storage = buffer.storage
    if storage.ndim != 1:
        raise ValueError(f"save_replay supports storages with ndim=1, got ndim={storage.ndim}")
    data = storage._storage[: len(storage)] if len(storage) else None
    leaves = _leaves(data) if data is not None else []
    files = _dump_files(storage, data, leaves, buffer.writer, dump_id)  # written as they come
    path = Path(path)
    return write_folder_atomically(
        path,
        files,
        "the replay buffer dump",
        size=sum(t.numel() * t.element_size() for _, t in leaves),
        old=previous_dump(path),
        keep_old=keep_previous,
    )


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
        raise _damaged(path, f"{MANIFEST} is missing (an interrupted dump)") from None
    except (OSError, ValueError) as err:
        raise _damaged(path, f"{MANIFEST} is unreadable ({type(err).__name__})") from None
    fmt = manifest.get("format") if isinstance(manifest, dict) else None
    if type(fmt) is int and fmt != REPLAY_FORMAT:
        raise CheckpointError(
            f"replay buffer dump {path} has format {fmt}; this icco-torchrl reads only format "
            f"{REPLAY_FORMAT}: convert its run with python tools/convert_checkpoint.py --in-place "
            f"{shlex.quote(str(path.parent))}, or delete {path} to resume with an empty buffer"
        )
    keys = {"format", "segments", "capacity", "cursor", "write_count", "files", "tensors"}
    if (
        not isinstance(manifest, dict)
        or fmt != REPLAY_FORMAT
        or not keys <= set(manifest)
        or not isinstance(manifest["files"], dict)
        or not isinstance(manifest["tensors"], dict)
    ):
        raise _damaged(path, f"{MANIFEST} is not a replay manifest of format {REPLAY_FORMAT}")
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
    """The dumped segments as a TensorDict (its files were checked)."""
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
    n, cursor, count = manifest["segments"], manifest["cursor"], manifest["write_count"]
    if not n:
        return
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
    remove_stale_temps(path)
    if not path.is_dir():
        path = previous_dump(path)  # a swap was interrupted
    if not path.is_dir():
        return None
    manifest = _read_manifest(path)
    try:
        _restore_buffer(buffer, path, manifest)
    except CheckpointError:
        raise
    except Exception as err:  # a foreign dump: one clear line, not a torch traceback
        raise CheckpointError(
            f"replay buffer dump {path} is unreadable ({type(err).__name__}: {one_line(err)}); "
            "delete it to resume with an empty buffer"
        ) from None
    return path


# ---------------------------------------------------------------- which dump is on disk
def previous_dump(dump: Path) -> Path:
    """Where :func:`save_replay` keeps the previous dump while the new one is swapped in."""
    return dump.with_name(f".{dump.name}.old")


def dump_id_of(dump: Path) -> str | None:
    """The id in a dump's manifest (None without one)."""
    try:
        manifest = json.loads((dump / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    return manifest.get("id") if isinstance(manifest, dict) else None
