"""Learning curves across seeds: mean ± std per method from the runs' CSVs, as CSV and PNG/PDF.

    python experiments/aggregate.py multirun/four_quadrants                   # greedy eval reward
    python experiments/aggregate.py runs multirun --stream train --column episode_defense

A run is any folder holding ``config.yaml`` and ``<stream>.csv`` (what ``icco train`` writes);
folders are searched recursively and grouped by method (its paper name, " w/o TR" for agents
trained on the instruction reward alone). Writes ``<out>.png``, ``<out>.pdf`` and ``<out>.csv``
(frames, then mean/std/seeds per method) and prints each method's final value.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from omegaconf import OmegaConf

from icco_torchrl.evaluation.metrics import Curve, learning_curves, method_label
from icco_torchrl.evaluation.plots import plot_curves


def find_runs(roots, stream: str = "eval") -> dict[str, list[Path]]:
    """``{method label: [run folder, ...]}`` of the runs under ``roots`` with ``stream``.csv."""
    runs: dict[str, list[Path]] = {}
    for root in map(Path, roots):
        for config in sorted(root.rglob("config.yaml")):
            if (config.parent / f"{stream}.csv").is_file() and ".hydra" not in config.parts:
                label = method_label(OmegaConf.to_container(OmegaConf.load(config), resolve=False))
                runs.setdefault(label, []).append(config.parent)
    return runs


def write_curves(curves: dict[str, Curve], path: Path) -> Path:
    """One row per frame of the first method's grid; other methods' values where they have one."""
    grids = {
        label: dict(zip(c.frames.tolist(), zip(c.mean.tolist(), c.std.tolist())))
        for label, c in curves.items()
    }
    frames = sorted({f for grid in grids.values() for f in grid})
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(
            ["frames"] + [f"{label} {k}" for label in curves for k in ("mean", "std", "seeds")]
        )
        for f in frames:
            row = [f]
            for label, curve in curves.items():
                mean, std = grids[label].get(f, ("", ""))
                row += [mean, std, len(curve.runs)]
            writer.writerow(row)
    return path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("roots", nargs="+", help="folders to search for runs")
    parser.add_argument(
        "--stream", default="eval", help="eval (greedy evaluations) or train (training episodes)"
    )
    parser.add_argument(
        "--column", default="reward", help="column to average, e.g. reward, episode_reward, pick"
    )
    parser.add_argument(
        "--out", type=Path, default=Path("learning_curves"), help="output path without suffix"
    )
    args = parser.parse_args(argv)
    runs = find_runs(args.roots, args.stream)
    curves = learning_curves(runs, args.stream, args.column)
    if not curves:
        print(
            f"no run under {args.roots} has values in column {args.column!r} of {args.stream}.csv",
            file=sys.stderr,
        )
        return 2
    args.out.parent.mkdir(parents=True, exist_ok=True)
    paths = plot_curves(curves, args.out, ylabel=f"{args.stream} {args.column}") + [
        write_curves(curves, args.out.with_suffix(".csv"))
    ]
    for label, curve in curves.items():
        print(
            f"{label}: {curve.mean[-1]:.2f} ± {curve.std[-1]:.2f} at {int(curve.frames[-1])} "
            f"frames ({len(curve.runs)} seeds)"
        )
    print("wrote " + ", ".join(map(str, paths)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


# Markdown tables of the rendered pages, read back and rewritten by the report scripts.
def table_rows(table: str) -> list[list[str]]:
    return [[c.strip() for c in line.strip().strip("|").split("|")] for line in table.splitlines()]


def table_at(text: str, header: str) -> tuple[int, int, list[list[str]]]:
    """The Markdown table of ``text`` whose header line starts with ``header``: its start and end
    offsets and its rows as cells (the header first, without the separator line)."""
    start = text.index(header)
    end = text.find("\n\n", start)
    table = text[start : len(text) if end < 0 else end]
    rows = table_rows(table)
    return start, start + len(table), [rows[0], *rows[2:]]


def markdown_rows(rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0])]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows[1:]])
