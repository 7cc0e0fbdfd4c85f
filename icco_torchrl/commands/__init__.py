"""The ``icco`` commands, one module each; :mod:`icco_torchrl.cli` only dispatches to them.

A :class:`Command` says how its arguments become Hydra overrides (``prepare``) and what it runs
on the validated config (``run``). ``icco train`` (:mod:`.train`) runs the trainer; ``icco eval``
(:mod:`.evaluate`) and ``icco instruct`` (:mod:`.instruct`) sit above both
:mod:`icco_torchrl.evaluation` and :mod:`icco_torchrl.instructions`, which do not import each
other; ``icco live`` and ``icco bridge`` (:mod:`.live`) start :mod:`icco_torchrl.live`.
:func:`clean_errors` turns bad input into one line and exit code 2 (:func:`error_line`: a
checkpoint that is not there is said with the demo policy each command can run instead).
"""

from __future__ import annotations

import os
import shlex
import sys
import tempfile
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from importlib import import_module
from pathlib import Path

from icco_torchrl.training.config import ConfigError
from icco_torchrl.training.run_folder import CheckpointError

# Command name -> the module of this package that defines it (as NAME.upper(): TRAIN, EVAL...).
MODULES = {
    "train": "train",
    "eval": "evaluate",
    "instruct": "instruct",
    "live": "live",
    "bridge": "live",
}


def results_beside_checkpoint(command: str, args: list[str]) -> tuple[list[str], dict]:
    """The default ``prepare``: the arguments are overrides, and Hydra's own files go to a
    temporary folder (results are written next to the checkpoint, not under ``runs/``)."""
    folder = f"{tempfile.gettempdir()}/icco_{command}/${{now:%Y%m%d-%H%M%S-%f}}"
    return [f"hydra.run.dir={folder}", *args], {}


PACKAGE_DIR = Path(__file__).resolve().parents[1]
# Folders that ship with the project (the demo policy in assets/, the package): never written.
SHIPPED_DIRS = (PACKAGE_DIR, PACKAGE_DIR.parent / "assets")
# The small trained policy of a source checkout (assets/README.md says how it was made).
DEMO_POLICY = PACKAGE_DIR.parent / "assets" / "demo_icco.pt"
# What each command can do with the demo policy instead of a checkpoint that is not there.
DEMO_USES = {
    "eval": "give a run's checkpoint.pt, or evaluate the demo policy: icco eval checkpoint={demo}",
    "instruct": (
        "give a run's checkpoint.pt, or instruct the demo policy: "
        'icco instruct "Go right" checkpoint={demo}'
    ),
    "live": (
        "give a run's checkpoint.pt, or run the demo policy (the default without checkpoint=): "
        "icco live checkpoint={demo}"
    ),
    "bridge": "give a run's checkpoint.pt, or run the demo policy: icco bridge checkpoint={demo}",
    "train": (
        "resume= continues a run from its own checkpoint.pt; the demo policy is evaluated, not "
        "resumed: icco eval checkpoint={demo}"
    ),
}


def demo_hint(command: str) -> str:
    """What ``command`` can run instead of a checkpoint that is not there: the demo policy, as
    ``icco eval`` names it when no checkpoint is found; empty without one (an installed wheel)."""
    if not DEMO_POLICY.is_file():
        return ""
    shown = os.path.relpath(DEMO_POLICY) if DEMO_POLICY.is_relative_to(Path.cwd()) else DEMO_POLICY
    use = DEMO_USES.get(command, DEMO_USES["eval"]).format(demo=shlex.quote(str(shown)))
    return f": {use} (assets/README.md)"


def error_line(command: str, err: Exception) -> str:
    """The one line of a user error of ``command``; a checkpoint that is not there gets
    :func:`demo_hint`."""
    from icco_torchrl.training.checkpoint import CheckpointNotFound

    return f"{err}{demo_hint(command)}" if isinstance(err, CheckpointNotFound) else str(err)


def results_dir(out_dir: str | None, paths: list[Path], name: str) -> Path:
    """Where ``icco eval`` and ``icco instruct`` write: ``eval.out_dir`` when given; else
    ``<name>/`` beside the checkpoints, in their run (or sweep) folder; but for checkpoints that
    ship with the project (``assets/demo_icco.pt``) or lie in a folder this user cannot write,
    ``runs/<checkpoint name>/<name>/`` (under the working folder, as ``icco train``'s runs)."""
    from icco_torchrl.evaluation.runner import default_out_dir  # heavy: plots, tables

    if out_dir:
        return Path(out_dir)
    beside = default_out_dir(paths, name)
    folder = beside.parent.resolve()
    shipped = any(folder == d or d in folder.parents for d in SHIPPED_DIRS)
    if shipped or not os.access(folder, os.W_OK):
        return Path("runs") / Path(paths[0]).stem / name
    return beside


@dataclass(frozen=True)
class Command:
    """One ``icco`` command.

    ``prepare(command, args)`` turns its command-line arguments into Hydra overrides and the
    keyword options of ``run`` (raising ``ValueError`` with a one-line message for bad
    arguments); ``run(cfg, run_dir, **options)`` does the work on the config Hydra composed and
    :func:`~icco_torchrl.training.config.validate` checked, and returns the sweep's objective.
    """

    run: Callable[..., float | None]
    prepare: Callable[[str, list[str]], tuple[list[str], dict]] = results_beside_checkpoint


def find(command: str) -> Command:
    """The :class:`Command` named ``command`` (its module is imported only now)."""
    return getattr(import_module(f"{__name__}.{MODULES[command]}"), command.upper())


@contextmanager
def clean_errors(command: str):
    """Bad input (missing or incompatible checkpoint, bad value) ends the command with a
    one-line message and exit code 2 instead of a traceback."""
    try:
        yield
    except (CheckpointError, ConfigError, ValueError) as err:
        print(f"icco {command}: {error_line(command, err)}", file=sys.stderr)
        raise SystemExit(2) from None
