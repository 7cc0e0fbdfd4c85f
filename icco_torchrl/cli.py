"""``icco train|eval|instruct|live|bridge [overrides]`` (also ``python -m icco_torchrl ...``).

The commands live in :mod:`icco_torchrl.commands`; this module only dispatches. Hydra composes
``conf/`` once per run (``--help``, ``-m`` multirun and launcher overrides all work) and the
result is validated against the typed schema before any work starts; a bad value ends the
command with one line naming the field and exit code 2 (a misspelled field with the one it most
likely meant: :func:`did_you_mean`).
"""

from __future__ import annotations

import difflib
import errno
import os
import re
import sys
from typing import NoReturn

USAGE = """usage: icco {train,eval,instruct,live,bridge} [overrides...]

  icco train                                   ICCO on the default budget (CPU, offline)
  icco train method=qmix experiment=smoke      another method, a seconds-long run
  icco train -m method=icco,qmix seed=0,1,2    a Hydra multirun sweep
  icco train resume=runs/icco/.../checkpoint.pt
  icco eval checkpoint=runs/icco/.../checkpoint.pt [eval.protocol=quadrants] [eval.gif=true]
  icco instruct "Go right" checkpoint=...      run a trained policy with a language instruction
  icco live [checkpoint=...]                   a trained team in the browser: type instructions
  icco bridge checkpoint=... [live.fleet=true] command robots over UDP (JSON), DWA velocities
"""
COMMANDS = ("train", "eval", "instruct", "live", "bridge")
# Third-party warnings a user can do nothing about, each silenced by category, message and the
# module it is attributed to (any other warning still shows): ``(category, message, module)``.
KNOWN_WARNINGS = (
    # torch 2.13 deprecates a dynamo flag that tensordict still reads while the update compiles
    # (``make train``): printed in the middle of the progress bar.
    (
        FutureWarning,
        r"torch\._dynamo\.config\.inline_inbuilt_nn_modules is deprecated",
        r"tensordict\.",
    ),
)


def quiet_known_warnings() -> None:
    """Filter :data:`KNOWN_WARNINGS` in this process (every ``icco`` command does, at start)."""
    import warnings

    for category, message, module in KNOWN_WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=category, module=module)


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in COMMANDS:
        print(USAGE)
        raise SystemExit(0 if argv and argv[0] in ("-h", "--help", "help") else 2)
    name, args = argv[0], argv[1:]
    quiet_known_warnings()
    from icco_torchrl.training import compile_cache

    compile_cache.note_environment()  # before torch is imported: its import reads the variable
    from icco_torchrl.commands import find
    from icco_torchrl.training.config import check_command_line

    command = find(name)
    try:
        overrides, options = command.prepare(name, args)
    except ValueError as err:
        _fail(name, str(err))
    # Before Hydra, one line: an option file that does not exist; in a sweep, every job's config
    # (so a bad value in its last job does not wait for the first ones to train).
    bad = unknown_group_option(overrides)
    if not bad and any(a in ("-m", "--multirun") for a in overrides):
        bad = check_command_line(overrides)
    if bad:
        _fail(name, did_you_mean(bad, overrides))
    _run_hydra(name, overrides, lambda cfg, run_dir: command.run(cfg, run_dir, **options))


def _fail(command: str, message: str) -> NoReturn:
    print(f"icco {command}: {message}", file=sys.stderr)
    raise SystemExit(2)


def _run_hydra(name: str, overrides: list[str], task) -> None:
    """``task(cfg, run_dir)`` under ``hydra.main``: Hydra composes the config (once per run), and
    :func:`~icco_torchrl.training.config.validate` checks it. Every user error (a bad override,
    a bad value, an unusable checkpoint) ends the command in one line with exit code 2."""
    import hydra
    from hydra.core.hydra_config import HydraConfig
    from hydra.errors import HydraException
    from omegaconf import DictConfig
    from omegaconf.errors import OmegaConfBaseException

    from icco_torchrl.commands import error_line
    from icco_torchrl.paths import CONF_DIR
    from icco_torchrl.training.collector_process import CollectorError
    from icco_torchrl.training.config import ConfigError, compose_error, validate
    from icco_torchrl.training.run_folder import CheckpointError, RunFolderBusy

    @hydra.main(config_path=str(CONF_DIR), config_name="config", version_base=None)
    def main(raw: DictConfig) -> float | None:
        output_dir = HydraConfig.get().runtime.output_dir
        try:
            return task(validate(raw), output_dir)
        except RunFolderBusy as err:  # the folder is another process's: leave it as it is
            _fail(name, str(err))
        except CollectorError as err:  # the run's checkpoint stays: resume= continues it
            _fail(name, str(err))
        except (ConfigError, CheckpointError) as err:  # user errors: one clear line
            _remove_if_only_hydra(output_dir)
            _fail(name, error_line(name, err))
        except OSError as err:
            if err.filename is None:
                raise
            _fail(name, os_error_line(err))

    sys.argv = [f"icco {name}", *overrides]
    # Hydra prints a composition error over several lines and exits 1; raised instead, it is said
    # here in one line naming the field.
    os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        main()
    except (HydraException, OmegaConfBaseException) as err:
        _fail(name, did_you_mean(compose_error(err), overrides))
    except OSError as err:  # Hydra writing its own files (.hydra/) into a full or read-only folder
        if err.filename is None:
            raise
        _fail(name, os_error_line(err) + _unwritable_hint(name, overrides, err))
    except ValueError as err:  # Hydra's log file (cli.log) in a read-only folder, said by logging
        cause = err.__cause__ or err.__context__
        if not isinstance(cause, OSError) or cause.filename is None:
            raise
        _fail(name, os_error_line(cause) + _unwritable_hint(name, overrides, cause))


def os_error_line(err: OSError) -> str:
    """One line for a file the command could not write or read: the path and the reason."""
    return f"cannot access {err.filename}: {err.strerror or err}"


def _unwritable_hint(command: str, overrides: list[str], err: OSError) -> str:
    """What to do when ``icco train`` cannot write its run folder: a resume writes in the
    checkpoint's own folder, so it is resumed from a writable copy."""
    if command != "train" or err.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
        return ""
    if any(o.startswith("resume=") and o != "resume=null" for o in overrides):
        return (
            "; resume= continues a run in its checkpoint's folder, which must be writable: copy "
            "the run folder to a writable place and resume the copy"
        )
    return "; give hydra.run.dir= a writable folder"


def did_you_mean(message: str, overrides: list[str]) -> str:
    """``message`` with the field most likely meant when it names an unknown field (Hydra's
    "Key 'protocl' not in 'EvalConfig'"): each unknown part of the key typed is matched against
    the fields of the typed config (:class:`~icco_torchrl.training.config.Config`) at its place,
    so ``eval.protocl=quadrants`` gets "did you mean eval.protocol?". Unchanged when nothing is
    close."""
    found = re.match(r"config field '([^']+)': Key '[^']+' not in '\w+'", message)
    if not found:
        return message
    parts = found.group(1).split(".")
    typed = next(  # the whole key typed (Hydra names its first unknown part)
        (
            key
            for item in overrides
            if (key := item.partition("=")[0].lstrip("+~").split("."))[: len(parts)] == parts
        ),
        parts,
    )
    guess = _closest_field(typed)
    return f"{message}; did you mean {guess}?" if guess and guess != ".".join(typed) else message


def _closest_field(parts: list[str]) -> str | None:
    """The field path of the typed config nearest ``parts`` (each unknown part replaced by the
    closest field at its place), or None when one has no close match."""
    import dataclasses

    from icco_torchrl.training.config import Config

    schema, path = Config, []
    for part in parts:
        if schema is None:  # below a leaf field: not a field at all
            return None
        fields = {f.name: f for f in dataclasses.fields(schema)}
        if part not in fields:
            close = difflib.get_close_matches(part, list(fields), n=1, cutoff=0.6)
            if not close:
                return None
            part = close[0]
        factory = fields[part].default_factory
        nested = factory is not dataclasses.MISSING and dataclasses.is_dataclass(factory)
        schema = factory if nested else None
        path.append(part)
    return ".".join(path)


def _remove_if_only_hydra(folder: str) -> None:
    """A command that failed before any work leaves no run folder behind (Hydra made it); one
    that another ``icco train`` holds (it has just begun writing) is left alone."""
    import shutil
    from pathlib import Path

    path = Path(folder)
    from icco_torchrl.training.run_folder import LOCK_FILE, CheckpointError, RunFolderLock

    if path.is_dir() and {p.name for p in path.iterdir()} <= {".hydra", "cli.log", LOCK_FILE}:
        try:
            with RunFolderLock(path):
                shutil.rmtree(path, ignore_errors=True)
        except CheckpointError:  # held by another run, or its lock file is a link: not ours
            pass


def unknown_group_option(overrides: list[str]) -> str | None:
    """One line naming the first ``group=option`` override whose option file does not exist.

    Hydra reports these with a multi-line message and exit 1; we check the config groups of
    ``conf/`` (method, env, reward, experiment, llm) before Hydra starts. Multirun lists
    (``method=icco,qmix``) are checked item by item.
    """
    from icco_torchrl.paths import CONF_DIR

    for item in overrides:
        key, sep, value = item.partition("=")
        group = key.lstrip("+~")
        if (
            not sep
            or "." in group
            or "/" in group
            or not (CONF_DIR / group).is_dir()
            or group == "hydra"
        ):
            continue
        known = sorted(f.stem for f in (CONF_DIR / group).glob("*.yaml"))
        for option in value.split(","):
            if option and option not in known:
                return (
                    f"config group '{group}' has no option {option!r}; "
                    f"choose from {', '.join(known)}"
                )
    return None


if __name__ == "__main__":
    main()
