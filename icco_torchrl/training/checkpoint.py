"""Atomic checkpoints (temp file + rename) and clear errors for bad ones."""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import torch


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable, or does not match the requested config."""


# 2: agent embeds the previous action with nn.Embedding, attention keys have no bias.
FORMAT_VERSION = 2


def save_checkpoint(path: str | Path, payload: dict[str, Any]) -> Path:
    """Write ``payload`` so that a crash never leaves a half-written file at ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            torch.save({"format_version": FORMAT_VERSION, **payload}, handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def load_checkpoint(path: str | Path, map_location="cpu") -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as err:  # torch raises several types for truncated/corrupt files
        raise CheckpointError(f"checkpoint {path} is truncated or not a checkpoint ({type(err).__name__}: {err})") from None
    if not isinstance(payload, dict) or "format_version" not in payload:
        raise CheckpointError(f"{path} is not an icco-torchrl checkpoint")
    if payload["format_version"] != FORMAT_VERSION:
        raise CheckpointError(f"{path} has checkpoint format {payload['format_version']}; this version of icco-torchrl "
                              f"reads format {FORMAT_VERSION} (the networks changed): retrain, or evaluate it with the "
                              "release that wrote it")
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
        raise CheckpointError(f"checkpoint {path} does not match the {method} networks: missing {missing[:4]}, "
                              f"unexpected {unexpected[:4]}, other shapes {reshaped[:4]}")
    try:
        loss.load_state_dict(state_dict)
    except (RuntimeError, KeyError) as err:
        raise CheckpointError(f"checkpoint {path} does not match the {method} networks: {err}") from None


def check_compatible(saved_cfg: dict, cfg: dict, path: str | Path) -> None:
    """Refuse a checkpoint whose method, model sizes or env layout differ from ``cfg``."""
    diffs = []
    for section in ("method",):
        for key in sorted(set(saved_cfg[section]) | set(cfg[section])):
            if key != "name" and saved_cfg[section].get(key) != cfg[section].get(key):
                diffs.append(f"{section}.{key}: checkpoint {saved_cfg[section].get(key)!r} vs config {cfg[section].get(key)!r}")
    for key in ("n_agents", "n_resources", "n_invaders", "n_waypoints"):
        a, b = saved_cfg["env"]["params"].get(key), cfg["env"]["params"].get(key)
        if a != b:
            diffs.append(f"env.params.{key}: checkpoint {a!r} vs config {b!r}")
    if diffs:
        raise CheckpointError(f"checkpoint {path} was trained with an incompatible config: " + "; ".join(diffs))


def save_replay(buffer, path: str | Path) -> Path:
    """Dump a TorchRL replay buffer (storage, writer, sampler) into the directory ``path``.

    Written to a temporary directory first and swapped in, so an interrupted write leaves the
    previous dump (or ``.<name>.old`` during the swap) intact.
    """
    path = Path(path)
    old = path.with_name(f".{path.name}.old")
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    try:
        buffer.dumps(tmp)
        shutil.rmtree(old, ignore_errors=True)
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def load_replay(buffer, path: str | Path) -> bool:
    """Fill ``buffer`` from a :func:`save_replay` dump; False when there is none to read."""
    path = Path(path)
    if not path.is_dir():
        path = path.with_name(f".{path.name}.old")  # a swap was interrupted
    if not path.is_dir():
        return False
    try:
        buffer.loads(path)
    except Exception as err:  # a partial or foreign dump: one clear line, not a torch traceback
        raise CheckpointError(f"replay buffer dump {path} is unreadable ({type(err).__name__}: {err}); "
                              "delete it to resume with an empty buffer") from None
    return True
