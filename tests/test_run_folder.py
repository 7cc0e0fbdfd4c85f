"""A run folder through the real CLI: a run refused by its lock (held by another run, or a lock
file that is a link) writes nothing into it, Hydra's ``.hydra/`` record included."""

from __future__ import annotations

import os

import pytest
from conftest import run_cli

from icco_torchrl.training.run_folder import LOCK_FILE, RunFolderLock

pytestmark = pytest.mark.fault


def _snapshot(folder):
    """Every entry under ``folder`` (itself included): its bytes (a link: its target) and times."""
    out = {}
    for path in [folder, *sorted(folder.rglob("*"))]:
        info = os.lstat(path)
        if path.is_symlink():
            content = os.readlink(path)
        elif path.is_file():
            content = path.read_bytes()
        else:
            content = sorted(p.name for p in path.iterdir())
        out[str(path.relative_to(folder))] = (content, info.st_mtime_ns, info.st_size)
    return out


def _run_folder(tmp_path):
    """What a run folder holds as far as a refused resume can tell: a checkpoint (unreadable
    here: the refusal comes before it is read), Hydra's record, its log and a metrics file."""
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text("train:\n  lr: 0.001\n")
    (run / ".hydra" / "overrides.yaml").write_text("- train.lr=0.001\n")
    (run / "cli.log").write_text("")
    (run / "train.csv").write_text("frames\n128\n")
    (run / "checkpoint.pt").write_bytes(b"PK\x03\x04 a checkpoint")
    return run


def test_a_resume_refused_by_the_lock_writes_nothing_into_the_running_runs_folder(tmp_path):
    run = _run_folder(tmp_path)
    with RunFolderLock(run):  # the running run (this process)
        before = _snapshot(run)
        proc = run_cli(
            "train",
            "logger.progress=false",
            f"resume={run / 'checkpoint.pt'}",
            "train.lr=0.5",
            check=False,
        )
        after = _snapshot(run)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"icco train: run folder {run} is in use by another icco train (pid {os.getpid()}): "
        "wait for it to end, or stop it first"
    ]
    assert after == before  # .hydra/ says lr 0.001, as the running run trains


def test_a_resume_on_a_folder_whose_lock_is_a_link_leaves_the_target_untouched(tmp_path):
    run = _run_folder(tmp_path)
    victim = tmp_path / "elsewhere.txt"
    victim.write_text("not a lock\n")
    (run / LOCK_FILE).symlink_to(victim)
    before = _snapshot(run)
    proc = run_cli("train", "logger.progress=false", f"resume={run / 'checkpoint.pt'}", check=False)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f"its {LOCK_FILE} is a symbolic link" in lines[0], lines
    assert victim.read_text() == "not a lock\n"
    assert _snapshot(run) == before


def test_a_failed_command_leaves_a_folder_that_a_run_holds(tmp_path):
    from icco_torchrl.cli import _remove_if_only_hydra

    folder = tmp_path / "run"
    with RunFolderLock(folder):  # a run that has just begun: its folder holds only the lock
        (folder / "cli.log").write_text("")
        _remove_if_only_hydra(str(folder))
        assert (folder / LOCK_FILE).is_file()
    _remove_if_only_hydra(str(folder))  # no run holds it: Hydra's empty folder goes
    assert not folder.exists()
