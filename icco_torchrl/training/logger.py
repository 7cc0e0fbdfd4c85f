"""One logger for a run: CSV files always, wandb when asked (offline by default in docs, never
required).

Streams are CSV files in the run folder, one per kind of row (``train``, ``eval``, ``timing``):
a stream's columns are fixed by its first row, and a later row with other keys is an error
rather than silently dropped data. ``timing`` holds wall-clock figures (SPS, timers) so the
other streams are bit-identical between two runs with the same seed.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf


def truncate_after(path: Path, frames: int) -> int:
    """Drop the rows of a CSV stream whose ``frames`` exceed ``frames`` (atomic rewrite); returns
    how many were dropped. Files without a ``frames`` column are left alone."""
    with path.open(newline="") as handle:
        rows = list(csv.reader(handle))
    if not rows or "frames" not in rows[0]:
        return 0
    col = rows[0].index("frames")
    keep = [rows[0]] + [r for r in rows[1:] if r and float(r[col]) <= frames]
    dropped = len(rows) - len(keep)
    if dropped:
        tmp = path.with_name(f".{path.name}.tmp")
        with tmp.open("w", newline="") as handle:
            csv.writer(handle).writerows(keep)
        os.replace(tmp, path)
    return dropped


class RunLogger:
    def __init__(
        self,
        run_dir: str | Path,
        cfg: DictConfig,
        *,
        total_frames: int,
        initial_frames: int = 0,
        truncate: bool = False,
    ):
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if truncate:  # a resumed run: rows logged after its checkpoint are logged again
            for path in self.run_dir.glob("*.csv"):
                truncate_after(path, initial_frames)
        self._files: dict[str, tuple[Any, csv.DictWriter, list[str]]] = {}
        self._wandb = None
        wb = cfg.logger.wandb
        if wb.mode != "disabled":
            os.environ.setdefault("WANDB_SILENT", "true")
            import wandb  # lazy: heavy import, optional at run time

            self._wandb = wandb.init(
                mode=wb.mode,
                project=wb.project,
                entity=wb.entity,
                group=wb.group or cfg.method.name,
                dir=str(self.run_dir),
                name=f"{cfg.method.name}_seed{cfg.seed}",
                config=OmegaConf.to_container(cfg, resolve=True),
            )
        self._bar = None
        if cfg.logger.progress:
            from tqdm import tqdm

            # One throughput on the bar: the postfix's env-steps/s (collection + training, the SPS
            # of timing.csv); tqdm's own rate would also count evaluations and checkpoints.
            self._bar = tqdm(
                total=total_frames,
                initial=initial_frames,
                unit="env steps",
                dynamic_ncols=True,
                desc=f"{cfg.method.name} seed {cfg.seed}",
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} "
                "[{elapsed}<{remaining}{postfix}]",
            )

    def log(self, stream: str, row: dict[str, float]) -> None:
        """Append ``row`` to ``<run_dir>/<stream>.csv`` (and to wandb as ``stream/key``)."""
        row = {k: (float(v) if not isinstance(v, (int, str)) else v) for k, v in row.items()}
        if stream not in self._files:
            path = self.run_dir / f"{stream}.csv"
            exists = path.exists() and path.stat().st_size > 0
            handle = path.open("a", newline="")
            fields = list(row) if not exists else next(csv.reader(path.open()))
            writer = csv.DictWriter(handle, fieldnames=fields)
            if not exists:
                writer.writeheader()
            self._files[stream] = (handle, writer, fields)
        handle, writer, fields = self._files[stream]
        if set(row) != set(fields):
            raise KeyError(f"{stream}.csv has columns {fields}, row has {sorted(row)}")
        writer.writerow(row)
        handle.flush()
        if self._wandb is not None:
            step = int(row.get("frames", 0))
            self._wandb.log(
                {f"{stream}/{k}": v for k, v in row.items() if k != "frames"}, step=step
            )

    def progress(self, frames: int, **postfix: float) -> None:
        if self._bar is None:
            return
        self._bar.update(frames - self._bar.n)
        self._bar.set_postfix(
            {
                k: (f"{v:.3g}" if isinstance(v, float) and math.isfinite(v) else v)
                for k, v in postfix.items()
            },
            refresh=False,
        )

    def print(self, message: str) -> None:
        """A line for the console that does not break the progress bar."""
        if self._bar is not None:
            self._bar.write(message)
        else:
            print(message, flush=True)

    def close(self) -> None:
        for handle, _, _ in self._files.values():
            handle.close()
        self._files.clear()
        if self._bar is not None:
            self._bar.close()
        if self._wandb is not None:
            self._wandb.finish()


def read_column(
    run_dir: str | Path, stream: str, column: str
) -> tuple[np.ndarray, np.ndarray] | None:
    """``(frames, values)`` of a run's ``{stream}.csv`` (empty or NaN values left out)."""
    path = Path(run_dir) / f"{stream}.csv"
    if not path.is_file():
        return None
    with path.open() as handle:
        reader = csv.DictReader(handle)
        if column not in (reader.fieldnames or []):
            raise ValueError(f"{path} has no column {column!r} (columns: {reader.fieldnames})")
        pairs = [
            (float(r["frames"]), float(r[column])) for r in reader if r[column] not in ("", "nan")
        ]
    if not pairs:
        return None
    frames, values = map(np.array, zip(*pairs))
    return frames, values


def last_evaluation(run_dir: str | Path, frames: int) -> dict | None:
    """The metrics of ``eval.csv``'s last row when it is at ``frames`` (a stopped run's evaluation
    of its last frame), else None."""
    path = Path(run_dir) / "eval.csv"
    if not path.is_file():
        return None
    with path.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    if not rows or not rows[-1].get("frames") or float(rows[-1]["frames"]) != frames:
        return None
    out = {}
    for key, value in rows[-1].items():
        try:
            out[key] = float(value)
        except (TypeError, ValueError):
            out[key] = math.nan
    out.pop("frames", None)
    return out


def clock_seconds(timing_row: dict) -> float:
    """A ``timing.csv`` row's run clock in seconds: the sum of its ``time_*`` timers (collection,
    updates, evaluations), so waits outside the run (a paused job, a resume) do not count."""
    return sum(float(v) for k, v in timing_row.items() if k.startswith("time_"))
