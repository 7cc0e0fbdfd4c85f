"""Resumable training runs, several side by side: the one job runner of the experiment scripts.

A run is ``icco train <overrides> hydra.run.dir=<folder>``. :func:`run_status` says whether its
checkpoint reached the budget; :func:`train_runs` starts missing runs, resumes partial ones from
their checkpoint (``resume=``) and keeps ``jobs`` processes busy (one torch thread each: two
side by side use a 2-core machine fully). Each run logs to ``<folder>.log``; every 10 minutes
the runner prints each running run's frames and, at its pace so far, the minutes it has left.
"""

from __future__ import annotations

import argparse
import copy
import csv
import functools
import importlib.util
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

from omegaconf import OmegaConf

from icco_torchrl.evaluation.metrics import write_csv
from icco_torchrl.training.checkpoint import export_policy, load_checkpoint
from icco_torchrl.training.config import EnvConfig, TrainConfig

# The training recipe before sequence replay became the default (commit 396580d): 4-step items,
# one-step targets, no shaping. Scripts that compare against it, or whose measurements were taken
# at it, add these overrides.
PRE_SEQUENCE_REPLAY = [
    "train.sequence_length=4",
    "train.batch_segments=128",
    "train.buffer_segments=20000",
    "train.warmup_segments=512",
    "train.td_lambda=0",
    "train.shaping.potentials=[]",
]


# A smoke run's budget, seconds per run: proves a pipeline, says nothing about the methods.
SMOKE_BUDGET = (
    "experiment=smoke",
    "train.total_frames=512",
    "train.eval_interval=256",
    "train.checkpoint_interval=0",
    "train.eval_envs=2",
)


def budget(smoke: bool, overrides: list[str] | None, default: list[str]) -> list[str]:
    """An experiment script's training overrides: with ``--smoke`` the smoke budget plus
    ``--budget``'s overrides, else ``--budget`` or the script's ``default``."""
    if smoke:
        return [*SMOKE_BUDGET, *(overrides or [])]
    return list(overrides or default)


def run_status(run: Path, total_frames: int) -> str:
    """``done`` (checkpoint at the budget), ``partial`` (a checkpoint short of it) or ``missing``.

    The budget is this invocation's, so raising ``train.total_frames`` extends finished runs.
    """
    checkpoint = run / "checkpoint.pt"
    if not checkpoint.is_file():
        return "missing"
    frames = load_checkpoint(checkpoint).get("frames", 0)
    return "done" if frames >= total_frames else "partial"


def child_environment() -> dict[str, str]:
    """This process's environment for a training run, without the Inductor cache folder torch
    wrote into it on import (``TORCHINDUCTOR_CACHE_DIR`` at torch's default): a run given that
    would compile into a cold temporary folder instead of icco's persistent cache."""
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    env = dict(os.environ)
    if env.get("TORCHINDUCTOR_CACHE_DIR") == default_cache_dir():
        del env["TORCHINDUCTOR_CACHE_DIR"]
    return env


def positive(text: str) -> int:
    """A count that must be at least 1 (``--jobs``, ``--trials``, ``--steps``), as an argparse
    type: a bad value is one line before anything trains (``--jobs 0`` would wait forever with
    nothing running; ``--trials 0`` would fail only after the training)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value}: must be at least 1")
    return value


def last_row(path: Path) -> dict | None:
    """The last complete row of the CSV file ``path`` as a dict (its header read from the first
    line, the row from the tail, so a long log costs no more than a short one), or None when the
    file is missing or has no complete row. A row still being written (no newline yet) is skipped.
    """
    try:
        with path.open("rb") as handle:
            header = handle.readline().decode(errors="replace")
            start = handle.tell()
            handle.seek(0, os.SEEK_END)
            handle.seek(max(start, handle.tell() - 4096))
            tail = handle.read().decode(errors="replace")
    except OSError:
        return None
    if not header.endswith("\n"):
        return None
    names = next(csv.reader([header]))
    for line in reversed(tail.split("\n")[:-1]):  # the text after the last newline is unfinished
        values = next(csv.reader([line]), [])
        if len(values) == len(names):
            return dict(zip(names, values))
    return None


def frames_logged(run: Path) -> int | None:
    """The frame count of the last complete row of ``run/train.csv``, or None before its first."""
    row = last_row(run / "train.csv")
    return None if row is None else int(row["frames"])


def progress_line(seen: dict[Path, tuple[int, int, float, float]], waiting: int) -> str:
    """One line on the runs in progress: ``seen[run] = (total, frames then, frames now, seconds
    between)``, each with its frames, its share of the budget and, once it moved, the minutes
    it has left at its pace so far; ``waiting`` runs still queued."""
    parts = []
    for run, (total, first, now, seconds) in seen.items():
        part = f"{run.name} {now:,} of {total:,} frames ({100 * now / total:.0f} %)"
        if now > first and seconds > 0:
            left = (total - now) / ((now - first) / seconds) / 60
            part += f", about {left:.0f} min left"
        parts.append(part)
    queued = f"; {waiting} queued" if waiting else ""
    return "progress: " + "; ".join(parts) + queued


def train_runs(
    runs: dict[Path, tuple[list[str], int]], jobs: int = 2, report_every: float = 600.0
) -> None:
    """Bring every run ``{folder: (overrides, total_frames)}`` to its budget, ``jobs`` at a time,
    with a :func:`progress_line` every ``report_every`` seconds (the runs' own logs hold the
    rest)."""
    if jobs < 1:
        raise ValueError(f"jobs={jobs}: at least 1 run at a time")
    status = {run: run_status(run, total) for run, (_, total) in runs.items()}
    print("runs: " + ", ".join(f"{run.name}={state}" for run, state in status.items()), flush=True)
    queue = []
    for run, state in status.items():
        if state == "done":
            continue
        if state == "missing" and run.exists():
            # Died before its first checkpoint: its CSVs would be appended to, so start clean.
            shutil.move(str(run), str(run.with_name(f"{run.name}.failed-{int(time.time())}")))
        resume = [f"resume={run / 'checkpoint.pt'}"] if state == "partial" else []
        queue.append(
            (
                run,
                [
                    sys.executable,
                    "-m",
                    "icco_torchrl",
                    "train",
                    *runs[run][0],
                    *resume,
                    "logger.progress=false",
                    f"hydra.run.dir={run}",
                ],
            )
        )
    running: list[tuple[Path, subprocess.Popen]] = []
    failed = []
    first: dict[Path, tuple[int, float]] = {}  # each run's first logged frames, and when
    reported = time.monotonic()
    while queue or running:
        while queue and len(running) < jobs:
            run, command = queue.pop(0)
            run.parent.mkdir(parents=True, exist_ok=True)
            print(f"$ icco {' '.join(command[3:])}  > {run}.log", flush=True)
            with open(f"{run}.log", "a") as log:
                running.append(
                    (
                        run,
                        subprocess.Popen(
                            command, stdout=log, stderr=subprocess.STDOUT, env=child_environment()
                        ),
                    )
                )
        time.sleep(2)
        now = time.monotonic()
        for run, _ in running:
            if run not in first and (frames := frames_logged(run)) is not None:
                first[run] = (frames, now)
        if now - reported >= report_every:
            reported = now
            seen = {}
            for run, _ in running:
                if run in first and (frames := frames_logged(run)) is not None:
                    seen[run] = (runs[run][1], first[run][0], frames, now - first[run][1])
            if seen:
                print(progress_line(seen, len(queue)), flush=True)
        for item in [r for r in running if r[1].poll() is not None]:
            running.remove(item)
            run, proc = item
            print(
                f"{run.name}: "
                f"{'done' if proc.returncode == 0 else f'FAILED (exit {proc.returncode})'}",
                flush=True,
            )
            if proc.returncode:
                failed.append(run.name)
    if failed:
        raise SystemExit(f"training failed for {failed}: see their .log files")


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``), what every page records its numbers on."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def script(path: Path, name: str):
    """The script ``path`` as a module called ``name`` (script names are not unique: every
    experiment has a ``run.py``), registered in ``sys.modules`` so that its dataclasses can look
    their module up while it runs."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


# What a finished run leaves behind once its checkpoint is gone: enough for learning curves,
# budgets and time to skill (``find_runs``, ``timing.csv``, ``references.json``), and its policy
# weights (``POLICY``, about 0.6 MB: no optimizer, no replay), so that any protocol can be played
# again without retraining.
RECORD_FILES = ("config.yaml", "eval.csv", "timing.csv", "references.json")
POLICY = "policy.pt"
REFERENCES_TRIALS = "references_trials.csv"


def _thin_timing(timing: Path, evals: Path) -> list[dict]:
    """``timing.csv``'s rows (one cumulative row per collector batch, ~10k at 5M frames) cut to
    the first row at or past each evaluation and the last row: what the clock is read at."""
    with evals.open() as handle:
        marks = sorted(int(float(r["frames"])) for r in csv.DictReader(handle))
    with timing.open() as handle:
        rows = list(csv.DictReader(handle))
    kept, i = [], 0
    for n, row in enumerate(rows):
        frames = int(float(row["frames"]))
        if (i < len(marks) and frames >= marks[i]) or n == len(rows) - 1:
            kept.append(row)
            while i < len(marks) and frames >= marks[i]:
                i += 1
    return kept


# The blocks of a run's ``config.yaml`` that make its training recipe (the seed aside; ``eval``,
# ``live`` and ``llm`` only say how it is watched), and those every method of one table shares
# (its method block is its own).
RECIPE_BLOCKS = ("method", "env", "train")
SHARED_BLOCKS = ("env", "train")
# Train settings that only ICCO's consistency term reads: compared between runs of one method
# that has the term, never across methods (a QMIX run's train.ce_clamp changes nothing it does).
TERM_SETTINGS = ("train.ce_clamp",)
CONVERTER = Path(__file__).resolve().parents[1] / "tools" / "convert_checkpoint.py"


def in_todays_fields(tree: dict, path: Path) -> dict:
    """A record's config in today's fields, as the library would load it: the converter's upgrade
    (a field added since it was written at the value it trained with, an option removed since
    dropped), then the schema's default for any other field added since (an option added
    without an entry in the converter's tables leaves the run as it was at its default)."""
    payload = {"cfg": copy.deepcopy(tree)}
    _converter().upgrade(payload, path)
    cfg = payload["cfg"]
    for block, defaults in _schema_defaults().items():
        if isinstance(cfg.get(block), dict):
            cfg[block] = {**defaults, **cfg[block]}
            for key, value in defaults.items():  # one level down (env.params, train.shaping)
                if isinstance(value, dict) and isinstance(cfg[block][key], dict):
                    cfg[block][key] = {**value, **cfg[block][key]}
    return cfg


@functools.cache
def _converter():
    return script(CONVERTER, "convert_checkpoint")


@functools.cache
def _schema_defaults() -> dict[str, dict]:
    """The train and env blocks of today's schema at their defaults (read-only: callers copy)."""
    return {
        block: OmegaConf.to_container(OmegaConf.structured(schema))
        for block, schema in (("train", TrainConfig), ("env", EnvConfig))
    }


def _flat(tree, prefix: str = "") -> dict:
    if not isinstance(tree, dict):
        return {prefix: tree}
    out = {}
    for key, value in tree.items():
        out.update(_flat(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def check_one_recipe(runs: dict[Path, str]) -> None:
    """Refuse to pool runs ``{folder: method}`` trained with different recipes (a record of an
    older recipe left beside the new ones): the runs of one method share their
    :data:`RECIPE_BLOCKS`, and all runs their :data:`SHARED_BLOCKS`. A mismatch is one
    line naming the two runs and the first field that differs."""
    import yaml

    configs = {}
    for folder in runs:
        path = folder / "config.yaml"
        tree = yaml.safe_load(path.read_text()) if path.is_file() else {}
        tree = in_todays_fields(tree or {}, path)
        method = tree.get("method") or {}
        term = method.get("coordinator") and (method.get("ce_coef") or method.get("entropy_coef"))
        configs[folder] = {
            k: v
            for k, v in _flat(tree).items()
            if k.split(".")[0] in RECIPE_BLOCKS and (term or k not in TERM_SETTINGS)
        }
    first_of: dict[str, Path] = {}
    for folder, method in runs.items():
        for other, blocks in ((first_of.get(method), None), (next(iter(runs)), SHARED_BLOCKS)):
            if other is None or other == folder:
                continue
            a, b = configs[other], configs[folder]
            keys = sorted(
                k
                for k in a.keys() | b.keys()
                if blocks is None or (k.split(".")[0] in blocks and k not in TERM_SETTINGS)
            )
            for key in keys:
                if a.get(key, "(absent)") != b.get(key, "(absent)"):
                    raise SystemExit(
                        f"{other.name} and {folder.name} were trained with different recipes "
                        f"({key}: {a.get(key, '(absent)')} vs {b.get(key, '(absent)')}): one table "
                        "pools one recipe; move the other's records to a folder of their own"
                    )
        first_of.setdefault(method, folder)


def score_quadrants(checkpoints: list[Path], out: Path, trials: int, *overrides: str) -> Path:
    """Four quadrants for every checkpoint in one ``icco eval`` (the scripted references play
    once, on the same episodes), coordination measures off, into ``out``; its trials file."""
    command = [
        sys.executable,
        "-m",
        "icco_torchrl",
        "eval",
        f"eval.checkpoints=[{','.join(map(str, checkpoints))}]",
        "eval.protocol=quadrants",
        f"eval.trials={trials}",
        "eval.coordination.enabled=false",
        *overrides,
        f"eval.out_dir={out}",
        f"hydra.run.dir={out}",
    ]
    print(f"four quadrants: {len(checkpoints)} checkpoints into {out}", flush=True)
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    return out / "quadrants_trials.csv"


def keep_run(run: Path, dest: Path) -> Path:
    """File the run folder ``run`` as the record ``dest``: its :data:`RECORD_FILES`
    (``timing.csv`` cut to the rows at its evaluations and its last) and, when it has a
    ``checkpoint.pt``, its policy weights (:data:`POLICY`). Returns ``dest``."""
    dest.mkdir(parents=True, exist_ok=True)
    thin = (run / "timing.csv").is_file() and (run / "eval.csv").is_file()
    for name in RECORD_FILES:
        if name == "timing.csv" and thin:
            write_csv(_thin_timing(run / name, run / "eval.csv"), dest / name)
        elif (run / name).is_file():
            shutil.copyfile(run / name, dest / name)
    if (run / "checkpoint.pt").is_file():
        export_policy(run / "checkpoint.pt", dest / POLICY)
    return dest


def keep_records(results: Path, trials: Path, records: Path) -> list[Path]:
    """File each checkpoint of an ``icco eval`` (``results``: its JSON, ``trials``: its trials
    CSV) as a record ``records/<run>/`` (:func:`keep_run`: its files and policy weights),
    ``checkpoint.json`` (its entry in the evaluation) and ``trials.csv`` (its own rows). The
    scripted references' rows go to ``records/references_trials.csv``; every evaluation plays the
    same initial configurations, so they are the same rows whichever evaluation wrote them.
    Returns the record folders."""
    with trials.open() as handle:
        rows = list(csv.DictReader(handle))
    kept = []
    for entry in json.loads(results.read_text())["checkpoints"]:
        run = Path(entry["path"]).parent
        dest = keep_run(run, records / run.name)
        (dest / "checkpoint.json").write_text(
            json.dumps({k: v for k, v in entry.items() if k != "path"}, indent=1) + "\n"
        )
        own = [{**r, "checkpoint": run.name} for r in rows if r["checkpoint"] == entry["path"]]
        write_csv(own, dest / "trials.csv")
        kept.append(dest)
    references = [r for r in rows if not r["checkpoint"]]
    if references:
        write_csv(references, records / REFERENCES_TRIALS)
    return kept
