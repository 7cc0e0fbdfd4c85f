"""Shared test helpers: one CPU thread (stable on shared machines), a CLI runner, bridge + fleet."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
torch.set_num_threads(1)


def run_cli(
    *args: str, cwd: Path | None = None, timeout: float = 300, check: bool = True
) -> subprocess.CompletedProcess:
    """Run ``python -m icco_torchrl ARGS`` as a user would, offline, one thread."""
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "WANDB_MODE": "disabled",
        "LITELLM_LOCAL_MODEL_COST_MAP": "True",
    }
    proc = subprocess.run(
        [sys.executable, "-m", "icco_torchrl", *args],
        cwd=cwd or ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    if check and proc.returncode != 0:
        raise AssertionError(
            f"icco {' '.join(args)} failed "
            f"({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
        )
    return proc


@contextlib.contextmanager
def bridge_with_fleet(bridge, fleet, seconds: float):
    """``bridge`` and ``fleet`` serving each other in threads for at most ``seconds``; stopped,
    joined and closed on exit (also when the test fails)."""
    stop = threading.Event()
    threads = [
        threading.Thread(target=bridge.serve, args=(stop, seconds), daemon=True),
        threading.Thread(target=fleet.run, args=(stop, seconds), daemon=True),
    ]
    for t in threads:
        t.start()
    try:
        yield
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=10)
        bridge.close()
        fleet.close()
