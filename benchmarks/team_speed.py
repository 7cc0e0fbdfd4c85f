"""Fixed-size training at ``n_agents=3`` before and after the any-team change, side by side.

The any-team change (per-env team sizes, absent-robot masks, masked networks; commit c7556b1
and the two after it) must not slow today's fixed-size path. This script exports the commit
before it (``--baseline``, 031a02c) into a temporary folder and runs the same
``benchmarks/train_speed.py`` (1 thread, the default recipe, both update paths) in that tree
and in this one, in turn for ``--rounds`` rounds, so load on the machine falls on both alike.
Reported per tree: the median over rounds of end-to-end env steps per second and ms per update,
and their ratios (this tree over the baseline). Writes ``benchmarks/results/team_speed.json``.

    .venv/bin/python benchmarks/team_speed.py                    # 3 rounds, 20 batches each
    .venv/bin/python benchmarks/team_speed.py --rounds 1 --batches 5
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
BASELINE = "031a02c"  # the compiled update, before per-env team sizes (c7556b1)


def export(commit: str, dest: Path) -> Path:
    """The tracked files of ``commit`` under ``dest`` (no worktree metadata to clean up)."""
    dest.mkdir(parents=True)
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", commit], check=True, capture_output=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest


def train_speed(tree: Path, batches: int, out: Path) -> dict:
    """One ``train_speed.py`` run inside ``tree``, importing that tree's package."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    name = f"team_speed_{os.getpid()}.json"
    command = [
        sys.executable,
        str(tree / "benchmarks" / "train_speed.py"),
        "--threads",
        "1",
        "--batches",
        str(batches),
        "--run-dir",
        str(out / "runs"),
        "--out",
        name,
    ]
    where = subprocess.run(
        [sys.executable, "-c", "import icco_torchrl; print(icco_torchrl.__file__)"],
        env=env,
        cwd=tree,
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    if not Path(where).is_relative_to(tree):
        raise SystemExit(f"team_speed: {tree} imports icco_torchrl from {where}")
    subprocess.run(command, env=env, cwd=tree, check=True)
    path = tree / "benchmarks" / "results" / name
    payload = json.loads(path.read_text())
    path.unlink()  # the results folder keeps only team_speed.json
    return {**payload["results"][0], "cpu": payload["cpu"]}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default=BASELINE, help="commit to compare against")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--batches", type=int, default=20, help="collector batches per path")
    args = parser.parse_args(argv)
    head = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    rows: dict[str, list[dict]] = {"baseline": [], "current": []}
    with tempfile.TemporaryDirectory(prefix="team_speed_") as tmp:
        trees = {"baseline": export(args.baseline, Path(tmp) / "tree"), "current": ROOT}
        for r in range(args.rounds):
            for name, tree in trees.items():
                print(f"round {r + 1}/{args.rounds}: {name}", flush=True)
                rows[name].append(train_speed(tree, args.batches, Path(tmp)))
    summary = {}
    for name, runs in rows.items():
        summary[name] = {
            path: {
                key: statistics.median(run["paths"][path][key] for run in runs)
                for key in ("env_steps_per_s", "ms_per_update", "ops_per_update")
            }
            for path in ("eager", "compiled")
        }
    ratios = {
        path: {
            "env_steps_per_s": summary["current"][path]["env_steps_per_s"]
            / summary["baseline"][path]["env_steps_per_s"],
            "ms_per_update": summary["current"][path]["ms_per_update"]
            / summary["baseline"][path]["ms_per_update"],
        }
        for path in ("eager", "compiled")
    }
    for path, ratio in ratios.items():
        print(
            f"{path}: env steps/s {ratio['env_steps_per_s']:.3f}x, ms/update "
            f"{ratio['ms_per_update']:.3f}x (current over {args.baseline})"
        )
    payload = {
        "baseline": args.baseline,
        "current": head,
        "threads": 1,
        "rounds": args.rounds,
        "batches": args.batches,
        "cpu": rows["current"][0].get("cpu"),
        "median": summary,
        "current_over_baseline": ratios,
        "runs": rows,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "team_speed.json").write_text(json.dumps(payload, indent=1) + "\n")


if __name__ == "__main__":
    main()
