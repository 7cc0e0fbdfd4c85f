"""The experiment scripts' run lists compose into valid configs (a typo there would only show
after hours), and the README's count of the VMAS example's ICCO lines is the example's."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from icco_torchrl.training.build import compose_config

ROOT = Path(__file__).resolve().parents[1]


def _load(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_recipe_lever_composes_and_trains_its_method():
    levers = _load(ROOT / "experiments" / "recipe" / "run.py").LEVERS
    assert len(levers) > 20
    for name, (_, _, method, overrides) in levers.items():
        cfg = compose_config([f"method={method}", *overrides])
        assert cfg.method.name == method, name
    shaped = compose_config(["method=qmix", *levers["collect35_qmix"][3]])
    assert shaped.train.env_params.collect_reward == 3.5 and shaped.env.params.collect_reward == 1.0


def test_every_sequence_replay_screen_and_benchmark_recipe_composes():
    screens = _load(ROOT / "experiments" / "sequence_replay" / "run.py")
    for name, (_, _, method, overrides) in screens.SCREENS.items():
        cfg = compose_config([f"method={method}", *screens.BUDGET, *overrides])
        t = cfg.train
        replayed = t.updates_per_batch * t.batch_segments * t.sequence_length
        assert replayed == 8 * cfg.env.num_envs * t.steps_per_batch, name  # the replay ratio
    recipes = _load(ROOT / "benchmarks" / "train_throughput.py").RECIPES
    for name, overrides in recipes.items():
        t = compose_config(["method=icco", *overrides]).train
        frames = 32 * t.steps_per_batch if "envs64" not in name else 64 * t.steps_per_batch
        replayed = t.updates_per_batch * t.batch_segments * t.sequence_length
        assert replayed == 8 * frames, name  # 8 replayed transitions per collected one
    skill = _load(ROOT / "benchmarks" / "time_to_skill.py")
    for overrides in skill.RECIPES.values():
        compose_config(["method=icco", *skill.BUDGET, *overrides])


def _icco_glue_lines(path: Path) -> int:
    """Lines of the simple statements whose last line is marked ``# ICCO`` (as formatted)."""
    import ast

    text = path.read_text()
    lines = text.splitlines()
    counted = set()
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.stmt) and not hasattr(node, "body"):
            if "# ICCO" in lines[node.end_lineno - 1]:
                counted.update(range(node.lineno, node.end_lineno + 1))
    return len(counted)


def test_readme_states_the_vmas_example_glue():
    import re

    glue = _icco_glue_lines(ROOT / "examples" / "vmas_qmix.py")
    stated = re.search(r"plus\s+(\d+)\s+lines\s+of\s+ICCO", (ROOT / "README.md").read_text())
    assert stated and int(stated.group(1)) == glue, glue


def test_benchmarks_readme_is_rendered_from_the_results():
    report = _load(ROOT / "benchmarks" / "report.py")
    readme = (ROOT / "benchmarks" / "README.md").read_text()
    assert readme == report.render(), "stale: run python benchmarks/report.py"


def test_four_quadrant_bar_checks_both_scripted_ends_and_half_the_blends_work():
    report = _load(ROOT / "experiments" / "four_quadrants" / "report.py")

    def row(method, reward, pick=0.0, collect=0.0, defense=0.0, in_quadrant=0.0):
        return dict(
            method=method,
            reward=reward,
            pick=pick,
            collect=collect,
            defense=defense,
            in_quadrant=in_quadrant,
        )

    refs = {
        "follower": row("follower", 280.0, 2.0, 1.0, 5.0, 0.7),
        "heuristic": row("heuristic", 300.0, 40.0, 40.0, 30.0, 0.2),
        "blend (r=1.75 m)": row("blend (r=1.75 m)", 370.0, 16.0, 14.0, 30.0, 0.5),
    }
    # Past the heuristic (the better end), exactly half the blend's picks, short of its
    # deliveries, its defenses met, in quadrant less often than the blend.
    rows = {"ICCO": row("ICCO", 301.0, 8.0, 6.9, 15.0, 0.49)}
    lines = report.criteria(rows, refs)
    assert "the heuristic's" in lines[0]
    assert lines[1] == (
        "  - ICCO: 3 of 5 met (team 301.0 vs 300.0 met; picks 8.0 vs 8.0 met; deliveries 6.9 vs "
        "7.0 NOT met; defenses 15.0 vs 15.0 met; in quadrant 0.49 vs 0.50 NOT met)."
    )
    assert report.criteria(rows, {"follower": refs["follower"]}) == [
        "- Reference policies missing: the bar is not checked."
    ]


def test_a_sweeps_note_is_quoted_on_its_page_and_absent_without_one():
    report = _load(ROOT / "experiments" / "four_quadrants" / "report.py")
    assert report.sweep_note({}) == ""
    assert report.sweep_note({"note": "**Recipe.** a\n\nb\n"}) == "> **Recipe.** a\n>\n> b\n\n"


def test_team_size_runs_compose_with_the_any_team_networks_and_their_team_sizes():
    run = _load(ROOT / "experiments" / "team_size" / "run.py")
    for budget in (["experiment=repro_cpu"], list(run.jobs.SMOKE_BUDGET)):
        for method in run.METHODS:
            mixed = compose_config(run.run_overrides(method, "mixed", 1, budget))
            fixed = compose_config(run.run_overrides(method, "fixed3", 1, budget))
            for cfg in (mixed, fixed):
                assert cfg.method.name == method and cfg.seed == 1
                assert (cfg.method.mixer, cfg.method.posterior_input) == ("attention", "tokens")
            assert mixed.env.params.n_agents == 4 and list(mixed.train.team_sizes) == [2, 3, 4]
            assert fixed.env.params.n_agents == 3 and fixed.train.team_sizes is None
    assert (
        compose_config(run.run_overrides("icco", "mixed", 0, ["experiment=repro_cpu"])).train[
            "total_frames"
        ]
        == 800_000
    )
    # --train-beta: the same run with the threshold in training, in its own folder.
    trained = compose_config(run.run_overrides("icco", "mixed", 1, ["experiment=repro_cpu"], 4.0))
    assert trained.method.broadcast_threshold == 4.0 and list(trained.train.team_sizes) == [2, 3, 4]
    assert mixed.method.broadcast_threshold == 0.0
    assert run.run_dir(ROOT, "icco", "mixed", 1, 4.0).name == "icco_mixed_beta4_seed1"
    assert run.run_dir(ROOT, "icco", "mixed", 1).name == "icco_mixed_seed1"
    with pytest.raises(SystemExit):
        run.main(["--train-beta", "0"])


def _team_size_results(points_5_6: dict, betas: list[tuple[float, float, float]]) -> dict:
    """A small results.json: ``{label: (reward per robot at 5, at 6)}`` (the blend's under
    "blend"), and beta sweep points ``(beta, team reward, broadcast rate)`` at T = 4."""

    def entry(method, k, per_robot, trained_on):
        return dict(
            method=method,
            kind="reference" if trained_on is None else "trained",
            trained_on=trained_on,
            team_size=k,
            trials=2,
            seeds=1,
            reward=per_robot * k,
            reward_std=1.0,
            reward_per_robot=per_robot,
            reward_per_robot_std=1.0 / k,
            broadcast_rate=None,
            broadcast_rate_std=None,
        )

    sizes = []
    for label, values in points_5_6.items():
        trained_on = None if label == "blend" else ([3] if label.endswith("(3)") else [2, 3, 4])
        for k, value in zip((5, 6), values):
            if value is not None:
                sizes.append(
                    entry(label if label != "blend" else "blend (r=1.75 m)", k, value, trained_on)
                )
    points = [
        dict(
            method="ICCO (2-4)",
            beta=b,
            team_size=3,
            reward=r,
            reward_std=2.0,
            reward_per_robot=r / 3,
            broadcast_rate=rate,
            broadcast_rate_std=0.0,
        )
        for b, r, rate in betas
    ]
    return dict(
        smoke=False,
        frames=800_000,
        checkpoint_frames=800_256,
        budget=["experiment=repro_cpu"],
        seeds=[0],
        trials=2,
        steps=145,
        episode_steps=580,
        period=4,
        team_sizes=[5, 6],
        sizes=sizes,
        beta_sweep=dict(team_size=3, points=points),
        commands=["icco train ..."],
        machine=dict(cpu="test"),
        wall_s=dict(train=60.0, eval=6.0),
    )


def test_team_size_report_checks_both_targets_from_the_numbers(tmp_path):
    report = _load(ROOT / "experiments" / "team_size" / "report.py")
    sweep = [(0.0, 300.0, 0.25), (0.5, 310.0, 0.1), (1.0, 280.0, 0.05), (2.0, 200.0, 0.02)]
    results = _team_size_results(
        {
            "blend": (10.0, 9.0),
            "ICCO (2-4)": (8.5, 7.0),  # 85 % at 5, 78 % at 6: not met
            "QMIX (FULL) (2-4)": (8.0, 7.65),  # 80 % and 85 %: met
            "ICCO (3)": (100.0, 100.0),  # not trained on 2-4: not a candidate
        },
        sweep,
    )
    zero_shot, beta = report.targets(results).splitlines()
    assert zero_shot.endswith(
        "**: met (by QMIX (FULL) (2-4)). ICCO (2-4): 5 robots 8.50 vs 10.00 per robot (85 %), "
        "met; 6 robots 7.00 vs 9.00 per robot (78 %), NOT met. QMIX (FULL) (2-4): 5 robots 8.00 "
        "vs 10.00 per robot (80 %), met; 6 robots 7.65 vs 9.00 per robot (85 %), met."
    )
    # beta = 0.5 sends 40 % of the every-T broadcasts (too many); beta = 1 sends 20 %, keeps 93 %.
    assert beta.endswith(
        "**: met: beta = 1 sends 20 % of the every-T broadcasts (broadcast rate 0.050 of "
        "robot-steps, every T: 0.250) and keeps 280.0 of 300.0 (93 %)."
    )
    lower = _team_size_results({"blend": (10.0, 9.0), "ICCO (2-4)": (7.0, None)}, sweep[:2])
    zero_shot, beta = report.targets(lower).splitlines()
    assert "**: not met. ICCO (2-4): 5 robots 7.00 vs 10.00 per robot (70 %), NOT met" in zero_shot
    assert "6 robots not evaluated" in zero_shot
    assert (
        "**: not measured (no beta sent <= 25 % of the every-T broadcasts; the fewest: 40 %" in beta
    )
    worse = _team_size_results({"ICCO (2-4)": (7.0, 7.0)}, [(0.0, 300.0, 0.25), (1.0, 250.0, 0.05)])
    zero_shot, beta = report.targets(worse).splitlines()
    assert zero_shot.endswith(
        "**: not measured. ICCO (2-4): 5 robots not evaluated; 6 robots not evaluated."
    )
    assert "**: not met: beta = 1 sends 20 %" in beta and "(83 %)." in beta
    assert report.targets(None).count("not measured (the experiment has not been run)") == 2

    path = tmp_path / "results.json"
    path.write_text(json.dumps(results))
    readme = tmp_path / "README.md"
    assert report.main([str(path), "--readme", str(readme)]) == 0
    assert "Not run (`run.py --beta-screen CHECKPOINT...`)." in readme.read_text()
    screen = {
        "period": 4,
        "checkpoints": ["multirun/x/icco_seed1/checkpoint.pt"],
        "eval_overrides": ["eval.trials=20", "eval.steps=145"],
        "beta_sweep": dict(results["beta_sweep"], policy="ICCO (3, 5M)"),
        "commands": ["icco eval ..."],
    }
    (tmp_path / "beta_screen.json").write_text(json.dumps(screen))
    assert report.main([str(path), "--readme", str(readme)]) == 0
    text = readme.read_text()
    assert "- **Screen: at a broadcast rate <= 25 % ICCO keeps >= 90 % of its every-T team " in text
    assert "ICCO (3, 5M) at 3 robots, T = 4." in text and "`icco_seed1`" in text
    assert "| QMIX (FULL) (2-4) | 8.00 ± 0.20 | 7.65 ± 0.17 |" in text
    assert "| 1 | 280.0 ± 2.0 | 93.33 | 0.050 | 20 % | 93 % | – |" in text  # no in_quadrant
    assert (
        "![team reward against broadcast rate](figures/beta_sweep.png)" in text and "$" not in text
    )
    for name in ("reward_per_robot.png", "beta_sweep.png"):
        assert (tmp_path / "figures" / name).stat().st_size > 0
    assert "Not run (`run.py --train-beta B`)." in text

    # --train-beta's sweep: read against its own every-T reward (270) and the beta = 0 policy's.
    trained = dict(
        screen,
        train_beta=4.0,
        seeds=[0, 1],
        frames=800_256,
        train_command="icco train ... method.broadcast_threshold=4 hydra.run.dir=...",
        beta_sweep=dict(
            team_size=3,
            policy="ICCO (2-4, trained at beta = 4)",
            points=[
                dict(p, beta=b, reward=r, broadcast_rate=rate)
                for p, (b, r, rate) in zip(
                    results["beta_sweep"]["points"], [(0.0, 270.0, 0.25), (4.0, 255.0, 0.05)]
                )
            ],
        ),
    )
    (tmp_path / "beta_trained.json").write_text(json.dumps(trained))
    assert report.main([str(path), "--readme", str(readme)]) == 0
    text = readme.read_text()
    assert (
        "- **Trained at beta = 4: at a broadcast rate <= 25 % ICCO keeps >= 90 % of its every-T "
        "team reward**: met: beta = 4 sends 20 % of the every-T broadcasts" in text
    )
    assert "keeps 255.0 of 270.0 (94 %)." in text
    assert (
        "- **Against the beta = 0 policy's every-T reward** (300.0, ICCO (2-4)): not met, 255.0 "
        "at beta = 4 (85 %)." in text
    )
    assert "seeds [0, 1], checkpoints at 800,256 env steps" in text and "$" not in text
    assert "Read with care" not in text  # 0.05 of robot-steps: 29 z per 580-step episode

    # A rate of one z per robot per episode (the first, at t = 0) is flagged.
    trained["episode_steps"] = 580
    trained["beta_sweep"]["points"][1].update(broadcast_rate=1 / 580, in_quadrant=0.47)
    (tmp_path / "beta_trained.json").write_text(json.dumps(trained))
    assert report.main([str(path), "--readme", str(readme)]) == 0
    text = readme.read_text()
    assert (
        "- **Read with care:** at beta = 4 a robot receives 1.0 z per 580-step episode (one z is "
        "0.0017 of robot-steps): little more than the first." in text
    )
    assert "| 4 | 255.0 ± 2.0 | 103.33 | 0.002 | 1 % | 94 % | 0.47 |" in text


def test_team_size_readme_says_it_has_not_been_run_until_results_exist():
    report = _load(ROOT / "experiments" / "team_size" / "report.py")
    if (ROOT / "experiments" / "team_size" / "results.json").is_file():
        return  # rendered from results: the other test covers the rendering
    readme = (ROOT / "experiments" / "team_size" / "README.md").read_text()
    screen = ROOT / "experiments" / "team_size" / "beta_screen.json"
    screen = json.loads(screen.read_text()) if screen.is_file() else None
    trained = ROOT / "experiments" / "team_size" / "beta_trained.json"
    trained = json.loads(trained.read_text()) if trained.is_file() else None
    assert readme == report.render(None, screen=screen, trained=trained), (
        "stale: run python experiments/team_size/report.py"
    )
    assert "Not run yet at its budget" in readme


def test_run_records_from_two_machines_pool_like_one_evaluation(tmp_path):
    """Seeds evaluated on different machines (``run.py --records``) give the table one joint
    evaluation gives: each run's own trials, the references' once."""
    import numpy as np

    from icco_torchrl.evaluation.metrics import EPISODE, METRICS, summarize, write_csv

    jobs = _load(ROOT / "experiments" / "jobs.py")
    report = _load(ROOT / "experiments" / "four_quadrants" / "report.py")
    rng = np.random.default_rng(0)

    def rows(method, seed, checkpoint):
        return [
            dict(method=method, seed=seed, checkpoint=checkpoint, episode=0, trial=t, segment=s)
            | dict(steps=145 if s != EPISODE else 580, **{m: float(rng.normal()) for m in METRICS})
            for t in range(3)
            for s in ("quadrant 1", EPISODE)
        ]

    references = rows("follower", -1, "")
    joint, records = list(references), tmp_path / "records"
    for seed in (0, 1):  # one machine per seed
        run = tmp_path / f"machine{seed}" / f"icco_seed{seed}"
        run.mkdir(parents=True)
        (run / "config.yaml").write_text("seed: 0\n")
        (run / "eval.csv").write_text("frames,reward\n1,2.0\n")
        (run / "timing.csv").write_text("frames,time_train\n1,1.0\n2,2.0\n3,3.0\n")
        own = rows("ICCO", seed, str(run / "checkpoint.pt"))
        joint += own
        entry = dict(path=str(run / "checkpoint.pt"), method="ICCO", seed=seed, frames=5_000_000)
        results = tmp_path / f"machine{seed}" / "quadrants.json"
        results.write_text(json.dumps({"checkpoints": [entry]}))
        write_csv(own + references, tmp_path / f"machine{seed}" / "trials.csv")
        kept = jobs.keep_records(results, tmp_path / f"machine{seed}" / "trials.csv", records)
        assert kept == [records / run.name]
        assert (records / run.name / "eval.csv").read_text() == "frames,reward\n1,2.0\n"
        # timing: the row at the evaluation (frames 1) and the last one
        timing = (records / run.name / "timing.csv").read_text().split()
        assert timing == ["frames,time_train", "1,1.0", "3,3.0"]

    pooled, checkpoints, runs = report.pooled_records(records)
    assert [c["seed"] for c in checkpoints] == [0, 1] and "path" not in checkpoints[0]
    assert [r.name for r in runs] == ["icco_seed0", "icco_seed1"]
    got = {(r["method"], r["segment"]): r for r in summarize(pooled)}
    want = {(r["method"], r["segment"]): r for r in summarize(joint)}
    assert got.keys() == want.keys()
    for key, row in want.items():
        assert got[key]["n"] == row["n"] and got[key]["seeds"] == row["seeds"], key
        for metric in METRICS:
            assert got[key][metric] == row[metric], (key, metric)
    assert got[("ICCO", EPISODE)]["seeds"] == 2 and got[("follower", EPISODE)]["n"] == 3


def test_team_size_keeps_an_evaluation_only_with_its_overrides_and_newer_than_its_checkpoints(
    tmp_path,
):
    import os

    run = _load(ROOT / "experiments" / "team_size" / "run.py")
    checkpoint = tmp_path / "checkpoint.pt"
    checkpoint.write_bytes(b"x")
    out = tmp_path / "eval_beta4"
    overrides = [f"eval.checkpoints=[{checkpoint}]", "eval.broadcast_threshold=4.0"]
    assert not run.is_current(out, overrides, [checkpoint])  # nothing there
    (out / ".hydra").mkdir(parents=True)
    (out / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    assert not run.is_current(out, overrides, [checkpoint])  # no result
    (out / "quadrants.json").write_text("{}")
    os.utime(checkpoint, (1e9, 1e9))
    assert run.is_current(out, overrides, [checkpoint])
    assert not run.is_current(out, [*overrides[:1], "eval.broadcast_threshold=6.0"], [checkpoint])
    os.utime(checkpoint, None)  # retrained after the evaluation
    os.utime(out / "quadrants.json", (1e9 - 1, 1e9 - 1))
    assert not run.is_current(out, overrides, [checkpoint])
