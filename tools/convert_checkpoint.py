"""Convert an icco-torchrl checkpoint of an older format (2), or one of today's format (3) written
before a method option existed, to what the library reads.

Usage::

    python tools/convert_checkpoint.py OLD.pt NEW.pt
    python tools/convert_checkpoint.py --in-place RUN_DIR/checkpoint.pt    # or RUN_DIR

The library reads only its own checkpoint format (``FORMAT_VERSION`` in
``icco_torchrl/training/checkpoint.py``), with every field of today's ``MethodConfig``, and refuses
any other file in one line naming this script.
The upgrade of older files lives here, and only here:

- The file is read with ``torch.load(weights_only=True)``; a file written before the weights-only
  writer (numpy's RNG state pickled as numpy arrays) gets numpy's array rebuild allowed for that
  one call (:func:`legacy_numpy_globals`). A crafted file runs no code.
- The config gets the fields added since it was written at the value it was trained with
  (:data:`METHOD_FIELDS_ADDED`, :data:`TRAIN_FIELDS_ADDED`); an option removed from the library
  since (:data:`METHOD_FIELDS_REMOVED`, :data:`TRAIN_FIELDS_REMOVED`) is dropped at its one
  remaining value, and any other value is refused in one line naming the last commit that loads
  the file. The result must pass today's
  config schema.
- A training checkpoint gets what a resume now requires where it lacks it, at the values the older
  library assumed: the record of its final outputs (written when ``learning_curve.png`` lies beside
  it), its replay dump's id (none) and segment count (0).
- It is written through the library's ``save_checkpoint`` (atomically: a stop leaves the old file)
  and read back with ``load_checkpoint``. A ``NEW.pt`` named ``checkpoint.pt`` is a run folder's:
  it is written under the run's lock (``.train.lock``), so while an ``icco train`` writes that
  folder the converter refuses in one line and writes nothing.
- A file whose data nests deeper, or expands to more values, than any checkpoint (a crafted file
  of shared lists) is refused in one line before it is walked (``check_structure``).

``--in-place`` converts the file where it is; for a run folder's ``checkpoint.pt`` it holds the
run's lock and also converts the run's replay buffer dump (``replay/``, and ``.replay.old`` left
by a stop between the dump and the checkpoint), so ``icco train resume=RUN_DIR/checkpoint.pt``
continues the run with its buffer. A format-2 dump holds the same files as a format-3 one: only
its manifest's format is rewritten (atomically; the files' checksums stay and are checked by the
resume). A format-1 dump (a memory-mapped TensorDict) is not converted: it is left as it is and
said, and the resume refuses it in one line (delete it to resume with an empty buffer). Without
``--in-place`` only the checkpoint is written; a resume next to an unconverted dump refuses it in
one line naming ``--in-place``. Nothing is dropped silently.

A file that cannot be converted is one line on stderr (exit status 2), and nothing is written.
"""

from __future__ import annotations

import argparse
import copy
import json
import shlex
import sys
import warnings
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from icco_torchrl.training.checkpoint import (
    FORMAT_VERSION,
    check_structure,
    config_section,
    load_checkpoint,
    save_checkpoint,
)
from icco_torchrl.training.config import ConfigError, MethodConfig, TrainConfig, validate
from icco_torchrl.training.replay_dump import MANIFEST, REPLAY_FORMAT, previous_dump
from icco_torchrl.training.run_folder import (
    CHECKPOINT,
    REPLAY_DIR,
    CheckpointError,
    RunFolderLock,
    fresh_outputs,
    one_line,
    write_atomically,
)

# The oldest format converted: format 1 had other networks (the agent's previous-action input, the
# attention keys' bias; commit aaf2287), which no config of today builds.
OLDEST = 2
# A dump of these formats holds the files of today's (REPLAY_FORMAT): only its manifest changes.
DUMP_FORMATS_RELABELLED = (2,)

# ---------------------------------------------------------------- the upgrade tables
# Method fields added after checkpoints had been written, with the value those older checkpoints
# were trained with (not today's default, which may differ), so an older checkpoint (the demo
# policy, a committed result) restores the networks it was trained with. A field filled in must be
# one of today's config (a field dropped since belongs in METHOD_FIELDS_REMOVED).
METHOD_FIELDS_ADDED = {
    "waypoint_features": False,
    "mixer": "qmix",
    "posterior_input": "flat",
    "broadcast_threshold": 0.0,
    "layer_norm": False,  # added with format 3: no format-2 file has it
}
# Options measured and dropped from the library: the only value it still builds, and the last commit
# that can load a checkpoint trained with another value (refused in one line naming it).
METHOD_FIELDS_REMOVED = {
    "instruction_head": (False, "396580d"),
    "z_input": ("head", "396580d"),
    "reward_channels": ("team", "6ecb567"),  # experiments/best_team: not kept
}
# Train fields of options measured and dropped, as METHOD_FIELDS_REMOVED (ANY: dropped at any
# value, a setting of the removed option that did nothing while it was off).
ANY = "any value"
TRAIN_FIELDS_REMOVED = {
    "teacher": (None, "6da9543"),  # experiments/best_team: teacher data not kept
    "teacher_envs": (ANY, "6da9543"),
    "teacher_share": (ANY, "6da9543"),
}
# Env parameters of options measured and dropped, as METHOD_FIELDS_REMOVED; in train.env_params
# (the training env's own overrides) they are dropped unset (None) or at the value left.
ENV_FIELDS_REMOVED = {
    "inst_reward": ("cosine", "1169af0"),  # "progress": experiments/language/routes, not kept
}
# Train fields added after checkpoints had been written, with the value those runs trained with:
# a resumed older run keeps its recipe (4-step items, no shaping) instead of today's defaults.
TRAIN_FIELDS_ADDED = {
    "sequence_length": 4,
    "burn_in": 0,
    "shaping": {"potentials": [], "weight": 0.3},
    "ce_clamp": False,  # unclamped until the consistency screen made the clamps the default
}


# ---------------------------------------------------------------- the checkpoint
def legacy_numpy_globals() -> list:
    """What checkpoints written before the weights-only format need: numpy's ndarray rebuild.

    ``_reconstruct`` builds an empty array of an allow-listed class and ``ndarray.__setstate__``
    fills it from raw bytes; nothing else is allowed, so these run no code of the file's choosing.
    """
    core = getattr(np, "_core", None) or np.core
    return [core.multiarray._reconstruct, np.ndarray, np.dtype, type(np.dtype(np.uint32))]


def read_old(path: Path) -> dict:
    """The raw contents of the checkpoint at ``path`` (weights-only, numpy's array rebuild allowed
    for this call only), of a format this script converts; anything else is one line."""
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        with warnings.catch_warnings(), torch.serialization.safe_globals(legacy_numpy_globals()):
            warnings.simplefilter("ignore")  # torch's notes on an old pickle protocol
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # empty, truncated, text, crafted: torch raises several types
        raise CheckpointError(
            f"{path} is not a readable checkpoint ({type(err).__name__}: {one_line(err)})"
        ) from None
    check_structure(payload, path)  # before anything walks it: a crafted file stops here
    version = payload.get("format_version") if isinstance(payload, dict) else None
    if type(version) is not int:
        raise CheckpointError(
            f"{path} is not an icco-torchrl checkpoint (no integer format_version)"
        )
    if version > FORMAT_VERSION:
        raise CheckpointError(
            f"{path} has checkpoint format {version}, newer than the format {FORMAT_VERSION} of "
            "this icco-torchrl: use the icco-torchrl that wrote it"
        )
    if version < OLDEST:
        raise CheckpointError(
            f"{path} has checkpoint format {version}, whose networks no config of today builds: "
            "retrain, or evaluate it with the release that wrote it (before commit aaf2287)"
        )
    return payload


def upgrade(payload: dict, path: Path) -> list[str]:
    """Bring ``payload``'s config to today's fields, in place (the upgrade tables); returns what
    changed. An option removed since, at another value than the one left, is one line."""
    changes = []
    cfg = payload.get("cfg")
    for section, added, schema in (
        ("train", TRAIN_FIELDS_ADDED, TrainConfig),
        ("method", METHOD_FIELDS_ADDED, MethodConfig),
    ):
        fields = cfg.get(section) if isinstance(cfg, dict) else None
        if not isinstance(fields, dict):
            continue
        for key, value in added.items():  # added later: it trained the old way
            if key not in fields and key in schema.__dataclass_fields__:
                fields[key] = copy.deepcopy(value)
                changes.append(f"{section}.{key}={value!r}")
    for where, removed, unset in (
        (("method",), METHOD_FIELDS_REMOVED, ()),
        (("train",), TRAIN_FIELDS_REMOVED, ()),
        (("env", "params"), ENV_FIELDS_REMOVED, ()),
        (("train", "env_params"), ENV_FIELDS_REMOVED, (None,)),
    ):
        fields = config_section(cfg, where)
        section = ".".join(where)
        if fields is None:
            continue
        for key, (value, commit) in removed.items():  # only one value loads
            if key not in fields:
                continue
            if value is not ANY and fields[key] != value and fields[key] not in unset:
                raise CheckpointError(
                    f"{path} was trained with {section}.{key}={fields[key]!r}, an option removed "
                    f"from icco-torchrl; evaluate it at commit {commit}"
                )
            was = fields.pop(key)
            changes.append(
                f"{section}.{key} dropped (it was {was!r}{'' if value is ANY else ', as today'})"
            )
    return changes


def complete_training_state(payload: dict, src: Path) -> list[str]:
    """A training checkpoint (not an exported policy) gets the fields a resume requires where it
    lacks them, at the values the older library assumed; returns what was added."""
    if payload.get("policy_only") or "optimizer" not in payload:
        return []
    changes = []
    if not isinstance(payload.get("outputs"), dict):  # complete when its learning curve exists
        done = (src.parent / "learning_curve.png").is_file()
        payload["outputs"] = {**fresh_outputs(), "final_evaluation": done, "learning_curve": done}
        changes.append(f"outputs (final outputs {'written' if done else 'not written'})")
    for key, value in (("replay_id", None), ("replay_segments", 0)):
        if key not in payload:
            payload[key] = value
            changes.append(f"{key}={value!r}")
    return changes


def check_config(payload: dict, path: Path) -> None:
    """The converted config passes today's schema (what restore and resume read), or one line."""
    cfg = payload.get("cfg")
    if not isinstance(cfg, dict):
        return  # load_checkpoint names what is missing, where it is required
    try:
        validate(OmegaConf.create(cfg))
    except ConfigError as err:
        raise CheckpointError(
            f"{path} converted has a config this icco-torchrl refuses: {err}"
        ) from None
    except Exception as err:  # a config OmegaConf cannot even read
        raise CheckpointError(
            f"{path} converted has an unreadable config ({type(err).__name__}: {one_line(err)})"
        ) from None


def convert_file(src: Path, dst: Path) -> str:
    """Convert the checkpoint ``src`` into ``dst`` (may be ``src``); returns the line saying what
    was done. Refusals are one :class:`CheckpointError` line, and write nothing."""
    payload = read_old(src)
    version = payload.pop("format_version")
    changes = upgrade(payload, src) + complete_training_state(payload, src)
    check_config(payload, src)
    save_checkpoint(dst, payload)  # format_version: FORMAT_VERSION
    load_checkpoint(dst, require=())  # it reads back
    what = "; ".join(changes) if changes else "no field changed"
    return f"{src} (format {version}) -> {dst} (format {FORMAT_VERSION}): {what}"


# ---------------------------------------------------------------- a run's replay dump
def _dump_format(dump: Path):
    """The format in the manifest of the dump ``dump`` (None when unreadable)."""
    try:
        manifest = json.loads((dump / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    return manifest.get("format") if isinstance(manifest, dict) else None


def convert_dump(dump: Path) -> str | None:
    """Bring the replay dump ``dump`` to REPLAY_FORMAT where only its manifest differs; returns the
    line saying what was done (None when there is no dump)."""
    if not dump.is_dir():
        return None
    keep = f"left as it is: the resume refuses it; delete {dump} to resume with an empty buffer"
    try:
        manifest = json.loads((dump / MANIFEST).read_text())
    except (OSError, ValueError) as err:
        return f"note: replay dump {dump} has no readable {MANIFEST} ({type(err).__name__}); {keep}"
    fmt = manifest.get("format") if isinstance(manifest, dict) else None
    if fmt == REPLAY_FORMAT:
        return f"replay dump {dump} is already format {REPLAY_FORMAT}"
    if fmt not in DUMP_FORMATS_RELABELLED:
        return f"note: replay dump {dump} has format {fmt!r}, which is not converted; {keep}"
    keys = {"segments", "capacity", "cursor", "write_count", "files", "tensors"}
    if not keys <= set(manifest) or not isinstance(manifest["tensors"], dict):
        return f"note: replay dump {dump} has a damaged {MANIFEST}; {keep}"
    manifest["format"] = REPLAY_FORMAT
    write_atomically(
        dump / MANIFEST, json.dumps(manifest, indent=1).encode(), "the replay manifest"
    )
    return f"replay dump {dump} (format {fmt}) -> format {REPLAY_FORMAT}"


def convert_to(src: Path, dst: Path) -> list[str]:
    """Convert ``src`` into ``dst``; a ``dst`` that is a run folder's checkpoint under that run's
    lock, so a training writing the folder is refused in one line and left alone (two writers of
    one checkpoint would remove each other's temp file)."""
    if dst.name != CHECKPOINT:
        return [convert_file(src, dst)]
    with RunFolderLock(dst.parent):
        return [convert_file(src, dst)]


def convert_in_place(path: Path) -> list[str]:
    """Convert ``path`` where it is; a run folder's checkpoint with the run's replay dump, under
    the run's lock (a run training there is left alone)."""
    if path.is_dir():
        path = path / CHECKPOINT
    if path.name != CHECKPOINT:  # a file of its own (an exported policy): no run around it
        return [convert_file(path, path)]
    run_dir = path.parent
    with RunFolderLock(run_dir):
        said = [convert_file(path, path)]  # first: a checkpoint it cannot convert stops it here
        dump = run_dir / REPLAY_DIR
        said += [line for d in (dump, previous_dump(dump)) if (line := convert_dump(d))]
    return said


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python tools/convert_checkpoint.py",
        description=f"Convert an icco-torchrl checkpoint to format {FORMAT_VERSION}.",
    )
    parser.add_argument(
        "src", type=Path, help="the checkpoint to convert (with --in-place: or its run folder)"
    )
    parser.add_argument("dst", type=Path, nargs="?", help="where to write the converted checkpoint")
    parser.add_argument(
        "--in-place",
        action="store_true",
        help="convert SRC where it is; a run folder's checkpoint.pt with its replay dump, so the "
        "run can be resumed",
    )
    args = parser.parse_args(argv)
    if args.in_place == (args.dst is not None):
        parser.error("give OLD.pt NEW.pt, or --in-place RUN_DIR/checkpoint.pt")
    try:
        said = convert_in_place(args.src) if args.in_place else convert_to(args.src, args.dst)
    except (CheckpointError, OSError) as err:  # one line, never a traceback
        print(
            f"convert_checkpoint: {err if isinstance(err, CheckpointError) else one_line(err)}",
            file=sys.stderr,
        )
        return 2
    print("\n".join(said))
    if not args.in_place and args.dst.name == CHECKPOINT:
        dump = args.dst.parent / REPLAY_DIR
        if dump.is_dir() and _dump_format(dump) != REPLAY_FORMAT:  # a run's older dump beside it
            print(
                f"note: the replay dump {dump} is still of an older format: to resume with it, "
                f"run python tools/convert_checkpoint.py --in-place {shlex.quote(str(dump.parent))}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
