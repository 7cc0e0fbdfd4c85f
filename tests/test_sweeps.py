"""Hydra sweeps: the basic launcher and submitit_local (when the extra is installed)."""

from __future__ import annotations

import pytest
from conftest import run_cli

TINY = (
    "experiment=smoke",
    "logger.progress=false",
    "train.total_frames=256",
    "train.eval_interval=0",
    "train.checkpoint_interval=0",
    "eval.trials=2",
    "train.eval_envs=2",
    "eval.references=[]",
)


def test_basic_multirun_makes_one_folder_per_run(tmp_path):
    run_cli("train", "-m", "method=qmix,icco", *TINY, f"hydra.sweep.dir={tmp_path}")
    for name in ("qmix_seed0", "icco_seed0"):
        assert (tmp_path / name / "checkpoint.pt").exists()
        assert (tmp_path / name / "train.csv").read_text().startswith("frames,")


def test_submitit_local_two_job_sweep(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    run_cli(
        "train",
        "-m",
        "hydra/launcher=local_cpu",
        "seed=0,1",
        "method=qmix",
        *TINY,
        f"hydra.sweep.dir={tmp_path}",
        timeout=600,
    )
    for seed in (0, 1):
        assert (tmp_path / f"qmix_seed{seed}" / "checkpoint.pt").exists()
    assert list(tmp_path.glob(".submitit/*")), "the jobs did not go through submitit"
