"""``icco eval`` end to end on smoke checkpoints: tables, figures, clean refusals."""

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import locked, session_dir

from icco_torchrl.cli import main
from icco_torchrl.envs.reference_policies import reference_label
from icco_torchrl.evaluation.metrics import learning_curves
from icco_torchrl.evaluation.plots import plot_curves
from icco_torchrl.evaluation.runner import find_checkpoints
from icco_torchrl.training.build import compose_config

# A seconds-long training run: a checkpoint with real weights, nothing learned (the evaluations
# here give their own eval.references).
SMOKE = [
    "experiment=smoke",
    "train.total_frames=256",
    "train.eval_interval=0",
    "train.checkpoint_interval=0",
    "train.eval_envs=2",
    "eval.references=[]",
    "logger.progress=false",
]


def icco(*args: str) -> int:
    """The real command line (``icco ARGS``: Hydra, config validation, the command) run in this
    process, which has paid for its imports already; returns the exit code."""
    argv = sys.argv
    try:
        main(list(args))
    except SystemExit as exit_info:
        return exit_info.code
    finally:
        sys.argv = argv
    return 0


def smoke_checkpoints(tmp_path_factory, methods) -> dict[str, Path]:
    """``{method: checkpoint}``, trained once per test run (in parallel), shared by modules and
    by the xdist workers (one trains, another waits for it)."""
    root = session_dir(tmp_path_factory, "smoke_checkpoints")
    with locked(root / ".lock"):
        _train_missing(root, methods)
    return {m: root / m / "checkpoint.pt" for m in methods}


def _train_missing(root: Path, methods) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "WANDB_MODE": "disabled"}
    jobs = {
        m: subprocess.Popen(
            [
                sys.executable,
                "-m",
                "icco_torchrl",
                "train",
                f"method={m}",
                *SMOKE,
                f"hydra.run.dir={root / m}",
            ],
            cwd=root,
            env=env,
            text=True,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        for m in methods
        if not (root / m / "checkpoint.pt").exists()
    }
    for method, job in jobs.items():
        out, _ = job.communicate(timeout=300)
        assert job.returncode == 0, f"smoke training of {method} failed:\n{out}"


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    return smoke_checkpoints(tmp_path_factory, ["icco", "qmix"])


def test_eval_compares_two_methods_and_writes_tables_and_figures(checkpoints, tmp_path, capsys):
    out = tmp_path / "eval"
    code = icco(
        "eval",
        f"eval.checkpoints=[{checkpoints['icco']},{checkpoints['qmix']}]",
        "eval.protocol=quadrants",
        "eval.trials=2",
        "eval.steps=6",
        "eval.gif=true",
        f"eval.out_dir={out}",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    )
    printed = capsys.readouterr()
    assert code == 0, printed.err
    table = [
        line for line in (out / "quadrants.md").read_text().splitlines() if line.startswith("| ")
    ]
    whole = table[
        : table.index("| method | quadrant 1 | quadrant 2 | quadrant 3 | quadrant 4 | episode |")
    ]
    refs = [
        "random",
        "follower",
        "heuristic",
        "blend (r=1.75 m)",
        reference_label("best_scripted"),
    ]  # eval.references, on the same episodes
    assert [row.split(" | ")[0] for row in whole[1:]] == ["| ICCO", "| QMIX"] + [
        f"| {r}" for r in refs
    ]
    assert "| ICCO | 2 (1 seed) |" in printed.out  # the table is printed too
    rows = list(csv.DictReader((out / "quadrants_trials.csv").open()))
    assert len(rows) == 7 * 2 * 5  # (methods + references) x trials x (4 quadrants + episode)
    assert {r["method"] for r in rows} == {"ICCO", "QMIX", *refs}
    summary = json.loads((out / "quadrants.json").read_text())
    assert [c["method"] for c in summary["checkpoints"]] == ["ICCO", "QMIX"]
    for name in (
        "quadrants_summary.csv",
        "quadrants_reward.png",
        "quadrants_reward.pdf",
        "quadrants_trajectories.png",
        "quadrants_trajectories.pdf",
        "quadrants_icco.gif",
        "quadrants_qmix.gif",
    ):
        assert (out / name).stat().st_size > 0, name


def test_a_checkpoint_for_another_env_layout_is_refused_cleanly(checkpoints, tmp_path, capsys):
    code = icco(
        "eval",
        f"checkpoint={checkpoints['icco']}",
        "env.params.n_resources=4",
        "eval.trials=2",
        "eval.steps=4",
        f"hydra.run.dir={tmp_path}",
    )
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("icco eval: ") and len(err.strip().splitlines()) == 1
    assert "another env layout" in err and "n_resources: trained 6, evaluated 4" in err


def test_without_a_checkpoint_the_newest_run_is_used_or_the_user_is_told_to_train(tmp_path):
    cfg = compose_config([])
    with pytest.raises(ValueError, match="run `make train` first"):
        find_checkpoints(cfg, root=tmp_path)
    for name, mtime in (("old", 1_000), ("new", 2_000)):
        path = tmp_path / "runs" / "icco" / name / "checkpoint.pt"
        path.parent.mkdir(parents=True)
        path.touch()
        os.utime(path, (mtime, mtime))
    assert find_checkpoints(cfg, root=tmp_path) == [
        tmp_path / "runs" / "icco" / "new" / "checkpoint.pt"
    ]
    with pytest.raises(ValueError, match="'nowhere/\\*.pt' matched no file"):
        find_checkpoints(compose_config(["eval.checkpoints=[nowhere/*.pt]"]))


def test_learning_curves_average_seeds(tmp_path):
    runs = []
    for seed, rewards in enumerate(([0.0, 2.0, 4.0], [2.0, 4.0, 6.0])):
        run = tmp_path / f"seed{seed}"
        run.mkdir()
        lines = ["frames,reward,reward_std"] + [
            f"{f},{r},0" for f, r in zip((0, 100, 200), rewards)
        ]
        (run / "eval.csv").write_text("\n".join(lines) + "\n")
        runs.append(run)
    curves = learning_curves({"ICCO": runs + [tmp_path / "no_csv_yet"]})
    assert curves["ICCO"].mean.tolist() == [1.0, 3.0, 5.0] and curves["ICCO"].std.tolist() == [
        1.0,
        1.0,
        1.0,
    ]
    assert len(curves["ICCO"].runs) == 2
    assert all(p.stat().st_size > 0 for p in plot_curves(curves, tmp_path / "curves"))


ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "assets" / "demo_icco.pt"


def _tree(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*")}


def test_eval_and_instruct_on_the_demo_policy_write_under_runs_not_assets(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    assets = _tree(ROOT / "assets")
    quick = ("eval.trials=2", "eval.steps=4", "eval.references=[]")
    assert icco("eval", f"checkpoint={DEMO}", *quick) == 0, capsys.readouterr().err
    assert icco("instruct", "Go right", f"checkpoint={DEMO}", *quick) == 0, capsys.readouterr().err
    assert _tree(ROOT / "assets") == assets, "a command wrote into assets/"
    written = sorted(p.name for p in (tmp_path / "runs" / "demo_icco").iterdir())
    assert written[0] == "eval_random_walk" and written[1].startswith("instruct_go_right_")
    assert (tmp_path / "runs" / "demo_icco" / "eval_random_walk" / "random_walk.md").is_file()
    # eval.out_dir still wins.
    assert icco("eval", f"checkpoint={DEMO}", *quick, f"eval.out_dir={tmp_path / 'mine'}") == 0
    assert (tmp_path / "mine" / "random_walk.md").is_file()


def test_results_of_a_run_folder_checkpoint_stay_beside_it(tmp_path):
    from icco_torchrl.commands import results_dir

    run = tmp_path / "runs" / "icco" / "seed0"
    run.mkdir(parents=True)
    assert results_dir(None, [run / "checkpoint.pt"], "eval_quadrants") == run / "eval_quadrants"
    assert results_dir(None, [DEMO], "eval_quadrants") == Path("runs/demo_icco/eval_quadrants")
    assert results_dir("elsewhere", [DEMO], "eval_quadrants") == Path("elsewhere")


def _text(path):
    path.write_text("epoch 1: loss 0.52\n")


def _fields_missing(path):
    import torch

    from icco_torchrl.training.checkpoint import FORMAT_VERSION

    torch.save({"format_version": FORMAT_VERSION}, path)


@pytest.mark.parametrize("make", [_text, _fields_missing])
def test_eval_of_an_unreadable_checkpoint_is_one_plain_line(tmp_path, capsys, make):
    path = tmp_path / "checkpoint.pt"
    make(path)
    code = icco("eval", f"checkpoint={path}", "eval.trials=2", f"hydra.run.dir={tmp_path / 'h'}")
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("icco eval: ") and len(err.strip().splitlines()) == 1, err
    assert str(path) in err and "Traceback" not in err and "KeyError" not in err


# ---------------------------------------------------------------- another team size, another beta
def test_a_checkpoint_trained_on_3_robots_is_evaluated_with_5(checkpoints, tmp_path, capsys):
    out = tmp_path / "eval"
    code = icco(
        "eval",
        f"checkpoint={checkpoints['icco']}",
        "eval.protocol=quadrants",
        "eval.trials=2",
        "eval.steps=4",
        "eval.team_size=5",
        "eval.references=[blend]",
        f"eval.out_dir={out}",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    )
    assert code == 0, capsys.readouterr().err
    payload = json.loads((out / "quadrants.json").read_text())
    assert payload["team_size"] == 5 and "teams of 5 robots" in (out / "quadrants.md").read_text()
    [entry] = payload["checkpoints"]
    assert entry["team_size"] == 5 and entry["trained_team_size"] == 3
    assert "n_agents: trained 3, evaluated 5" in entry["env_differences"]
    episode = {r["method"]: r for r in payload["summary"] if r["segment"] == "episode"}
    assert set(episode) == {"ICCO", "blend (r=1.75 m)"}  # the reference at the same size
    # beta = 0: every robot gets z every T = 4 steps of the 16; a policy without one has no rate.
    assert episode["ICCO"]["broadcast_rate"] == pytest.approx(0.25)
    assert episode["blend (r=1.75 m)"]["broadcast_rate"] is None


def test_another_team_size_loads_the_acting_weights_and_acts_for_every_robot(checkpoints):
    import torch

    from icco_torchrl.training.checkpoint import load_checkpoint
    from icco_torchrl.training.restore import restore

    saved = load_checkpoint(checkpoints["icco"])["loss"]
    run = restore(checkpoints["icco"], num_envs=2, n_agents=5)
    assert run.layout.n_agents == 5 and run.env.base_env.n_agents == 5
    state = run.loss.state_dict()
    acting = [k for k in saved if k.startswith(("agent_params.", "coordinator_params."))]
    assert len(acting) > 10 and all(torch.equal(state[k], saved[k]) for k in acting)
    # The QMixer of 5 robots has other shapes than the checkpoint's: it stays fresh.
    mixer = [k for k in saved if k.startswith("mixer_params.")]
    assert any(state[k].shape != saved[k].shape for k in mixer)
    acted = run.policy(run.env.reset())
    assert acted.get(("agents", "action")).shape[:2] == (2, 5)


@pytest.fixture(scope="module")
def flat_checkpoint(tmp_path_factory):
    return smoke_checkpoints(tmp_path_factory, ["qmix_full_flat"])["qmix_full_flat"]


def test_networks_tied_to_one_team_size_are_refused_at_another_in_one_line(
    flat_checkpoint, tmp_path, capsys
):
    quick = ("eval.trials=2", "eval.steps=4", "eval.references=[]")
    code = icco(
        "eval",
        f"checkpoint={flat_checkpoint}",
        "eval.team_size=5",
        *quick,
        f"hydra.run.dir={tmp_path}",
    )
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("icco eval: ") and len(err.strip().splitlines()) == 1, err
    assert "cannot act in a team of 5 robots (trained with n_agents=3)" in err
    assert "state_encoder=flat" in err and "eval.team_size=3" in err
    # At its own size it is evaluated as before.
    out = tmp_path / "own"
    code = icco(
        "eval",
        f"checkpoint={flat_checkpoint}",
        "eval.team_size=3",
        *quick,
        f"eval.out_dir={out}",
        f"hydra.run.dir={tmp_path}",
    )
    assert code == 0 and (out / "random_walk.json").is_file()


@pytest.mark.parametrize(
    "override, field",
    [
        ("eval.team_size=0", "eval.team_size"),
        ("eval.broadcast_threshold=-0.5", "eval.broadcast_threshold"),
    ],
)
def test_a_bad_team_size_or_beta_is_one_line_naming_the_field(
    checkpoints, tmp_path, capsys, override, field
):
    code = icco("eval", f"checkpoint={checkpoints['icco']}", override, f"hydra.run.dir={tmp_path}")
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and field in err, err


def test_checkpoints_of_different_team_sizes_need_an_explicit_one(checkpoints, tmp_path):
    from icco_torchrl.evaluation.runner import team_size
    from icco_torchrl.training.checkpoint import load_checkpoint, save_checkpoint

    four = load_checkpoint(checkpoints["icco"])
    four["cfg"]["env"]["params"]["n_agents"] = 4
    save_checkpoint(tmp_path / "four.pt", four)
    both = [checkpoints["icco"], tmp_path / "four.pt"]
    with pytest.raises(ValueError, match="different team sizes .*: give eval.team_size=K"):
        team_size(compose_config([]), both)
    assert team_size(compose_config(["eval.team_size=6"]), both) == 6
    assert team_size(compose_config([]), both[1:]) == 4  # default: the checkpoints' own


def test_the_broadcast_threshold_override_reaches_the_coordinator(checkpoints):
    from icco_torchrl.evaluation.protocols import quadrant_schedule, run_schedule, schedule_env
    from icco_torchrl.modules.coordinator import Coordinator

    rates = {}
    for beta in (None, 1e9):
        restored = schedule_env(checkpoints["icco"], 16, 2, broadcast_threshold=beta)
        coordinators = [m for m in restored.policy.modules() if isinstance(m, Coordinator)]
        assert coordinators and {c.threshold for c in coordinators} == {beta or 0.0}
        assert restored.cfg.method.broadcast_threshold == (beta or 0.0)
        run = run_schedule(restored.env, restored.policy, quadrant_schedule(4), 2)
        rates[beta] = float(run.per_step["broadcast_rate"].mean())
    assert rates[None] == pytest.approx(0.25)  # the checkpoint's beta = 0: every T = 4 steps
    assert rates[1e9] == pytest.approx(1 / 16)  # z never moves that far: only the first step's
    qmix = schedule_env(checkpoints["qmix"], 16, 2, broadcast_threshold=0.5)  # nothing to set
    run = run_schedule(qmix.env, qmix.policy, quadrant_schedule(4), 2)
    assert all(r["broadcast_rate"] != r["broadcast_rate"] for r in run.rows)  # NaN: no coordinator


def test_without_any_checkpoint_the_error_says_how_to_evaluate_the_demo_policy(
    tmp_path, monkeypatch
):
    monkeypatch.chdir(Path(__file__).resolve().parents[1])  # the checkout, as `make eval` runs
    with pytest.raises(ValueError) as err:
        find_checkpoints(compose_config([]), root=tmp_path)
    message = str(err.value)
    assert "\n" not in message and "run `make train` first" in message
    assert "icco eval checkpoint=assets/demo_icco.pt (assets/README.md)" in message


def test_the_env_difference_note_says_which_differences_change_the_scores():
    import inspect

    from icco_torchrl.envs import ResourceCollectionEnv
    from icco_torchrl.evaluation.runner import REWARD_WEIGHTS, UNUSED_IN_EVAL, difference_effect

    text = difference_effect(["n_agents", "pick_reward", "waypoint_path_prob", "accel"])
    assert text.startswith("changed by n_agents, accel (the task differs")
    assert "; reward columns only, by pick_reward (counts and behaviour unchanged)" in text
    assert text.endswith(
        "; unchanged by waypoint_path_prob (the protocol sets the episode length "
        "and writes the waypoints)"
    )
    assert difference_effect(["waypoint_sigma"]).startswith("unchanged by waypoint_sigma")
    # both lists name env parameters (a renamed one would silently count as score-changing)
    params = inspect.signature(ResourceCollectionEnv.__init__).parameters
    assert set(UNUSED_IN_EVAL + REWARD_WEIGHTS) <= set(params)


def test_eval_measures_a_coordinator_and_leaves_qmix_na(checkpoints, tmp_path):
    """The coordination columns (docs/consistency.md): per checkpoint with a coordinator, in the
    JSON summary rows, the summary CSV and a table of their own; none for QMIX; none at all with
    eval.coordination.enabled=false."""
    args = [
        f"eval.checkpoints=[{checkpoints['icco']},{checkpoints['qmix']}]",
        "eval.trials=2",
        "eval.steps=6",
        "eval.references=[]",
        "eval.coordination.episodes=4",
        "eval.coordination.fit_steps=5",
    ]
    out = tmp_path / "measured"
    assert icco("eval", *args, f"eval.out_dir={out}", f"hydra.run.dir={out}") == 0
    report = json.loads((out / "random_walk.json").read_text())
    rows = {r["method"]: r for r in report["summary"] if r["segment"] == "episode"}
    for column in ("mi_bound", "mi_null", "consistency", "swap_agreement", "own_agreement"):
        assert isinstance(rows["ICCO"][column], float), column
        assert rows["QMIX"][column] is None, column  # n/a: no coordinator
    icco_entry, qmix_entry = report["checkpoints"]
    assert icco_entry["coordination"]["mi"]["windows"] == [3 * 36, 36]
    assert "coordination" not in qmix_entry
    assert "## Coordinator: information and consistency" in (out / "random_walk.md").read_text()
    assert "mi_bound" in (out / "random_walk_summary.csv").read_text().splitlines()[0]
    skipped = tmp_path / "skipped"
    flag = "eval.coordination.enabled=false"
    assert icco("eval", *args, flag, f"eval.out_dir={skipped}", f"hydra.run.dir={skipped}") == 0
    report = json.loads((skipped / "random_walk.json").read_text())
    assert all("mi_bound" not in r for r in report["summary"])
