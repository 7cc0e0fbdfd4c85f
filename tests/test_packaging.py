"""A built wheel carries the Hydra configs: `icco train` works from outside the repository."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

from conftest import ROOT


def test_wheel_installs_and_trains_from_outside_the_repo(tmp_path):
    had_build = (ROOT / "build").exists()
    try:
        subprocess.run(
            [
                sys.executable,
                "-m",
                "pip",
                "wheel",
                str(ROOT),
                "--no-deps",
                "--no-build-isolation",
                "-q",
                "-w",
                str(tmp_path / "dist"),
            ],
            check=True,
            capture_output=True,
            timeout=300,
        )
    finally:
        if not had_build:  # setuptools builds in the source tree
            shutil.rmtree(ROOT / "build", ignore_errors=True)
    wheel = next((tmp_path / "dist").glob("icco_torchrl-*.whl"))
    site = tmp_path / "site"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--no-deps",
            "-q",
            "--target",
            str(site),
            str(wheel),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    # PYTHONPATH puts the installed wheel ahead of the editable install of the dev environment.
    env = {
        **os.environ,
        "PYTHONPATH": str(site),
        "OMP_NUM_THREADS": "1",
        "WANDB_MODE": "disabled",
        "LITELLM_LOCAL_MODEL_COST_MAP": "True",
    }
    where = subprocess.run(
        [sys.executable, "-c", "from icco_torchrl.paths import CONF_DIR; print(CONF_DIR)"],
        cwd=outside,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    assert where.stdout.strip() == str(site / "icco_torchrl" / "conf")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "icco_torchrl",
            "train",
            "experiment=smoke",
            "logger.progress=false",
            "hydra.run.dir=run",
        ],
        cwd=outside,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (outside / "run" / "checkpoint.pt").is_file() and (
        outside / "run" / "eval.csv"
    ).is_file()
