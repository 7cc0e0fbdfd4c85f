"""The training pipeline through the real CLI: every method, resume, determinism, bad input.

Tests that only read a finished run, or resume or break a copy of one, share it (conftest's
``trained``: one training per set of arguments); those that only need a checkpoint to resume,
break or kill skip the reference policies (``QUICK``): they read no ``references.json``.
"""

from __future__ import annotations

import csv
import math
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
import torch
from conftest import copy_run, run_cli

from icco_torchrl import methods
from icco_torchrl.envs.reference_policies import reference_label
from icco_torchrl.training.build import compose_config
from icco_torchrl.training.checkpoint import FORMAT_VERSION, load_checkpoint
from icco_torchrl.training.run_folder import CheckpointError

SMOKE = ("experiment=smoke", "logger.progress=false")
# The smoke run without the reference policies' five evaluations at its start.
QUICK = (*SMOKE, "eval.references=[]")
# A new icco run's first half: the checkpoint the resume tests continue (each on its own copy).
HALF = (*QUICK, "train.total_frames=1024")


def read_csv(path):
    with open(path) as handle:
        return list(csv.DictReader(handle))


@pytest.mark.parametrize("method", methods.names())
def test_every_method_trains_end_to_end(trained, method):
    run = trained(f"method={method}", *SMOKE)
    rows = read_csv(run / "train.csv")
    assert int(rows[-1]["frames"]) == 2048
    assert int(rows[-1]["updates"]) > 0
    losses = [float(r["loss_td"]) for r in rows if int(r["updates"]) > 0]
    assert losses and all(
        math.isfinite(x) and x >= 0 for x in losses
    )  # logged and finite once updates start
    assert ("loss_ce" in rows[0]) == (method == "icco")
    assert len(read_csv(run / "eval.csv")) >= 2
    ckpt = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ckpt["frames"] == 2048 and ckpt["cfg"]["method"]["name"] == method
    assert (run / "learning_curve.png").stat().st_size > 0
    if method.startswith("qmix_full"):  # the paper's QMIX (FULL) reads the state as one flat vector
        assert ckpt["cfg"]["method"]["full_state"] and (
            ckpt["cfg"]["method"]["state_encoder"] == "flat"
        ) == (method == "qmix_full_flat")


def test_layer_norm_trains_end_to_end(tmp_path):
    run_cli("train", "method.layer_norm=true", *QUICK, f"hydra.run.dir={tmp_path}")
    ckpt = load_checkpoint(tmp_path / "checkpoint.pt")
    assert ckpt["cfg"]["method"]["layer_norm"] is True
    assert any("trunk_norm" in key for key in ckpt["loss"])


def test_training_reports_the_reference_policies(trained):
    import json

    run = trained("method=icco", *SMOKE)  # the default method's smoke run
    refs = json.loads((run / "references.json").read_text())
    assert list(refs) == [
        "random",
        "follower",
        "heuristic",
        "blend (r=1.75 m)",
        reference_label("best_scripted"),
    ]
    assert refs["heuristic"]["task_reward"] > refs["random"]["task_reward"] + 30
    assert refs["follower"]["inst_reward"] > refs["random"]["inst_reward"] + 30
    rows = read_csv(run / "eval.csv")
    for row in rows:  # the logged task reward is the team reward without the instruction reward
        assert float(row["task_reward"]) == pytest.approx(
            float(row["reward"]) - float(row["inst_reward"]), abs=1e-3
        )


def test_same_seed_gives_identical_metrics(tmp_path):
    run_cli("train", *QUICK, "seed=3", f"hydra.run.dir={tmp_path / 'a'}")
    # The second run also logs to wandb in offline mode: no network, no account, same metrics.
    run_cli(
        "train", *QUICK, "seed=3", "logger.wandb.mode=offline", f"hydra.run.dir={tmp_path / 'b'}"
    )
    assert list((tmp_path / "b" / "wandb").glob("offline-run-*")), "wandb offline wrote nothing"
    for stream in ("train.csv", "eval.csv"):
        assert (tmp_path / "a" / stream).read_text() == (tmp_path / "b" / stream).read_text()
    run_cli("train", *QUICK, "seed=4", "train.total_frames=1024", f"hydra.run.dir={tmp_path / 'c'}")
    c = read_csv(tmp_path / "c" / "train.csv")
    a = read_csv(tmp_path / "a" / "train.csv")[: len(c)]
    assert [r["loss_td"] for r in a] != [r["loss_td"] for r in c], "the seed has no effect"


def test_resume_continues_frames_and_schedules(tmp_path, trained):
    copy_run(trained(*HALF), tmp_path / "part")
    first = torch.load(tmp_path / "part" / "checkpoint.pt", weights_only=False)
    assert first["frames"] == 1024
    assert first["replay_segments"] > 0 and (tmp_path / "part" / "replay").is_dir()
    proc = run_cli(
        "train",
        *QUICK,
        f"resume={tmp_path / 'part' / 'checkpoint.pt'}",
        f"hydra.run.dir={tmp_path / 'other'}",
    )
    assert f"replay buffer restored: {first['replay_segments']} segments" in proc.stdout
    resumed = torch.load(tmp_path / "part" / "checkpoint.pt", weights_only=False)
    assert resumed["frames"] == 2048
    assert resumed["updates"] > first["updates"]
    rows = read_csv(tmp_path / "part" / "train.csv")
    frames = [int(r["frames"]) for r in rows]
    assert frames == sorted(frames) and frames[-1] == 2048 and len(set(frames)) == len(frames)
    eps = [float(r["epsilon"]) for r in rows]
    assert all(b <= a for a, b in zip(eps, eps[1:])), "epsilon restarted after resume"
    # The uninterrupted run reaches the same frame count.
    full = read_csv(trained("method=icco", *SMOKE) / "train.csv")
    assert int(full[-1]["frames"]) == 2048 and float(full[-1]["epsilon"]) == pytest.approx(eps[-1])


def test_resume_without_the_replay_dump_says_so_and_refills(tmp_path, trained):
    run = copy_run(trained(*HALF), tmp_path / "run")
    shutil.rmtree(run / "replay")
    proc = run_cli("train", *QUICK, f"resume={run / 'checkpoint.pt'}")
    assert "resuming with an empty buffer" in proc.stdout
    assert torch.load(run / "checkpoint.pt", weights_only=False)["frames"] == 2048


def test_unreadable_replay_dump_is_one_clear_line(tmp_path, trained):
    run = copy_run(trained(*HALF), tmp_path / "run")
    shutil.rmtree(run / "replay" / "storage")
    proc = run_cli("train", *QUICK, f"resume={run / 'checkpoint.pt'}", check=False)
    assert (
        proc.returncode == 2
        and "replay buffer dump" in proc.stderr
        and "Traceback" not in proc.stderr
    )


def test_replay_dump_can_be_turned_off(tmp_path):
    run_cli(
        "train",
        *QUICK,
        "train.total_frames=1024",
        "train.checkpoint_buffer=false",
        f"hydra.run.dir={tmp_path}",
    )
    assert not (tmp_path / "replay").exists()
    assert torch.load(tmp_path / "checkpoint.pt", weights_only=False)["replay_segments"] == 0


@pytest.mark.parametrize(
    "override, field",
    [
        ("train.total_frames=-5", "train.total_frames"),
        ("train.totl_frames=5", "train.totl_frames"),
        ("train.total_frames=lots", "train.total_frames"),
        ("train.batch_segments=100000", "train.batch_segments"),
        ("device=cuda:7", "device"),
        ("logger.wandb.mode=sometimes", "logger.wandb.mode"),
        ("method=sarsa", "method"),
        ("env.params.spawn=edge", "env.params.spawn"),
        ("env.params.n_agents=0", "env.params.n_agents"),
        ("env.params.vision_radius=-1", "env.params.vision_radius"),
        ("env.params.field_size=0", "env.params.field_size"),
        ("+env.params.bogus=1", "env.params.bogus"),
        ("llm.timeout_s=abc", "llm.timeout_s"),
        ("train.updates_per_batch=0", "train.updates_per_batch"),
        ("train.warmup_segments=30000", "train.warmup_segments"),
        ("train.lr=0", "train.lr"),
        ("train.tau=0", "train.tau"),
        ("train.env_params.max_steps=0", "train.env_params.max_steps"),
        ("train.env_params.spawn=edge", "train.env_params.spawn"),
        ("train.env_params.collect_reward=much", "train.env_params.collect_reward"),
    ],
)
def test_bad_config_fails_naming_the_field(override, field):
    with pytest.raises(Exception) as info:
        compose_config(["experiment=smoke", override])
    assert field in str(info.value)


@pytest.mark.parametrize(
    "override, message",
    [
        (
            "reward=bogus",
            "config group 'reward' has no option 'bogus'; choose from calibrated, paper",
        ),
        ("env.params.spawn=edge", "config field 'env.params.spawn' must be one of"),
    ],
)
def test_unknown_preset_or_spawn_mode_fails_before_any_work(tmp_path, override, message):
    proc = run_cli("train", *SMOKE, override, f"hydra.run.dir={tmp_path}", check=False)
    assert proc.returncode == 2 and message in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "train.csv").exists()


def test_bad_config_on_the_cli_is_one_clear_line(tmp_path):
    proc = run_cli(
        "train", *SMOKE, "train.total_frames=-5", f"hydra.run.dir={tmp_path}", check=False
    )
    assert proc.returncode == 2
    assert "train.total_frames" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "train.csv").exists()


@pytest.mark.parametrize("content", [None, b"not a checkpoint", b"PK\x03\x04truncated"])
def test_bad_checkpoint_gives_a_clear_error(tmp_path, content):
    path = tmp_path / "ckpt.pt"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(CheckpointError, match=str(path)):
        load_checkpoint(path)


def test_checkpoint_of_another_format_names_both_formats(tmp_path):
    path = tmp_path / "old.pt"
    torch.save({"format_version": FORMAT_VERSION - 1, "loss": {}}, path)
    with pytest.raises(
        CheckpointError, match=f"format {FORMAT_VERSION - 1}.*format {FORMAT_VERSION}"
    ):
        load_checkpoint(path)


def test_weights_that_do_not_fit_the_networks_are_one_clear_line(tmp_path, trained):
    run = copy_run(trained(*QUICK, "method=qmix", "train.total_frames=512"), tmp_path / "run")
    path = run / "checkpoint.pt"
    ckpt = torch.load(path, weights_only=False)
    ckpt["loss"] = {k: v for k, v in ckpt["loss"].items() if "prev_action_embed" not in k}
    torch.save(ckpt, path)
    proc = run_cli(
        "train", *QUICK, "method=qmix", "train.total_frames=1024", f"resume={path}", check=False
    )
    assert proc.returncode == 2 and "does not match the qmix networks" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_bad_checkpoint_on_the_cli_is_one_clear_line(tmp_path):
    path = tmp_path / "ckpt.pt"
    path.write_bytes(b"PK\x03\x04truncated")
    proc = run_cli(
        "train", *SMOKE, f"resume={path}", f"hydra.run.dir={tmp_path / 'run'}", check=False
    )
    assert proc.returncode == 2
    assert (
        "truncated" in proc.stderr and str(path) in proc.stderr and "Traceback" not in proc.stderr
    )


def test_incompatible_checkpoint_is_refused(tmp_path, trained):
    copy_run(trained(*QUICK, "method=qmix", "train.total_frames=512"), tmp_path / "q")
    proc = run_cli(
        "train",
        *QUICK,
        "method=icco",
        f"resume={tmp_path / 'q' / 'checkpoint.pt'}",
        f"hydra.run.dir={tmp_path / 'i'}",
        check=False,
    )
    assert (
        proc.returncode == 2
        and "incompatible" in proc.stderr
        and "method.coordinator" in proc.stderr
    )


LONG_RUN = (
    "logger.progress=false",
    "train.total_frames=10000000",
    "env.num_envs=8",
    "train.warmup_segments=16",
    "train.batch_segments=16",
)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.fault
def test_ctrl_c_and_sigterm_save_a_checkpoint_and_exit_cleanly(tmp_path, sig):
    cmd = [sys.executable, "-m", "icco_torchrl", "train", *LONG_RUN, f"hydra.run.dir={tmp_path}"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and not (tmp_path / "train.csv").exists():
        time.sleep(0.5)
    time.sleep(1.0)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=180)
    assert proc.returncode == 0, err[-2000:]
    ckpt = load_checkpoint(tmp_path / "checkpoint.pt")
    assert 0 < ckpt["frames"] < 10_000_000
    assert (
        f"interrupted by {signal.Signals(sig).name}" in out
        and f"icco train resume={tmp_path}" in out
    )


def _frames(path):
    return [int(r["frames"]) for r in read_csv(path)]


@pytest.mark.fault
def test_kill_9_then_resume_logs_every_frame_once(tmp_path):
    """SIGKILL after a checkpoint (rows already logged past it), resume: the CSVs have the frame
    column of an uninterrupted same-seed run (values differ: the env state is not checkpointed)."""
    budget = (
        "train.total_frames=4096",
        "train.checkpoint_interval=1024",
        "train.eval_interval=1024",
    )
    run = tmp_path / "killed"
    proc = subprocess.Popen(
        [sys.executable, "-m", "icco_torchrl", "train", *QUICK, *budget, f"hydra.run.dir={run}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 150
    while (
        time.time() < deadline and proc.poll() is None
    ):  # until rows exist past the last checkpoint
        if (run / "checkpoint.pt").exists() and (run / "train.csv").exists():
            try:
                saved = load_checkpoint(run / "checkpoint.pt")["frames"]
            except CheckpointError:
                saved = None  # being written
            if saved and _frames(run / "train.csv")[-1] > saved:
                break
        time.sleep(0.2)
    proc.kill()
    proc.wait(timeout=30)
    assert proc.returncode != 0, "the run finished before it could be killed"
    run_cli("train", *QUICK, *budget, f"resume={run / 'checkpoint.pt'}")
    run_cli("train", *QUICK, *budget, f"hydra.run.dir={tmp_path / 'whole'}")
    for stream in ("train.csv", "eval.csv", "timing.csv"):
        assert _frames(run / stream) == _frames(tmp_path / "whole" / stream), stream


def test_a_bare_resume_continues_the_run_with_its_own_method_seed_and_budget(tmp_path):
    run_cli(
        "train",
        *QUICK,
        "method=qmix",
        "seed=3",
        "train.total_frames=1024",
        f"hydra.run.dir={tmp_path}",
    )
    ckpt = tmp_path / "checkpoint.pt"
    # Only the new budget is given: method, seed and the smoke settings are the run's own.
    run_cli("train", "logger.progress=false", f"resume={ckpt}", "train.total_frames=2048")
    saved = torch.load(ckpt, weights_only=False)
    assert (
        saved["frames"] == 2048
        and saved["cfg"]["method"]["name"] == "qmix"
        and saved["cfg"]["seed"] == 3
    )
    assert saved["cfg"]["env"]["num_envs"] == 8  # experiment=smoke's, not the default 32
    # Nothing given: the budget is the one it was last saved with (reached): nothing more to do.
    proc = run_cli("train", "logger.progress=false", f"resume={ckpt}")
    assert "done: 2,048 env steps" in proc.stdout
    assert torch.load(ckpt, weights_only=False)["updates"] == saved["updates"]


def test_a_resume_into_a_given_folder_keeps_the_runs_method_fields(tmp_path):
    # a non-default method field (and the smoke budget) must survive a resume that names its run
    # folder
    run_cli(
        "train",
        *QUICK,
        "method.waypoint_features=false",
        "train.total_frames=512",
        f"hydra.run.dir={tmp_path}",
    )
    run_cli(
        "train",
        "logger.progress=false",
        f"resume={tmp_path / 'checkpoint.pt'}",
        "train.total_frames=1024",
        f"hydra.run.dir={tmp_path}",
    )
    saved = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert saved["frames"] == 1024 and saved["cfg"]["method"]["waypoint_features"] is False


def test_training_env_params_shape_the_training_env_only():
    from icco_torchrl.training.build import build

    cfg = compose_config(["experiment=smoke", "train.env_params.collect_reward=3.5"])
    run = build(cfg, for_training=True)
    assert run.env.base_env.event_rewards["collect"] == 3.5
    assert run.eval_env.base_env.event_rewards["collect"] == 1.0  # the evaluations during training
    assert build(cfg).env.base_env.event_rewards["collect"] == 1.0  # restore, icco eval/instruct
    assert (
        run.env.base_env.event_rewards["pick"] == run.eval_env.base_env.event_rewards["pick"] == 5.0
    )


def test_training_env_params_survive_a_resume_and_may_change_there(tmp_path):
    run_cli(
        "train",
        *QUICK,
        "train.env_params.collect_reward=3.5",
        "train.total_frames=512",
        f"hydra.run.dir={tmp_path}",
    )
    ckpt = tmp_path / "checkpoint.pt"
    run_cli("train", "logger.progress=false", f"resume={ckpt}", "train.total_frames=1024")
    assert (
        torch.load(ckpt, weights_only=False)["cfg"]["train"]["env_params"]["collect_reward"] == 3.5
    )
    # A curriculum: the shaping changes at resume (the seed and env.params may not), and says so.
    proc = run_cli(
        "train",
        "logger.progress=false",
        f"resume={ckpt}",
        "train.total_frames=1536",
        "train.env_params.collect_reward=null",
    )
    assert "instead of {'collect_reward': 3.5}" in proc.stdout
    saved = torch.load(ckpt, weights_only=False)
    assert saved["frames"] == 1536 and saved["cfg"]["train"]["env_params"]["collect_reward"] is None


def test_resume_continues_in_the_checkpoint_folder():
    from icco_torchrl.commands.train import prepare_train

    def overrides(*args):
        return prepare_train("train", list(args))[0]

    # Hydra's .hydra/ record is written by the command once the run folder is locked.
    quiet = "hydra.output_subdir=null"
    assert overrides("resume=/a/b/checkpoint.pt") == [
        "resume=/a/b/checkpoint.pt",
        quiet,
        "hydra.run.dir=/a/b",
    ]
    assert overrides("resume=x.pt", "hydra.run.dir=D") == ["resume=x.pt", "hydra.run.dir=D", quiet]
    assert overrides("seed=1") == ["seed=1", quiet]
    assert prepare_train("train", ["seed=1"])[1] == {"record": ".hydra"}
    assert prepare_train("train", ["hydra.output_subdir=rec"]) == ([quiet], {"record": "rec"})
    assert prepare_train("train", ["hydra.output_subdir=null"])[1] == {"record": None}


@pytest.mark.parametrize(
    "override, named",
    [
        ("seed=5", "seed"),
        ("env.params.pick_reward=9", "env"),
        ("train.eps_decay_frames=5", "train.eps_decay_frames"),
    ],
)
def test_resume_refuses_overrides_it_cannot_honour(tmp_path, trained, override, named):
    run = copy_run(trained(*HALF), tmp_path / "run")
    config = (run / "config.yaml").read_text()
    proc = run_cli("train", *QUICK, f"resume={run / 'checkpoint.pt'}", override, check=False)
    assert proc.returncode == 2 and f"cannot change {named}" in proc.stderr, proc.stderr
    assert (run / "config.yaml").read_text() == config


def test_a_config_error_leaves_no_run_folder(tmp_path):
    proc = run_cli(
        "train", *SMOKE, "train.lr=abc", f"hydra.run.dir={tmp_path / 'run'}", check=False
    )
    assert proc.returncode == 2 and not (tmp_path / "run").exists()


@pytest.mark.fault
def test_repeated_kills_inside_checkpoints_and_dumps_lose_nothing(tmp_path):
    """Three SIGKILLs while the run checkpoints (and dumps its replay buffer) after every batch,
    each followed by a resume: the CSVs end with the uninterrupted run's frame column, the
    checkpoint loads, and no temp file or folder survives."""
    budget = (
        "train.total_frames=6144",
        "train.checkpoint_interval=128",
        "train.eval_interval=1024",
    )
    run = tmp_path / "killed"
    command = [sys.executable, "-m", "icco_torchrl", "train", *QUICK, *budget]
    kills = 0
    for delay in (1.0, 2.0, 3.0):
        resume = (
            [f"resume={run / 'checkpoint.pt'}"]
            if (run / "checkpoint.pt").exists()
            else [f"hydra.run.dir={run}"]
        )
        proc = subprocess.Popen(
            [*command, *resume], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        deadline = time.time() + 120
        while (
            time.time() < deadline and proc.poll() is None and not (run / "checkpoint.pt").exists()
        ):
            time.sleep(0.1)
        time.sleep(delay)
        if proc.poll() is None:
            proc.kill()
            kills += 1
        proc.wait(timeout=30)
    assert kills >= 2, "the run finished before it could be killed"
    proc = run_cli("train", *QUICK, *budget, f"resume={run / 'checkpoint.pt'}")
    assert "replay buffer restored" in proc.stdout
    run_cli("train", *QUICK, *budget, f"hydra.run.dir={tmp_path / 'whole'}")
    for stream in ("train.csv", "eval.csv", "timing.csv"):
        assert _frames(run / stream) == _frames(tmp_path / "whole" / stream), stream
    assert load_checkpoint(run / "checkpoint.pt")["frames"] == 6144
    assert not [p.name for p in run.iterdir() if p.name.endswith(".tmp")]


def test_an_exported_policy_acts_like_its_checkpoint_and_cannot_be_resumed(tmp_path, trained):
    from icco_torchrl.training.checkpoint import export_policy
    from icco_torchrl.training.restore import restore

    run = copy_run(trained(*HALF), tmp_path / "run")
    small = export_policy(run / "checkpoint.pt", run / "policy.pt")
    assert small.stat().st_size < 0.6 * (run / "checkpoint.pt").stat().st_size
    full, slim = restore(run / "checkpoint.pt", num_envs=2), restore(small, num_envs=2)
    a, b = full["loss"].state_dict(), slim["loss"].state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a if not k.startswith("target_"))
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    td = full["env"].reset()
    with (
        torch.no_grad(),
        set_exploration_type(ExplorationType.DETERMINISTIC),
    ):  # greedy, coordinator mean
        assert torch.equal(
            full["policy"](td.clone())["agents", "action_value"],
            slim["policy"](td.clone())["agents", "action_value"],
        )
    proc = run_cli("train", *QUICK, f"resume={small}", check=False)
    assert proc.returncode == 2 and "is an exported policy" in proc.stderr


def _popen_train(*args):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "WANDB_MODE": "disabled", "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        [sys.executable, "-m", "icco_torchrl", "train", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


@pytest.mark.fault
def test_two_resumes_of_one_checkpoint_at_once_the_second_is_refused_in_one_line(tmp_path):
    run_cli("train", *QUICK, "train.total_frames=512", f"hydra.run.dir={tmp_path}")
    ckpt = tmp_path / "checkpoint.pt"
    first = _popen_train("logger.progress=false", f"resume={ckpt}", "train.total_frames=10000000")
    lock = tmp_path / ".train.lock"
    deadline = time.time() + 120
    while time.time() < deadline and first.poll() is None:
        if lock.is_file() and lock.read_text().strip() == str(first.pid):
            break
        time.sleep(0.2)
    try:
        second = run_cli(
            "train", "logger.progress=false", f"resume={ckpt}", "train.lr=0.5", check=False
        )
    finally:
        first.send_signal(signal.SIGTERM)
        out, err = first.communicate(timeout=180)
    assert second.returncode == 2, second.stderr
    # The refused resume wrote nothing: Hydra's record is the running run's.
    record = (tmp_path / ".hydra" / "overrides.yaml").read_text()
    assert "train.total_frames=10000000" in record and "train.lr=0.5" not in record, record
    assert "lr: 0.5" not in (tmp_path / ".hydra" / "config.yaml").read_text()
    assert len(second.stderr.strip().splitlines()) == 1, second.stderr
    assert f"run folder {tmp_path} is in use by another icco train (pid {first.pid})" in (
        second.stderr
    )
    assert first.returncode == 0 and "interrupted by SIGTERM" in out, err[-2000:]
    frames = _frames(tmp_path / "train.csv")
    assert frames == sorted(frames) and len(set(frames)) == len(frames), "a frame logged twice"
    assert load_checkpoint(ckpt)["frames"] == frames[-1]


@pytest.mark.fault
def test_sigterm_in_the_final_evaluation_leaves_a_run_that_resume_completes(tmp_path):
    # eval_interval=0: the final evaluation is the first, so it runs after the last checkpoint.
    budget = ("train.total_frames=1024", "train.eval_interval=0")
    proc = _popen_train(*QUICK, *budget, f"hydra.run.dir={tmp_path}")
    for line in proc.stdout:
        if "[eval] final evaluation at 1024 frames" in line:
            proc.send_signal(signal.SIGTERM)
            break
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err[-2000:]
    assert "interrupted by SIGTERM during the final evaluation" in out, out
    stopped = out[out.index("stopped:") :]
    assert "learning_curve.png" not in stopped and "(writes the" in stopped
    ckpt = load_checkpoint(tmp_path / "checkpoint.pt")
    assert ckpt["frames"] == 1024 and not ckpt["outputs"]["learning_curve"]
    # The resume trains nothing, writes what is missing, and says only what exists.
    proc = run_cli("train", "logger.progress=false", f"resume={tmp_path / 'checkpoint.pt'}")
    assert "done: 1,024 env steps" in proc.stdout and "final greedy evaluation" in proc.stdout
    assert "figure: learning_curve.png" in proc.stdout
    assert (tmp_path / "learning_curve.png").stat().st_size > 0
    assert _frames(tmp_path / "eval.csv") == [1024]  # evaluated once, not twice
    saved = load_checkpoint(tmp_path / "checkpoint.pt")
    assert saved["outputs"]["final_evaluation"] and saved["outputs"]["learning_curve"]
    assert saved["updates"] == ckpt["updates"]
    # Once complete, a resume changes nothing and repeats the final metrics.
    again = run_cli("train", "logger.progress=false", f"resume={tmp_path / 'checkpoint.pt'}")
    assert "final greedy evaluation" in again.stdout and "[eval]" not in again.stdout
    assert _frames(tmp_path / "eval.csv") == [1024]


def test_the_finish_message_names_only_files_that_exist(tmp_path):
    from icco_torchrl.trainer import finish_message

    (tmp_path / "train.csv").write_text("frames\n1\n")
    (tmp_path / "learning_curve.png").write_bytes(b"partial")  # written, but not recorded
    outputs = {"final_evaluation": False, "learning_curve": False}
    message = finish_message(
        tmp_path, tmp_path / "checkpoint.pt", 1024, True, {}, outputs, pending=True
    )
    assert "metrics: train.csv (columns: docs/metrics.md)\n" in message + "\n"
    assert "eval.csv" not in message
    assert "learning_curve.png" not in message and "checkpoint:" not in message
    assert "(writes the final evaluation and the learning curve)" in message
    (tmp_path / "checkpoint.pt").write_bytes(b"x")
    done = finish_message(tmp_path, tmp_path / "checkpoint.pt", 1024, False, {}, {})
    assert "figure: learning_curve.png" in done and "checkpoint:" in done
    # The share of the best scripted team it reached, from its references.json.
    (tmp_path / "references.json").write_text(
        '{"follower": {"reward": 70.0}, "best scripted (defend=inf, collect=1, deliver=2 m)": '
        '{"reward": 100.0}}'
    )
    final = dict(reward=90.0, task_reward=1.0, pick=1.0, defense=1.0)
    done = finish_message(tmp_path, tmp_path / "checkpoint.pt", 1024, False, final, {})
    assert "  90 % of the best scripted team's reward on the same episodes (100.0)" in done
    (tmp_path / "references.json").write_text("not json")
    assert "best scripted" not in finish_message(
        tmp_path, tmp_path / "checkpoint.pt", 1024, False, final, {}
    )


def test_a_signal_before_the_loop_stops_at_once_but_never_inside_a_checkpoint_write():
    from icco_torchrl.training.interrupt import Interrupted, StopAtOnce

    order = []
    with StopAtOnce() as stop:
        with pytest.raises(Interrupted):
            with stop.held():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)
                order.append("write finished")
        assert order == ["write finished"] and stop.signal_name == "SIGTERM"
    with StopAtOnce():
        with pytest.raises(Interrupted):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)


def test_policy_snapshots_keep_the_weights_of_every_evaluation(tmp_path, trained):
    """train.policy_snapshots: one weights-only file per eval.csv row, named by its frames; the
    last is the exported policy of the final checkpoint, and an earlier one differs from it."""
    from icco_torchrl.training.checkpoint import export_policy, load_checkpoint
    from icco_torchrl.training.logger import read_column

    run = trained(*QUICK, "train.policy_snapshots=true", "train.eval_interval=1024")
    frames = [int(f) for f in read_column(run, "eval", "reward")[0]]
    snapshots = sorted((run / "policies").glob("*.pt"))
    assert [int(p.stem) for p in snapshots] == frames and len(frames) >= 2
    last, first = load_checkpoint(snapshots[-1]), load_checkpoint(snapshots[0])
    final = load_checkpoint(export_policy(run / "checkpoint.pt", tmp_path / "policy.pt"))
    assert last["policy_only"] and last["frames"] == frames[-1] == final["frames"]
    assert not any(k.startswith("target_") for k in last["loss"])
    assert set(last["loss"]) == set(final["loss"])
    assert all(torch.equal(last["loss"][k], final["loss"][k]) for k in final["loss"])
    assert not all(torch.equal(first["loss"][k], final["loss"][k]) for k in final["loss"])
