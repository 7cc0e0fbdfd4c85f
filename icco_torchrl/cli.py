"""``icco train|eval|instruct [hydra overrides]`` (also ``python -m icco_torchrl ...``).

Hydra composes ``conf/`` (``--help``, ``-m`` multirun and launcher overrides all work); the
result is validated against the typed schema before any work starts.
"""

from __future__ import annotations

import sys
import tempfile

USAGE = """usage: icco {train,eval,instruct,live,bridge} [overrides...]

  icco train                                   ICCO on the default budget (CPU, offline)
  icco train method=qmix experiment=smoke      another method, a seconds-long run
  icco train -m method=icco,qmix seed=0,1,2    a Hydra multirun sweep
  icco train resume=runs/icco/.../checkpoint.pt
  icco eval checkpoint=runs/icco/.../checkpoint.pt [eval.protocol=quadrants] [eval.gif=true]
  icco instruct "Go right" checkpoint=...      run a trained policy with a language instruction
  icco live [checkpoint=...]                   a trained team in the browser: type instructions, watch it act
  icco bridge checkpoint=... [live.fleet=true] command robots over UDP (JSON), DWA velocity commands
"""


def _run(command: str) -> None:
    import hydra
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import DictConfig

    from icco_torchrl.paths import CONF_DIR
    from icco_torchrl.training.checkpoint import CheckpointError
    from icco_torchrl.training.config import ConfigError, validate

    @hydra.main(config_path=str(CONF_DIR), config_name="config", version_base=None)
    def main(raw: DictConfig) -> float | None:
        output_dir = HydraConfig.get().runtime.output_dir
        try:
            return _dispatch(command, validate(raw), output_dir)
        except (ConfigError, CheckpointError) as err:  # user errors: one clear line, no traceback
            print(f"icco {command}: {err}", file=sys.stderr)
            _remove_if_only_hydra(output_dir)
            raise SystemExit(2) from None

    main()


def _remove_if_only_hydra(folder: str) -> None:
    """A command that failed before any work leaves no run folder behind (Hydra made it)."""
    import shutil
    from pathlib import Path

    path = Path(folder)
    if path.is_dir() and {p.name for p in path.iterdir()} <= {".hydra", "cli.log"}:
        shutil.rmtree(path, ignore_errors=True)


def _resume_folder(args: list[str]) -> list[str]:
    """``resume=PATH`` continues the run as it was last saved, in the checkpoint's folder: the run's own
    method, seed, env and ``train`` settings come first (``saved_run_overrides``; this command
    line's overrides win; a ``method=`` given picks that method's own fields), and Hydra's run folder
    is set to the checkpoint's (unless given), so a
    resume never leaves an empty ``runs/<method>/seed*_<time>/`` behind."""
    resume = next((a.split("=", 1)[1] for a in args if a.startswith("resume=")), None)
    if not resume or resume == "null" or any(a.startswith(("-m", "--multirun")) for a in args):
        return args
    from pathlib import Path

    from icco_torchrl.training.checkpoint import CheckpointError, load_checkpoint
    from icco_torchrl.training.trainer import saved_run_overrides

    try:
        saved = saved_run_overrides(load_checkpoint(resume)["cfg"], args)
    except (CheckpointError, KeyError, TypeError):
        saved = []  # the trainer reports a missing or damaged checkpoint in one line
    if any(a.startswith("hydra.run.dir=") for a in args):
        return [*saved, *args]
    return [*saved, *args, f"hydra.run.dir={Path(resume).resolve().parent}"]


def _dispatch(command: str, cfg, run_dir: str) -> float | None:
    if command == "train":
        from icco_torchrl.training.trainer import train

        return train(cfg, run_dir).get("reward")
    if command == "eval":
        from icco_torchrl.commands.evaluate import run_eval

        return run_eval(cfg, run_dir)
    if command in ("live", "bridge"):
        from icco_torchrl.live.cli import run_bridge, run_live

        try:
            return (run_live if command == "live" else run_bridge)(cfg)
        except (OSError, ValueError) as err:  # port in use, bad limits, no checkpoint: one line
            print(f"icco {command}: {err}", file=sys.stderr)
            raise SystemExit(2) from None
    from icco_torchrl.commands.instruct import run_instruct

    return run_instruct(cfg, run_dir, _INSTRUCTION)


_INSTRUCTION: str = ""


def main(argv: list[str] | None = None) -> None:
    global _INSTRUCTION
    argv = list(sys.argv[1:] if argv is None else argv)
    if (
        not argv
        or argv[0] in ("-h", "--help", "help")
        or argv[0] not in ("train", "eval", "instruct", "live", "bridge")
    ):
        print(USAGE)
        raise SystemExit(0 if argv and argv[0] in ("-h", "--help", "help") else 2)
    command, rest = argv[0], argv[1:]
    if command == "instruct":
        if not rest or "=" in rest[0] or rest[0].startswith("-"):
            print(
                'icco instruct: give the instruction first, e.g. icco instruct "Go right" checkpoint=PATH',
                file=sys.stderr,
            )
            raise SystemExit(2)
        _INSTRUCTION, rest = rest[0], rest[1:]
    if command == "train":
        rest = _resume_folder(rest)
    else:  # results go next to the checkpoint; keep Hydra's own files out of runs/
        rest = [
            f"hydra.run.dir={tempfile.gettempdir()}/icco_{command}/${{now:%Y%m%d-%H%M%S-%f}}",
            *rest,
        ]
    from icco_torchrl.training.config import check_command_line

    bad = unknown_group_option(rest) or check_command_line(
        rest
    )  # one line naming the field, before Hydra
    if bad:
        print(f"icco {command}: {bad}", file=sys.stderr)
        raise SystemExit(2)
    sys.argv = [f"icco {command}", *rest]
    _run(command)


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
                return f"config group '{group}' has no option {option!r}; choose from {', '.join(known)}"
    return None


if __name__ == "__main__":
    main()
