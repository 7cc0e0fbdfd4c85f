"""A run's saved state: its type, its file format, the rules of a resume, and the pair of a run's
checkpoint and its replay dump. The run folder's files and lock are :mod:`.run_folder`'s; the
replay dump's format is :mod:`.replay_dump`'s.

- **The state.** :class:`RunState` holds exactly a checkpoint's fields, typed and frozen.
  ``TrainingRun.state_dict()`` builds it and ``load_state_dict()`` takes it
  (:mod:`icco_torchrl.trainer`); :func:`save` writes it (and the replay dump it names) and
  :func:`resume` reads it back, checked, with the replay buffer refilled: one call each way.
  Adding a field: ``docs/extending.md`` ("Add a field to a run's saved state").

- **Format.** A checkpoint holds only tensors and plain Python data and is read with
  ``torch.load(weights_only=True)``: a crafted file cannot run code. It is written atomically
  (:func:`~icco_torchrl.training.run_folder.write_atomically`). Any file that is not a readable
  checkpoint (empty, text, a crafted or foreign pickle, a dict without the fields a checkpoint has)
  is one :class:`~icco_torchrl.training.run_folder.CheckpointError` line naming the path; so is a
  write that fails (a full disk, a read-only folder), which leaves no temp file.
- **One format.** Only :data:`FORMAT_VERSION` is read; a file of another format is one line
  naming the command that converts it (``tools/convert_checkpoint.py``, outside the package, which
  holds the upgrades of older files). So is a file whose config lacks a field of today's
  ``MethodConfig`` (written before that option existed): a new method option needs a row in the
  converter, not a new format, and is never read at today's default by mistake.
- **Resume rules.** :func:`check_resumable`: what a resumed run cannot change, and whether the
  networks and env layout fit (:func:`check_compatible`, :func:`load_weights`).
- **Checkpoint and dump.** :func:`save` writes the dump, then the checkpoint naming the dump's
  id, and only then drops the previous dump, so a stop between the two writes leaves a dump that
  matches the checkpoint; :func:`restore_replay` picks it (and says so) or refuses a foreign one.
"""

from __future__ import annotations

import io
import os
import pickle
import re
import shlex
import shutil
import uuid
import warnings
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from icco_torchrl.training.config import EnvParams, MethodConfig, TrainConfig, TrainEnvParams
from icco_torchrl.training.replay_dump import (
    dump_id_of,
    load_replay,
    previous_dump,
    save_replay,
)
from icco_torchrl.training.run_folder import (
    CHECKPOINT,
    REPLAY_DIR,
    CheckpointError,
    fresh_outputs,
    one_line,
    remove_stale_temps,
    write_atomically,
)

# 3: every config field is in the file (older files: tools/convert_checkpoint.py fills them in).
# 2: agent embeds the previous action with nn.Embedding, attention keys have no bias.
FORMAT_VERSION = 3
# Converts a checkpoint of an older format (run from the repository's root).
CONVERTER = "tools/convert_checkpoint.py"


# ---------------------------------------------------------------- the state
@dataclass(frozen=True)
class RunState:
    """A training run's saved state: exactly the fields of its checkpoint (the file adds its
    ``format_version``). The replay buffer is dumped beside the checkpoint, which names the dump;
    the exploration rate follows from ``frames``. The tensors are the run's own, not copies."""

    cfg: dict  # the run's config, resolved (the networks fit its method fields)
    layout: dict  # the ObsLayout fields of the env the networks were built for
    frames: int  # env steps collected
    updates: int  # gradient updates
    batches: int  # collector batches
    loss: dict  # ICCOLoss.state_dict(): every network, the target copies too
    optimizer: dict
    updater: dict  # the target updater's
    rng: dict  # the random streams: torch, numpy, the env's (and the collector process's)
    outputs: dict  # which final outputs of the last frame were written (run_folder.fresh_outputs)
    replay_id: str | None  # the replay dump saved with it (None: none)
    replay_segments: int  # the segments that dump holds (0: nothing to restore)

    def checkpoint(self) -> dict:
        """The fields as the checkpoint holds them."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


# What an exported policy keeps of a run's state (:func:`export_policy`): enough to act.
POLICY_FIELDS = ("cfg", "layout", "frames", "updates", "loss")
#: Config fields that hold a path of the training machine: cleared in an exported policy.
MACHINE_PATHS = ("resume", "checkpoint")

# numpy arrays (the RNG state of ``np.random.get_state()``) are stored as tensors under this tag.
_NDARRAY = "__ndarray__"


# ---------------------------------------------------------------- the file format
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
    return write_atomically(Path(path), _serialised(payload), "checkpoint")


def _serialised(payload: dict[str, Any]) -> memoryview:
    """The bytes of the checkpoint holding ``payload``."""
    buffer = io.BytesIO()
    torch.save(_to_plain({"format_version": FORMAT_VERSION, **payload}), buffer)
    return buffer.getbuffer()


# ---------------------------------------------------------------- reading files
# A checkpoint's plain data (its config, the optimiser's and updater's state, the RNG streams) is
# a few thousand values, nested a few levels: a file beyond these bounds is refused before anything
# walks it (:func:`check_structure`).
MAX_VALUES = 1_000_000  # counted as reading expands them: a list referenced twice counts twice
MAX_DEPTH = 64


class CheckpointNotFound(CheckpointError):
    """No file at a checkpoint's path (the commands add where a checkpoint comes from)."""


def check_structure(payload: Any, path: str | Path) -> None:
    """Refuse, in one line, data that nests deeper than :data:`MAX_DEPTH` or holds more than
    :data:`MAX_VALUES` values once its shared lists, tuples and dicts are expanded (what reading
    it, converting it or its config does): a crafted file of a few hundred KB would otherwise take
    every byte of memory, or the stack, of whatever walks it. Walked without recursion; a
    structure that contains itself is too deep."""
    stack, values = [(payload, 0)], 0
    while stack:
        obj, depth = stack.pop()
        if isinstance(obj, dict):
            items = [*obj.keys(), *obj.values()]
        elif isinstance(obj, (list, tuple, set, frozenset)):
            items = list(obj)
        else:
            continue
        if depth >= MAX_DEPTH:
            raise CheckpointError(
                f"checkpoint {path} nests its data more than {MAX_DEPTH} levels deep, which no "
                "checkpoint does: refusing to load it (a crafted or damaged file)"
            )
        values += len(items)
        if values > MAX_VALUES:
            raise CheckpointError(
                f"checkpoint {path} holds more than {MAX_VALUES:,} values once its shared lists "
                "and dicts are expanded, which no checkpoint does: refusing to load it (a crafted "
                "or damaged file)"
            )
        stack.extend((item, depth + 1) for item in items)


def check_finite(weights: dict, path: str | Path) -> None:
    """Refuse, in one line, weights that are not finite numbers (NaN or inf): a policy acting with
    them evaluates to numbers that look normal and mean nothing."""
    bad = [
        name
        for name, value in weights.items()
        if isinstance(value, torch.Tensor)
        and value.is_floating_point()
        and not bool(torch.isfinite(value).all())
    ]
    if bad:
        more = f" and {len(bad) - 3} more" if len(bad) > 3 else ""
        raise CheckpointError(
            f"checkpoint {path} has weights that are not finite numbers (NaN or inf in "
            f"{', '.join(bad[:3])}{more}): its training diverged or the file is damaged; use an "
            "earlier checkpoint, or train again"
        )


def _load_weights_only(path: Path, map_location) -> Any:
    """``torch.load(weights_only=True)``. torch's warnings about a file's pickle protocol are not
    the user's business: the error, if any, is."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
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
            f"checkpoint {path} is truncated or damaged ({type(err).__name__}: {one_line(err)}): "
            "use an earlier copy, or train again"
        )
    if head.startswith(b"PK") or head[:1] == b"\x80":  # a zip archive of torch.save, or a pickle
        unsafe = re.search(r"GLOBAL (\S+)", str(err))
        if unsafe and unsafe.group(1).startswith("numpy."):  # the writer before weights-only files
            return CheckpointError(
                f"{path} refers to {unsafe.group(1)}, as checkpoints written before the "
                f"weights-only format (format 2 and older) do; this icco-torchrl reads only format "
                f"{FORMAT_VERSION}: {_convert_it(path)}"
            )
        what = (
            f"refers to {unsafe.group(1)}, which a checkpoint never holds"
            if unsafe
            else (f"holds something a checkpoint never holds ({one_line(err)})")
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
    """The checkpoint at ``path``, of :data:`FORMAT_VERSION`.

    Anything else (a missing, empty, truncated, text, crafted or foreign file, another format, a
    dict without the ``require``d fields) is one :class:`CheckpointError` line naming ``path``;
    an older format's names the command that converts it (:func:`another_format`). So is data
    beyond a checkpoint's size and depth (:func:`check_structure`) and, with ``loss`` required,
    weights that are NaN or inf (:func:`check_finite`)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointNotFound(f"checkpoint not found: {path}")
    if path.stat().st_size == 0:
        raise CheckpointError(f"checkpoint {path} is empty (a write that never finished)")
    try:
        payload = _load_weights_only(path, map_location)
    except Exception as err:  # torch raises several types for truncated/corrupt/crafted files
        raise _read_error(path, err) from None
    check_structure(payload, path)
    if not isinstance(payload, dict) or "format_version" not in payload:
        raise CheckpointError(f"{path} is not an icco-torchrl checkpoint")
    version = payload["format_version"]
    if type(version) is not int:  # "2" or 2.0: not a number this project ever wrote
        raise CheckpointError(
            f"{path} is not an icco-torchrl checkpoint: its format_version is {version!r}, a "
            f"{type(version).__name__}, where icco-torchrl writes an integer ({FORMAT_VERSION})"
        )
    if version != FORMAT_VERSION:
        raise another_format(path, version)
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
    if "cfg" in require and (absent := missing_method_fields(cfg["method"])):
        raise CheckpointError(
            f"{path} was written before {', '.join(f'method.{k}' for k in absent)} existed: "
            f"{_convert_it(path)}"
        )
    if "cfg" in require and (removed := removed_fields(cfg)):
        raise CheckpointError(
            f"{path} was written with {', '.join(removed)}, since removed from icco-torchrl: "
            f"{_convert_it(path)}"
        )
    if "loss" in require and not isinstance(payload["loss"], dict):
        raise CheckpointError(f"{path} is not a complete icco-torchrl checkpoint: loss is no dict")
    if "loss" in require:
        check_finite(payload["loss"], path)
    return _from_plain(payload)


def missing_method_fields(method: dict) -> list[str]:
    """The fields of today's :class:`MethodConfig` that a checkpoint's ``method`` config lacks:
    options added after it was written, which the converter fills at the value it trained with."""
    return [f.name for f in fields(MethodConfig) if f.name not in method]


REMOVABLE_SECTIONS = (  # the config's sections whose removed fields the converter drops
    (("method",), MethodConfig),
    (("train",), TrainConfig),
    (("env", "params"), EnvParams),
    (("train", "env_params"), TrainEnvParams),
)


def config_section(cfg: dict, path: tuple[str, ...]) -> dict | None:
    """``cfg[path[0]][path[1]]...``, or None where a level is missing or no dict."""
    for key in path:
        cfg = cfg.get(key) if isinstance(cfg, dict) else None
    return cfg if isinstance(cfg, dict) else None


def removed_fields(cfg: dict) -> list[str]:
    """The fields of a checkpoint's config (``method``, ``train``, ``env.params``,
    ``train.env_params``) that today's schema lacks: options removed since it was written, which
    the converter drops where the run never used them."""
    removed = []
    for path, schema in REMOVABLE_SECTIONS:
        section = config_section(cfg, path)
        if section is not None:
            known = {f.name for f in fields(schema)}
            removed += [".".join((*path, key)) for key in section if key not in known]
    return removed


def another_format(path: Path, version: int) -> CheckpointError:
    """The one line for a checkpoint of another format than :data:`FORMAT_VERSION`: an older one
    names the command that converts it (a run's ``checkpoint.pt`` also in place, with its replay
    dump, so its run can be resumed)."""
    if version > FORMAT_VERSION:
        return CheckpointError(
            f"{path} has checkpoint format {version}, newer than the format {FORMAT_VERSION} this "
            "icco-torchrl reads: use the icco-torchrl that wrote it"
        )
    return CheckpointError(
        f"{path} has checkpoint format {version}; this icco-torchrl reads only format "
        f"{FORMAT_VERSION}: {_convert_it(path)}"
    )


def _convert_it(path: Path) -> str:
    """The command that converts the checkpoint ``path`` (a run's also in place)."""
    old = shlex.quote(str(path))
    new = shlex.quote(str(path.with_name(f"{path.stem}_v{FORMAT_VERSION}{path.suffix}")))
    in_place = (
        f" (or python {CONVERTER} --in-place {old}, which also converts its run's replay dump so "
        "the run can be resumed)"
        if path.name == CHECKPOINT
        else ""
    )
    return f"convert it with python {CONVERTER} {old} {new}{in_place}"


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
    return save_checkpoint(dst, policy_of(load_checkpoint(src)))


def policy_of(state: dict | RunState) -> dict:
    """The weights-only payload of a run's state (a checkpoint's dict or a :class:`RunState`):
    :data:`POLICY_FIELDS`, the networks without their target copies, and the config without
    :data:`MACHINE_PATHS` (a shared policy names no folder of the machine that trained it)."""
    ckpt = state.checkpoint() if isinstance(state, RunState) else state
    slim = {k: ckpt[k] for k in POLICY_FIELDS if k in ckpt}
    if isinstance(slim.get("cfg"), dict):  # the training machine's paths stay on that machine
        slim["cfg"] = {**slim["cfg"], **{k: None for k in MACHINE_PATHS if k in slim["cfg"]}}
    slim["loss"] = {k: v for k, v in ckpt["loss"].items() if not k.startswith("target_")}
    slim["policy_only"] = True
    return slim


def check_compatible(saved_cfg: dict, saved_layout: dict, cfg, layout, path: str | Path) -> None:
    """The one check that weights saved with ``saved_cfg`` for an env of ``saved_layout`` fit what
    ``cfg`` builds for an env of ``layout``: the method's fields (its name and label aside: sizes,
    encoders, coordinator) and the observation layout (robot, resource, invader and waypoint
    counts) must be the saved ones. Used by :func:`resume` and by
    :func:`~icco_torchrl.training.restore.restore`; raises one ``CheckpointError`` naming every
    difference."""
    cfg = cfg if isinstance(cfg, dict) else OmegaConf.to_container(cfg, resolve=True)
    saved_m, m = saved_cfg["method"], cfg["method"]
    method = [
        f"method.{key}: checkpoint {saved_m.get(key)!r} vs config {m.get(key)!r}"
        for key in sorted(set(saved_m) | set(m))
        if key not in ("name", "label") and saved_m.get(key) != m.get(key)
    ]
    shape = [
        f"{key}: checkpoint {value} vs env {getattr(layout, key)}"
        for key, value in (saved_layout or {}).items()
        if value != getattr(layout, key)
    ]
    problems = (
        [f"was trained with an incompatible config: {'; '.join(method)}"] if method else []
    ) + ([f"was trained for another env layout: {'; '.join(shape)}"] if shape else [])
    if problems:
        raise CheckpointError(f"checkpoint {path} " + ", and ".join(problems))


def read(path: str | Path) -> RunState:
    """The run's state saved at ``path``: its checkpoint read once (:func:`load_checkpoint`), as a
    :class:`RunState`. An exported policy (no optimiser, targets or RNG state), a file without a
    training state, or one written before a field of the state existed is one
    ``CheckpointError`` line (the last names the converter)."""
    path = Path(path)
    ckpt = load_checkpoint(path)
    if ckpt.get("policy_only"):
        raise CheckpointError(
            f"{path} is an exported policy (no optimiser, targets or RNG state): "
            f"resume from the run's own checkpoint.pt"
        )
    missing = [f.name for f in fields(RunState) if f.name not in ckpt]
    if "optimizer" in missing:
        raise CheckpointError(
            f"{path} cannot be resumed: it lacks the training state {', '.join(missing)}"
        )
    if missing:
        raise CheckpointError(
            f"{path} cannot be resumed: it was written before the run state's "
            f"{', '.join(missing)} existed: {_convert_it(path)}"
        )
    if not isinstance(ckpt["outputs"], dict):
        raise CheckpointError(f"{path} cannot be resumed: its outputs record is no dict")
    state = RunState(**{f.name: ckpt[f.name] for f in fields(RunState)})
    return replace(state, outputs={**fresh_outputs(), **state.outputs})


def resume(
    path: str | Path, cfg: DictConfig, *, layout, buffer, state: RunState | None = None
) -> RunState:
    """Continue the run saved at ``path`` with ``cfg``, in one call: its state (:func:`read`; or
    ``state``, when the command line has read it already to compose ``cfg``), checked against
    what ``cfg`` builds for an env of ``layout`` (:func:`check_resumable`), and ``buffer``
    refilled from the replay dump it names (:func:`restore_replay`, said in one line). Returns
    the state to continue from, for ``TrainingRun.load_state_dict``: a run with frames left
    writes its final outputs anew; one at its budget only those its checkpoint says are missing
    (a stop in the final evaluation)."""
    path = Path(path)
    state = read(path) if state is None else state
    check_resumable(state, cfg, layout, path)
    said = restore_replay(buffer, path.resolve().parent, state, path)
    if said:
        print(said, flush=True)
    if cfg.train.total_frames > state.frames:
        state = replace(state, outputs=fresh_outputs())
    return state


def check_resumable(state: RunState, cfg: DictConfig, layout, path: str | Path) -> None:
    """Refuse, in one line, a run state this config cannot continue: a command line that changes
    what a resumed run cannot honour (:func:`check_resume_overrides`) or networks and env layout
    that differ (:func:`check_compatible`). A new ``train.env_params`` is allowed (a shaping
    curriculum), and said: the replayed data keeps the old rewards."""
    config = OmegaConf.to_container(cfg, resolve=True)
    check_resume_overrides(state.cfg, config, path)
    check_compatible(state.cfg, state.layout, config, layout, path)
    before, now = (  # the fields of train.env_params that are set
        {k: v for k, v in (c["train"].get("env_params") or {}).items() if v is not None}
        for c in (state.cfg, config)
    )
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
    ``train.env_params`` (a shaping curriculum) may change. A field the saved config lacks (an
    option added since it was written) is today's default on both sides."""
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
        if not _kept(a, b):
            diffs.append(f"{'.'.join(keys)} (checkpoint {a!r}, now {b!r})")
    if diffs:
        raise CheckpointError(
            f"resume={path} cannot change "
            + "; ".join(diffs)
            + ": drop these overrides, or start a new run without resume="
        )


def _kept(saved, now) -> bool:
    """Whether ``now`` keeps every value of ``saved`` (nested dicts key by key)."""
    if isinstance(saved, dict):
        return isinstance(now, dict) and all(_kept(v, now.get(k)) for k, v in saved.items())
    return saved == now


# ---------------------------------------------------------------- a run's checkpoint and its dump
def save(run_dir: str | Path, state: RunState, buffer=None) -> RunState:
    """Write ``state`` as the run's checkpoint, and with ``buffer`` a new replay dump first;
    returns the state as written (with ``buffer``, naming the new dump). Without ``buffer`` the
    checkpoint names the dump ``state`` names (the one on disk, unchanged).

    The dump replaces the previous one but keeps it (``.replay.old``) until the checkpoint naming
    the new one is written: a stop between the two writes leaves the previous dump, which matches
    the checkpoint on disk (:func:`restore_replay`)."""
    run_dir = Path(run_dir)
    dump = run_dir / REPLAY_DIR
    if buffer is not None:
        state = replace(state, replay_id=uuid.uuid4().hex[:16], replay_segments=len(buffer))
    data = _serialised(state.checkpoint())
    if buffer is not None:
        save_replay(buffer, dump, dump_id=state.replay_id, keep_previous=True)
    write_atomically(run_dir / CHECKPOINT, data, "checkpoint")
    if buffer is not None:
        shutil.rmtree(previous_dump(dump), ignore_errors=True)  # no checkpoint names it any more
    return state


def restore_replay(buffer, run_dir: str | Path, state: RunState, path: str | Path) -> str | None:
    """Refill ``buffer`` from the dump that the run's ``state`` (read from ``path``) was saved
    with, and return the line that says what happened (None when it saved no buffer).

    The dump and the checkpoint share an id. A dump written after the checkpoint (a stop between
    the two writes) is set aside for the previous one, which matches, and said; a dump matching
    neither is refused in one line."""
    if not state.replay_segments:
        return None
    dump = Path(run_dir) / REPLAY_DIR
    remove_stale_temps(dump)
    expected = state.replay_id
    previous = previous_dump(dump)
    if dump_id_of(dump) == expected:
        load_replay(buffer, dump)
        return f"replay buffer restored: {len(buffer)} segments"
    if dump_id_of(previous) == expected:
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
            f"replay buffer dump {found} (id {dump_id_of(found)}) is not the one {path} was saved "
            f"with (id {expected}): delete {found} to resume with an empty buffer"
        )
    return f"no replay buffer dump in {run_dir}: resuming with an empty buffer (warm-up again)"
