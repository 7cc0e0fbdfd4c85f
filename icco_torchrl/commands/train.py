"""``icco train [overrides]``: train ``method`` and evaluate it (:mod:`icco_torchrl.training`).

    icco train                                   ICCO on the default budget (CPU, offline)
    icco train method=qmix experiment=smoke      another method, a seconds-long run
    icco train -m method=icco,qmix seed=0,1,2    a Hydra multirun sweep
    icco train resume=runs/icco/.../checkpoint.pt

``resume=PATH`` continues the run as it was last saved, in the checkpoint's folder
(:func:`prepare_train`); the run's state is read once, here, and handed to the trainer, which
refuses what a resumed run cannot honour.

Hydra's record of the run (``.hydra/``: the config, Hydra's own, the overrides) is written by
this command once the trainer holds the run folder's lock and the run has started or its resume
was checked (:func:`write_hydra_record`), not by Hydra before the task runs: a refused run (the
folder in use by another ``icco train``, a resume that cannot continue) writes nothing there.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from icco_torchrl.commands import Command
from icco_torchrl.training.config import set_env_params


def prepare_train(command: str, args: list[str]) -> tuple[list[str], dict]:
    """``resume=PATH`` continues the run as it was last saved, in the checkpoint's folder: the
    run's own method, seed, env and ``train`` settings come first (:func:`saved_run_overrides`;
    this command line's overrides win; a ``method=`` given picks that method's own fields), and
    Hydra's run folder is set to the checkpoint's (unless given), so a resume never leaves an
    empty ``runs/<method>/seed*_<time>/`` behind. The state read (a
    :class:`~icco_torchrl.training.checkpoint.RunState`) goes to :func:`run_train` as ``saved``:
    a resume reads its checkpoint once."""
    args, options = _record_after_the_lock(args)
    resume = next((a.split("=", 1)[1] for a in args if a.startswith("resume=")), None)
    if not resume or resume == "null" or any(a.startswith(("-m", "--multirun")) for a in args):
        return args, options
    from icco_torchrl.training import checkpoint
    from icco_torchrl.training.run_folder import CheckpointError

    try:
        options["saved"] = checkpoint.read(resume)
        saved = saved_run_overrides(options["saved"].cfg, args)
    except (CheckpointError, KeyError, TypeError):
        # the trainer reads it again and reports a missing or damaged checkpoint in one line
        options.pop("saved", None)
        saved = []
    if any(a.startswith("hydra.run.dir=") for a in args):
        return [*saved, *args], options
    return [*saved, *args, f"hydra.run.dir={Path(resume).resolve().parent}"], options


# Hydra's default ``hydra.output_subdir``: where it records a run's config in the run folder.
HYDRA_RECORD = ".hydra"


def _record_after_the_lock(args: list[str]) -> tuple[list[str], dict]:
    """Hydra writes ``.hydra/`` into the run folder before the task runs, so a run refused by
    the folder's lock would rewrite the running run's record: Hydra's is turned off
    (``hydra.output_subdir=null``) and :func:`run_train` writes the same files once the lock is
    held. A ``hydra.output_subdir`` given on the command line is honoured (null: no record)."""
    given = [a for a in args if a.lstrip("+").startswith("hydra.output_subdir=")]
    subdir = given[-1].split("=", 1)[1].strip("'\"") if given else HYDRA_RECORD
    kept = [a for a in args if a not in given]
    return [*kept, "hydra.output_subdir=null"], {
        "record": None if subdir in ("", "null") else subdir
    }


def saved_run_overrides(saved: dict, given: list[str]) -> list[str]:
    """Overrides that make ``icco train resume=PATH`` continue the run as it was last saved: its
    method (and every method field), seed, env and ``train`` settings from the checkpoint's
    config ``saved``, except those the command line ``given`` sets itself (``train.X=``, or
    ``experiment=`` for all of ``train``). Without them a resume composes the defaults: another
    budget (a 3M-frame run "done" at the default 1M), or a seed or method that the compatibility
    checks then refuse."""
    keys = {g.split("=", 1)[0].lstrip("+~") for g in given if "=" in g}
    out = []

    def put(key, value, force=False):
        if key not in keys and not isinstance(value, (dict, list)):
            out.append(f"{'++' if force else ''}{key}={_override_value(value)}")

    # A method given on the command line brings its own fields (checked, not forced).
    if "method" not in keys:
        out.append(f"method={saved['method']['name']}")  # a group option: unquoted
        for k, v in saved["method"].items():
            if k != "name":
                put(f"method.{k}", v, force=True)
    put("seed", saved["seed"])
    if not keys & {"env", "reward"}:
        put("env.num_envs", saved["env"]["num_envs"])
        for k, v in saved["env"].get("params", {}).items():
            put(f"env.params.{k}", v, force=True)
    if "experiment" not in keys:
        for k, v in saved["train"].items():
            if k == "env_params":  # one override per set field, so the command line may change one
                given_env_params = "train.env_params" in keys
                for name, value in set_env_params(v if not given_env_params else {}).items():
                    put(f"train.env_params.{name}", value, force=True)
            else:
                put(f"train.{k}", v, force=True)
    return out


def _override_value(value) -> str:
    """A config value as Hydra's override grammar reads it back."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"
    return repr(value)


def run_train(
    cfg: DictConfig, run_dir: str | Path, record: str | None = None, saved=None
) -> float | None:
    """The final greedy evaluation's team reward (a sweep's objective); None when the run was
    stopped early or had nothing left to train. With ``record``, Hydra's record of the run goes
    to ``run_dir/record`` once the trainer holds the lock (:func:`write_hydra_record`); ``saved``
    is the state of the run ``resume=`` continues, as :func:`prepare_train` read it."""
    from icco_torchrl.trainer import train

    on_start = (lambda: write_hydra_record(cfg, Path(run_dir) / record)) if record else None
    return train(cfg, run_dir, on_start=on_start, saved=saved).get("reward")


def write_hydra_record(cfg: DictConfig, folder: Path) -> None:
    """What Hydra writes into ``.hydra/`` (``config.yaml``, ``hydra.yaml``, ``overrides.yaml``),
    each file replaced atomically (a link in a folder received from elsewhere is replaced, never
    followed). A ``folder`` that is a link is left alone, and said."""
    from hydra.core.hydra_config import HydraConfig

    if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
        print(f"note: {folder} is not a folder: Hydra's record of the run is not written")
        return
    hydra = HydraConfig.instance().cfg  # {"hydra": ...}, as Hydra saves it
    hydra = OmegaConf.create(OmegaConf.to_container(hydra, resolve=False))
    hydra.hydra.output_subdir = folder.name  # what Hydra would have recorded
    files = {
        "config.yaml": cfg,
        "hydra.yaml": hydra,
        "overrides.yaml": HydraConfig.get().overrides.task,
    }
    folder.mkdir(parents=True, exist_ok=True)
    for name, content in files.items():
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{name}.", suffix=".tmp")
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as handle:
                handle.write(OmegaConf.to_yaml(content))
            os.replace(tmp, folder / name)
        except BaseException:
            os.unlink(tmp)
            raise


TRAIN = Command(run=run_train, prepare=prepare_train)
