"""Shared test helpers: one CPU thread (stable on shared machines), a CLI runner, finished
training runs shared by the tests that only read or resume them, bridge + fleet."""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
torch.set_num_threads(1)

# The files of minutes-long tests (the compiling tests, the CLI trainings), run first: pytest-xdist
# hands tests to its workers in collection order, so the last ones left are short and the workers
# finish together instead of one waiting for the other's last training.
SLOW_FIRST = ("test_fast_update.py", "test_train_cli.py", "test_collector_process.py")


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: else as collected


def pytest_configure(config):
    """Under ``--dist loadgroup`` an ``xdist_group`` reaches its worker as a ``@group`` suffix of
    the test's id, which pytest 9 ignores when pytest-xdist 3.8 writes it: the group's tests then
    spread over the workers, and the second compiling test waits out the first's cold compile on
    a lock, one core idle. Refuse that pair in one line (pyproject.toml pins pytest below 9)."""
    if getattr(config.option, "dist", "no") != "loadgroup":
        return
    import xdist

    versions = [
        tuple(int(x) for x in v.split(".")[:2]) for v in (pytest.__version__, xdist.__version__)
    ]
    if versions[0] >= (9, 0) and versions[1] <= (3, 8):
        raise pytest.UsageError(
            f"pytest {pytest.__version__} with pytest-xdist {xdist.__version__} does not keep an "
            "xdist_group on one worker under --dist loadgroup: make install (pytest < 9)"
        )


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


def session_dir(tmp_path_factory, name: str) -> Path:
    """The folder ``name`` of this test session, shared by its xdist workers (whose own base
    folders lie in the session's), created if missing."""
    base = tmp_path_factory.getbasetemp()
    folder = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / name
    folder.mkdir(exist_ok=True)
    return folder


@contextlib.contextmanager
def locked(path: Path):
    """The block run by one test process at a time (an exclusive ``flock`` on ``path``)."""
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def trained(tmp_path_factory):
    """``trained(*args) -> folder``: a finished ``icco train ARGS`` run (:func:`run_cli`), trained
    once per test session (its xdist workers included) and shared by every test that asks for the
    same ``args`` (training is deterministic: the same args give the same run). Read it as it is;
    to resume, break or otherwise change it, work on :func:`copy_run`'s copy."""
    root = session_dir(tmp_path_factory, "trained")

    def train(*args: str) -> Path:
        name = hashlib.sha1("\0".join(args).encode()).hexdigest()[:12]
        folder, done = root / name, root / f"{name}.done"
        with locked(root / f"{name}.lock"):
            if not done.exists():
                shutil.rmtree(folder, ignore_errors=True)  # a failed attempt's
                run_cli("train", *args, f"hydra.run.dir={folder}")
                done.write_text(" ".join(args) + "\n")
        return folder

    return train


def copy_run(folder: Path, to: Path) -> Path:
    """A copy of the run folder ``folder`` at ``to`` (its checkpoint, logs and replay dump name
    their files relative to the folder: the copy resumes as the original would)."""
    shutil.copytree(folder, to)
    return to


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
