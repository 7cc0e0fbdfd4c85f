"""What ships: a built wheel carries the Hydra configs (`icco train` works from outside the
repository), the tracked files name no path of one machine, the README stays short, and the
commands print no third-party warning."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import warnings

import pytest
from conftest import ROOT

# An absolute path of one machine: a checkout, a home folder, a scratch folder (not one inside a
# URL or a longer path: "github.com/org/work/" is fine).
MACHINE_PATH = re.compile(r"(?<![\w./-])(/work/|/root/|/home/[\w.-]+/|/tmp/[\w.-]+)")
CHECKED = (".md", ".py", ".yaml", ".json", ".sh", ".toml", ".html", ".txt", ".cfg")


def test_no_absolute_machine_paths_in_tracked_files():
    """Pages, code, configs, recorded results and kept policy weights use repository-relative
    paths (tests may build such paths on purpose and are left out)."""
    listed = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    if listed.returncode != 0:
        pytest.skip("not a git checkout")
    found = []
    for name in listed.stdout.split("\0"):
        path = ROOT / name
        if name.startswith("tests/") or not path.is_file():
            continue
        if name.endswith(".pt"):  # kept policy weights: their pickled config is plain bytes
            text = path.read_bytes().decode("latin-1")
            found += [f"{name}: {m.group(1)}" for m in MACHINE_PATH.finditer(text)]
        if not name.endswith(CHECKED):
            continue
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            found += [f"{name}:{number}: {m.group(1)}" for m in MACHINE_PATH.finditer(line)]
    assert not found, f"{len(found)} absolute machine paths:\n" + "\n".join(found[:20])


def test_the_readme_stays_short():
    """At most 160 lines: details live in docs/ and the experiment pages, linked from it."""
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 160, f"README.md has {len(lines)} lines; move details to docs/"


def test_the_machine_path_pattern_spares_urls_and_relative_paths():
    hits = ["/work/main/x", "see /root/.cache", "at /home/alice/runs", "--out /tmp/cal"]
    misses = ["https://github.com/org/work/x", "runs/tmp/x", "multirun/team_size", "/tmp"]
    assert all(MACHINE_PATH.search(text) for text in hits)
    assert not any(MACHINE_PATH.search(text) for text in misses)


def test_known_third_party_warnings_are_filtered_at_startup_and_others_still_show():
    from icco_torchrl.cli import KNOWN_WARNINGS, quiet_known_warnings

    category, message, _ = KNOWN_WARNINGS[0]
    text = message.replace("\\", "") + " and does not do anything"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        quiet_known_warnings()
        warnings.warn_explicit(text, category, "tensordict/utils.py", 1, module="tensordict.utils")
        warnings.warn_explicit(text, category, "mine.py", 1, module="mine")  # not the known source
        warnings.warn_explicit("another", category, "tensordict/utils.py", 1, "tensordict.utils")
    assert [(str(w.message), w.filename) for w in caught] == [
        (text, "mine.py"),
        ("another", "tensordict/utils.py"),
    ]


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
