"""The experiment scripts' run lists compose into valid configs (a typo there would only show
after hours), and the README's count of the VMAS example's ICCO lines is the example's."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from icco_torchrl.envs.reference_policies import BEST_SCRIPTED_LABEL
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
    ratios = {}
    for name, overrides in skill.RECIPES.items():
        cfg = compose_config([*skill.FIXED, *skill.BUDGET, *overrides])
        t = cfg.train
        assert cfg.method.name == "icco" and t.policy_snapshots and t.total_frames == 2_000_000
        replayed = t.updates_per_batch * t.batch_segments * t.sequence_length
        ratios[name] = replayed / (cfg.env.num_envs * t.steps_per_batch)
    assert ratios["replay ratio 4"] == 4 and ratios["replay ratio 2"] == 2  # what the names say
    assert {ratios[n] for n in ratios if "replay ratio" not in n} == {8}


def test_time_to_skill_reads_the_first_mark_at_90_percent_on_the_training_clock(tmp_path):
    """Hand-made scores: the best scripted team's episodes average 400; snapshots at 100k and
    200k frames average 300 (75 %) and 380 (95 %); the clock at 200k is 120 s of collection and
    updates, the evaluations' 50 s excluded."""
    skill = _load(ROOT / "benchmarks" / "time_to_skill.py")
    run = tmp_path / "run"
    (run / "policies").mkdir(parents=True)
    paths = [str(run / "policies" / f"{f:09d}.pt") for f in (100_000, 200_000)]
    header = "method,seed,checkpoint,episode,trial,segment,reward\n"
    rows = [f"ICCO,0,{paths[0]},{k},{k},episode,{r}" for k, r in enumerate((290, 310))]
    rows += [f"ICCO,0,{paths[1]},{k},{k},episode,{r}" for k, r in enumerate((370, 390))]
    rows += [f"ICCO,0,{paths[1]},0,0,quadrant 1,{10**6}"]  # a segment row: not an episode
    best = BEST_SCRIPTED_LABEL
    rows += [f'"{best} (x)",0,,{k},{k},episode,{r}' for k, r in enumerate((390, 410))]
    rows += [f"follower,0,,{k},{k},episode,{10**6}" for k in range(2)]
    (run / "trials.csv").write_text(header + "\n".join(rows) + "\n")
    (run / "timing.csv").write_text(
        "frames,sps,time_collect,time_train,time_eval\n"
        "100000,1,20.0,40.0,25.0\n200000,1,40.0,80.0,50.0\n"
    )
    got = skill.curve(run, run / "trials.csv")
    assert got["best_scripted"] == 400
    assert [m["share"] for m in got["marks"]] == [0.75, 0.95]
    assert got["frames_to_90_percent"] == 200_000 and got["minutes_to_90_percent"] == 2.0
    skill.TARGET = 0.99  # never reached: null, not the last mark
    assert skill.curve(run, run / "trials.csv")["minutes_to_90_percent"] is None


def test_time_to_skill_keeps_a_run_measured_on_another_cpu():
    skill = _load(ROOT / "benchmarks" / "time_to_skill.py")
    row = lambda recipe, seed, **kw: {"recipe": recipe, "seed": seed, **kw}  # noqa: E731
    previous = {  # the older layout: one CPU for the file
        "cpu": "Intel",
        "runs": [row("make train", 0, share=0.8), row("make train", 1, share=0.9)],
    }
    fresh = [row("make train", 0, cpu="AMD", share=0.7), row("make train", 1, cpu="Intel")]
    got = skill.merged(previous, fresh)
    assert [(r["recipe"], r["seed"], r["cpu"]) for r in got] == [
        ("make train", 0, "Intel"),  # kept: another CPU's measurement
        ("make train", 0, "AMD"),
        ("make train", 1, "Intel"),  # replaced: the same run measured again
    ]
    assert got[0]["share"] == 0.8 and "share" not in got[2]


def test_every_best_team_screen_composes_at_the_screen_budget_and_replay_ratio():
    best_team = _load(ROOT / "experiments" / "best_team" / "run.py")
    for name, (_, method, overrides) in best_team.SCREENS.items():
        cfg = compose_config([f"method={method}", *best_team.BUDGET, *overrides])
        t = cfg.train
        assert cfg.method.name == method and t.total_frames >= 2_000_000, name
        replayed = t.updates_per_batch * t.batch_segments * t.sequence_length
        assert replayed == 8 * cfg.env.num_envs * t.steps_per_batch, name


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


def test_the_kernel_profile_sorts_an_update_into_products_fused_kernels_and_the_rest():
    kernels = _load(ROOT / "benchmarks" / "update_kernels.py")
    events = {  # self ms per update, calls per update
        "aten::mm": (2.0, 3.0),
        "aten::addmm": (1.0, 2.0),
        "graph_0_cpp_fused_relu_threshold_backward_1": (1.0, 1.0),
        "graph_1_cpp_fused_add_softmax_2": (0.5, 1.0),
        "aten::copy_": (0.25, 4.0),
    }
    r = kernels.summarise(events, ms_update=6.0, flops=1.2e9, top=1)
    assert (r["gemm_ms"], r["gemm_calls"], r["gemm_gflop_s"]) == (3.0, 5.0, 400.0)
    assert (r["fused_kernels"], r["fused_ms"], r["relu_mask_kernels_ms"]) == (2, 1.5, 1.0)
    assert (r["other_aten_ms"], r["rest_ms"], r["achieved_gflop_s"]) == (0.25, 1.25, 200.0)
    assert [k["kernel"] for k in r["largest_fused"]] == [
        "graph_0_cpp_fused_relu_threshold_backward_1"
    ]


def test_the_verdict_rule_judges_a_gap_against_two_standard_errors_of_the_means():
    verdict = _load(ROOT / "experiments" / "verdict.py")
    Mean = verdict.Mean
    # se = std / sqrt(n): 4 / 4 = 1 and 3 / 3 = 1, combined sqrt(2) = 1.414, 2 SE = 2.83.
    a, b = Mean(10.0, 4.0, 16), Mean(6.0, 3.0, 9)
    assert (a.se, b.se) == (1.0, 1.0)
    clear = verdict.compare(a, b)
    assert clear.gap == 4.0 and abs(clear.se - 2**0.5) < 1e-12
    assert clear.word == "ahead" and clear.text() == "ahead (+4.0, 2 SE 2.8)"
    assert verdict.compare(b, a).text() == "behind (-4.0, 2 SE 2.8)"
    inside = verdict.compare(Mean(8.0, 4.0, 16), b)  # 2.0 < 2.83, though 2 trial stds is 7
    assert inside.text() == "within the spread (+2.0, 2 SE 2.8)"
    # n is the trials behind the mean: the same std over 4 trials (one seed) instead of 16
    # (four seeds pooled) doubles a's se, 2 SE = 2 sqrt(4 + 1) = 4.47, and the gap of 4 is open.
    assert verdict.compare(Mean(10.0, 4.0, 4), b).word == "within the spread"
    entry = {"seeds": 3, "reward": {"mean": 1.0, "std": 2.0}}
    assert verdict.Mean.of_result(entry, "reward", trials=20) == Mean(1.0, 2.0, 60)
    assert verdict.Mean.of_result({**entry, "seeds": 0}, "reward", 20).n == 20  # a reference
    row = {"reward": 5.0, "reward_std": 1.0, "n": 60, "pick": 2.0, "pick_std": 0.5}
    assert verdict.Mean.of_row(row, "pick") == Mean(2.0, 0.5, 60)
    # A bar a >= 0.5 x b: gap 5 - 4 = 1 against sqrt(0.1^2 + (0.5 x 0.2)^2) = 0.141.
    bar = verdict.compare(Mean(5.0, 1.0, 100), Mean(8.0, 2.0, 100), 0.5)
    assert bar.gap == 1.0 and abs(bar.se - 0.02**0.5) < 1e-12 and bar.word == "ahead"
    assert verdict.compare(Mean(float("nan"), 1.0, 10), b).text() == "not measured"
    assert verdict.compare(Mean(1.0, 1.0, 0), b).word == "not measured"  # no trials
    claim, any_of = verdict.claim, verdict.any_of
    assert claim(["ahead", "ahead"]) == "holds"
    assert claim(["ahead", "within the spread"]) == "not resolved at this budget"
    assert claim(["within the spread", "behind", "not measured"]) == "does not hold"
    assert claim(["ahead", "not measured"]) == claim([]) == "not measured"
    assert any_of(["does not hold", "holds"]) == "holds"
    assert any_of(["does not hold", "not resolved at this budget"]) == "not resolved at this budget"
    assert any_of(["does not hold", "does not hold"]) == "does not hold"
    assert any_of(["does not hold", "not measured"]) == any_of([]) == "not measured"
    assert verdict.pooled_n({"ICCO": 60, "follower": 20, "QMIX": 60}) == (
        "60 (ICCO, QMIX), 20 (follower)"
    )


def test_four_quadrant_target_is_a_share_of_the_best_scripted_teams_reward():
    report = _load(ROOT / "experiments" / "four_quadrants" / "report.py")

    def row(method, reward):  # std 10 over 100 trials: se 1
        return dict(method=method, n=100, reward=reward, reward_std=10.0)

    best = "best scripted (defend=inf, collect=1, deliver=2 m)"
    refs = {"follower": row("follower", 280.0), best: row(best, 400.0)}
    # 0.9 x 400 = 360: ICCO 363 is 3 past it, 2 SE sqrt(1 + 0.9^2) x 2 = 2.69: ahead; QMIX (FULL)
    # 362 is 2 past it: within the spread.
    rows = {"ICCO": row("ICCO", 363.0), "QMIX (FULL)": row("QMIX (FULL)", 362.0)}
    lines = report.criteria(rows, refs, "../calibration/README.md")
    assert "at least 90 % of the best scripted team's reward" in lines[0]
    assert "[the calibration](../calibration/README.md)" in lines[0]
    assert lines[1] == (
        "  - ICCO: holds. 91 % of the best scripted team's reward (363.0 vs 400.0); against 90 %: "
        "ahead (+3.0, 2 SE 2.7); against 100 % (moonshot): behind (-37.0, 2 SE 2.8)."
    )
    assert lines[2].startswith("  - QMIX (FULL): not resolved at this budget. 90 % of")
    assert report.criteria(rows, {"follower": refs["follower"]})[0].endswith(
        "not measured (no best scripted row on these episodes)."
    )


def _share_tables():
    """``(page, results, rows)`` for every experiment page with a 'share of best scripted'
    column: the rows of that table as cells, under their header."""
    from icco_torchrl.evaluation.metrics import SHARE

    for page in sorted((ROOT / "experiments").rglob("README.md")):
        if not (page.parent / "results.json").is_file():
            continue
        lines = page.read_text().splitlines()
        for i, line in enumerate(lines):
            if line.startswith("| method |") and f"| {SHARE} |" in line:
                end = next((k for k, x in enumerate(lines[i:]) if not x.startswith("|")), None)
                table = lines[i : i + end] if end is not None else lines[i:]
                cells = [[c.strip() for c in x.strip().strip("|").split("|")] for x in table]
                results = json.loads((page.parent / "results.json").read_text())
                yield page, results, [cells[0], *cells[2:]]


def test_pages_best_scripted_rows_and_shares_are_their_results():
    """The best scripted row and every share a page shows are its results.json's."""
    from icco_torchrl.evaluation.metrics import SHARE, SHARE_KEY, result_name

    pages = set()
    for page, results, rows in _share_tables():
        head, share = rows[0], rows[0].index(SHARE)
        seen = False
        for row in rows[1:]:
            if row[1] == "missing":
                continue
            entry = results["methods"][result_name(row[0])]
            want = entry.get(SHARE_KEY)
            assert row[share] == ("–" if want is None else f"{round(100 * want)} %"), (page, row[0])
            if result_name(row[0]) == "best_scripted":
                seen = True
                value = entry["reward"]
                reward = row[head.index("reward")]
                assert reward == f"{value['mean']:.1f} ± {value['std']:.1f}", page
        assert seen, f"{page}: a share column without a best scripted row"
        pages.add(page.relative_to(ROOT).as_posix())
    for page in (
        "experiments/four_quadrants/README.md",
        "experiments/four_quadrants/5m_no_layernorm/README.md",
        "experiments/four_quadrants/5m/README.md",
        "experiments/language/README.md",
        "experiments/language/5m/README.md",
        "experiments/language/5m_no_layernorm/README.md",
    ):
        assert page in pages, f"{page} shows no best scripted row and share"


def test_references_added_to_a_page_must_reproduce_the_ones_it_has(tmp_path):
    """A page's references come from the trials added to it only if those reproduce the rows it
    already has: the same episodes (report.py --from-results --references)."""
    import csv

    report = _load(ROOT / "experiments" / "four_quadrants" / "report.py")
    here = ROOT / "experiments" / "four_quadrants"
    for name in ("README.md", "results.json"):
        (tmp_path / name).write_text((here / name).read_text())
    source = here / "5m_no_layernorm" / "records" / "references_trials.csv"
    rows = list(csv.DictReader(source.open()))
    for row in rows:  # other episodes: the follower a little better on one trial
        if row["method"] == "follower" and row["trial"] == "0" and row["segment"] == "episode":
            row["reward"] = str(float(row["reward"]) + 1.0)
    with (tmp_path / "trials.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    with pytest.raises(SystemExit, match="do not reproduce the page's follower"):
        report.add_references(tmp_path / "README.md", tmp_path / "trials.csv")
    assert (tmp_path / "results.json").read_text() == (here / "results.json").read_text()


def test_four_quadrant_pages_state_the_comparison_their_results_give():
    """Every page four_quadrants/report.py renders (its own, 5m/, the screens') ends with the
    comparison that its results.json gives (``report.py --from-results`` rewrites it)."""
    report = _load(ROOT / "experiments" / "four_quadrants" / "report.py")
    pages = [
        path
        for path in sorted((ROOT / "experiments").rglob("README.md"))
        if (path.parent / "results.json").is_file()
        and report.COMPARISON_HEADING in path.read_text()
        and "# Four quadrants" in path.read_text()
    ]
    assert len(pages) >= 2, pages
    for page in pages:
        results = json.loads((page.parent / "results.json").read_text())
        summary = report.summary_from_results(results)
        missing = [m for m in report.EXPECTED if m not in {r["method"] for r in summary}]
        stated = page.read_text().split(report.COMPARISON_HEADING, 1)[1]
        assert (
            stated == report.comparison(summary, missing, report.calibration_link(page)) + "\n"
        ), (
            f"stale: run python experiments/four_quadrants/report.py --from-results --readme "
            f"{page.relative_to(ROOT)}"
        )


def test_sequence_replay_readme_is_rendered_from_its_results_with_the_verdicts():
    from string import Template

    run = _load(ROOT / "experiments" / "sequence_replay" / "run.py")
    here = ROOT / "experiments" / "sequence_replay"
    results = json.loads((here / "results.json").read_text())
    want = Template((here / "README.template.md").read_text()).substitute(
        table=run.table(results), verdicts=run.verdicts(results)
    )
    assert (here / "README.md").read_text() == want, (
        "stale: run python experiments/sequence_replay/run.py --report-only"
    )
    assert "The issue's targets hold for" in want


def test_language_comparison_judges_each_instruction_and_table_two_by_the_rule():
    from icco_torchrl.evaluation.metrics import EPISODE

    report = _load(ROOT / "experiments" / "language" / "report.py")
    segments = ["Go right", "Move top", "Gather center", "Spread out"]

    def row(method, segment, reward):  # std 10 over 100 trials: 2 SE of a gap 2 sqrt(2) = 2.83
        counts = dict(waypoint_dist=0.3, collect=1.0, defense=5.0)
        return dict(
            method=method, segment=segment, n=100, reward=reward, reward_std=10.0, **counts
        ) | {f"{k}_std": 1.0 for k in counts}

    fig5b = [row("ICCO", s, 60.0 + 2 * i) for i, s in enumerate(segments)]
    fig5b += [row("QMIX (FULL)", s, 57.0) for s in segments]
    fig5b += [row("ICCO", EPISODE, 252.0), row("QMIX (FULL)", EPISODE, 228.0)]
    # Table II: picks 3 / 2 / 1 per instruction segment, no spread but n = 4 segments each.
    trials = [
        dict(method=m, segment=s, pick=p, collect=p, defense=p)
        for m, p in (("ICCO", 3.0), ("QMIX-TAP", 2.0), ("QMIX-TAP w/o TR", 2.0))
        for s in segments
    ]
    table, means = report.table2(trials)
    assert means["ICCO"][0].n == 4 and means["ICCO"][0].std == 0.0
    text = report.comparison(fig5b, means)
    assert "n = trials pooled across seeds (Fig. 5b: 100 (ICCO, QMIX (FULL)); Table II: " in text
    # +3 (2 SE 2.83) is ahead, +5, +7, +9 too: every instruction.
    assert (
        "- **Paper: ICCO gets more reward than QMIX (FULL) for every instruction**: holds. ICCO is "
        "ahead on 4 and behind on 0 of 4 instructions (Go right: ahead (+3.0, 2 SE 2.8);" in text
    )
    assert "in Gather Center ICCO gathers and also collects/defends better**: not resolved" in text
    # QMIX-TAP against w/o TR: equal, no spread: within the spread, so not resolved.
    assert (
        "on picks, deliveries and defenses**: not resolved at this budget. Per count: pick not "
        "resolved at this budget (3.0 / 2.0 / 2.0; ICCO against QMIX-TAP ahead (+1.00, 2 SE 0.00), "
        "QMIX-TAP against w/o TR within the spread (+0.00, 2 SE 0.00))" in text
    )


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


def _team_size_results(
    points_5_6: dict, betas: list[tuple[float, float, float]], trials: int = 50
) -> dict:
    """A small results.json: ``{label: (reward per robot at 5, at 6)}`` (the blend's under
    "blend"), and beta sweep points ``(beta, team reward, broadcast rate)`` at T = 4; every
    entry over ``trials`` trials, team reward std 1 (per robot 1 / k), beta points' std 2."""

    def entry(method, k, per_robot, trained_on):
        return dict(
            method=method,
            kind="reference" if trained_on is None else "trained",
            trained_on=trained_on,
            team_size=k,
            trials=trials,
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
            trials=trials,
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
        trials=trials,
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
            "QMIX (FULL) (2-4)": (8.2, 7.65),  # 82 % and 85 %: holds
            "ICCO (3)": (100.0, 100.0),  # not trained on 2-4: not a candidate
        },
        sweep,
    )
    zero_shot, beta = report.targets(results).splitlines()
    # At 5 robots ICCO's 8.5 against the bar 0.8 x 10: +0.5, se sqrt((0.2^2 + 0.16^2) / 50).
    assert zero_shot.endswith(
        "**: holds (by QMIX (FULL) (2-4)). ICCO (2-4), does not hold: 5 robots 8.50 vs 10.00 per "
        "robot (85 %), against the bar: ahead (+0.50, 2 SE 0.07); 6 robots 7.00 vs 9.00 per robot "
        "(78 %), against the bar: behind (-0.20, 2 SE 0.06). QMIX (FULL) (2-4), holds: 5 robots "
        "8.20 vs 10.00 per robot (82 %), against the bar: ahead (+0.20, 2 SE 0.07); 6 robots 7.65 "
        "vs 9.00 per robot (85 %), against the bar: ahead (+0.45, 2 SE 0.06)."
    )
    # beta = 0.5 sends 40 % of the every-T broadcasts (too many); beta = 1 sends 20 %, keeps 93 %.
    assert beta.endswith(
        "**: holds: beta = 1 sends 20 % of the every-T broadcasts (broadcast rate 0.050 of "
        "robot-steps, every T: 0.250) and keeps 280.0 of 300.0 (93 %; against the bar: ahead "
        "(+10.0, 2 SE 0.8))."
    )
    # The same means over 2 trials each: 2 SE five times wider, the small gaps are open.
    few = _team_size_results(
        {"blend": (10.0, 9.0), "ICCO (2-4)": (8.5, 7.0), "QMIX (FULL) (2-4)": (8.2, 7.65)},
        sweep,
        trials=2,
    )
    zero_shot = report.targets(few).splitlines()[0]
    assert "**: not resolved at this budget. ICCO (2-4), not resolved at this budget:" in zero_shot
    assert "(78 %), against the bar: within the spread (-0.20, 2 SE 0.30)" in zero_shot
    assert (
        report.training_sizes(results)
        == "- **ICCO trained on 3 robots against ICCO trained on 2-4** (reward per robot): "
        "ICCO (3) is ahead at every team size, 5 to 6 robots. 5: 100.00 vs 8.50, ahead (+91.50, "
        "2 SE 0.08); 6: 100.00 vs 7.00, ahead (+93.00, 2 SE 0.07)."
    )
    mixed = _team_size_results({"ICCO (2-4)": (8.5, 7.0), "ICCO (3)": (8.5, 6.0)}, sweep)
    assert "ICCO (3) is within the spread at 5 robots; behind at 6 robots. 5: 8.50 vs 8.50" in (
        report.training_sizes(mixed)
    )
    lower = _team_size_results({"blend": (10.0, 9.0), "ICCO (2-4)": (7.0, None)}, sweep[:2])
    zero_shot, beta = report.targets(lower).splitlines()
    assert (
        "**: does not hold. ICCO (2-4), does not hold: 5 robots 7.00 vs 10.00 per robot (70 %), "
        "against the bar: behind (-1.00, 2 SE 0.07)" in zero_shot
    )
    assert "6 robots not evaluated" in zero_shot
    assert (
        "**: not measured (no beta sent <= 25 % of the every-T broadcasts; the fewest: 40 %" in beta
    )
    worse = _team_size_results({"ICCO (2-4)": (7.0, 7.0)}, [(0.0, 300.0, 0.25), (1.0, 250.0, 0.05)])
    zero_shot, beta = report.targets(worse).splitlines()
    assert zero_shot.endswith(
        "**: not measured. ICCO (2-4), not measured: 5 robots not evaluated; 6 robots not "
        "evaluated."
    )
    assert "**: does not hold: beta = 1 sends 20 %" in beta and "(83 %;" in beta
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
    assert "| QMIX (FULL) (2-4) | 8.20 ± 0.20 | 7.65 ± 0.17 |" in text
    assert "- **ICCO trained on 3 robots against ICCO trained on 2-4**" in text
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
        "team reward**: holds: beta = 4 sends 20 % of the every-T broadcasts" in text
    )
    assert "keeps 255.0 of 270.0 (94 %; against the bar: ahead (+12.0, 2 SE 0.8))." in text
    assert (
        "- **Against the beta = 0 policy's every-T reward** (300.0, ICCO (2-4)): does not hold, "
        "255.0 at beta = 4 (85 %; against the bar: behind (-15.0, 2 SE 0.8))." in text
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


def test_team_size_readme_is_rendered_from_its_results_or_says_it_has_not_been_run():
    report = _load(ROOT / "experiments" / "team_size" / "report.py")
    here = ROOT / "experiments" / "team_size"
    readme = (here / "README.md").read_text()

    def load(name):
        return json.loads((here / name).read_text()) if (here / name).is_file() else None

    screen, trained, results = (
        load("beta_screen.json"),
        load("beta_trained.json"),
        load("results.json"),
    )
    figures = {"sizes": "figures/reward_per_robot.png", "beta": "figures/beta_sweep.png"}
    want = report.render(results, figures if results else None, screen=screen, trained=trained)
    assert readme == want, "stale: run python experiments/team_size/report.py"
    if results is None:
        assert "Not run yet at its budget" in readme
    else:  # the page answers, from its numbers, whether training on 3 robots beats 2-4
        assert "- **ICCO trained on 3 robots against ICCO trained on 2-4**" in readme


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


def test_records_of_two_recipes_are_not_pooled_into_one_table(tmp_path):
    """A record of an older recipe left beside the new ones (a seed trained before LayerNorm
    became the default) stops the report in one line naming both runs and the field."""
    jobs = _load(ROOT / "experiments" / "jobs.py")
    base = {"method": {"name": "icco", "layer_norm": True}, "env": {"num_envs": 32}}
    configs = {
        "icco_seed0": {**base, "seed": 0, "train": {"lr": 1e-3}},
        "icco_seed1": {**base, "seed": 1, "train": {"lr": 1e-3}, "eval": {"trials": 5}},
        "qmix_seed0": {"method": {"name": "qmix"}, "env": {"num_envs": 32}, "train": {"lr": 1e-3}},
    }
    for name, config in configs.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "config.yaml").write_text(json.dumps(config))  # JSON is YAML
    runs = {tmp_path / "icco_seed0": "ICCO", tmp_path / "icco_seed1": "ICCO"}
    runs[tmp_path / "qmix_seed0"] = "QMIX"
    jobs.check_one_recipe(runs)  # seeds, eval settings and method blocks may differ

    (tmp_path / "icco_seed1" / "config.yaml").write_text(
        json.dumps({**configs["icco_seed1"], "method": {"name": "icco"}})
    )
    with pytest.raises(
        SystemExit,
        match=r"^icco_seed0 and icco_seed1 were trained with "
        r"different recipes \(method.layer_norm: True vs False\)",  # absent: trained without
    ):
        jobs.check_one_recipe(runs)
    (tmp_path / "icco_seed1" / "config.yaml").write_text(json.dumps(configs["icco_seed1"]))
    (tmp_path / "qmix_seed0" / "config.yaml").write_text(
        json.dumps({**configs["qmix_seed0"], "train": {"lr": 3e-4}})
    )
    with pytest.raises(SystemExit, match=r"\(train.lr: 0.001 vs 0.0003\)"):
        jobs.check_one_recipe(runs)


def test_a_record_older_than_an_option_pools_at_the_value_it_trained_with(tmp_path):
    """A record written before an option existed is read in today's fields: at the converter's
    value for it (train.ce_clamp: false, the clamps' default since) or the schema's default. The
    consistency term's settings are compared only between runs that have the term."""
    jobs = _load(ROOT / "experiments" / "jobs.py")
    icco = {"name": "icco", "coordinator": True, "ce_coef": 1e-3, "entropy_coef": 1e-3}
    qmix = {"name": "qmix", "coordinator": False, "ce_coef": 0.0, "entropy_coef": 0.0}
    train = {"lr": 1e-3, "ce_clamp": True, "policy_snapshots": False}
    configs = {  # the seed-0 records predate ce_clamp and policy_snapshots
        "icco_seed0": {"method": icco, "env": {}, "train": {"lr": 1e-3}},
        "icco_seed1": {"method": icco, "env": {}, "train": train},
        "qmix_seed0": {"method": qmix, "env": {}, "train": {"lr": 1e-3}},
        "qmix_seed1": {"method": qmix, "env": {}, "train": train},
    }
    for name, config in configs.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "config.yaml").write_text(json.dumps(config))
    qmix_runs = {tmp_path / f"qmix_seed{s}": "QMIX" for s in (0, 1)}
    jobs.check_one_recipe(qmix_runs)  # no term: its clamp changes nothing
    with pytest.raises(SystemExit, match=r"\(train.ce_clamp: False vs True\)"):
        jobs.check_one_recipe({tmp_path / f"icco_seed{s}": "ICCO" for s in (0, 1)})
    jobs.check_one_recipe({tmp_path / "icco_seed1": "ICCO", **qmix_runs})  # across methods


def test_every_consistency_screen_composes_with_its_weights_and_the_control_is_the_default():
    run = _load(ROOT / "experiments" / "consistency" / "run.py")
    for name, s in run.SCREENS.items():
        cfg = compose_config([f"method={s.method}", *run.BUDGET, *s.overrides])
        m, t = cfg.method, cfg.train
        assert (m.ce_coef, m.entropy_coef, t.ce_clamp) == (s.ce_coef, s.entropy_coef, s.clamp), name
        assert (t.total_frames, t.collector, t.threads) == (2_000_000, "inline", 1), name
    assert {s.ce_coef for s in run.SCREENS.values()} == {0.0, 1e-4, 1e-3, 1e-2, 1e-1, 1.0}
    weighted = [s for s in run.SCREENS.values() if s.ce_coef > 0 and s.entropy_coef == s.ce_coef]
    assert {(s.ce_coef, s.clamp) for s in weighted} == {
        (w, c) for w in (1e-4, 1e-3, 1e-2, 1e-1, 1.0) for c in (False, True)
    }
    default = compose_config(["method=icco"])
    control = run.SCREENS[run.CONTROL]
    assert (control.method, control.ce_coef, control.entropy_coef, control.clamp) == (
        "icco",
        default.method.ce_coef,
        default.method.entropy_coef,
        default.train.ce_clamp,
    )


def test_where_consistency_matters_pools_each_teams_seeds_against_the_same_references(tmp_path):
    """experiments/consistency/where.py on a hand-made evaluation: each team's episode rewards
    pooled over its two seeds, its coordination measures averaged over them, shares of the best
    scripted team's, and a verdict against ICCO w/o CE."""
    where = _load(ROOT / "experiments" / "consistency" / "where.py")
    teams = {"ce1": [tmp_path / "a0.pt", tmp_path / "a1.pt"], "wo_ce": [tmp_path / "b0.pt"]}
    rewards = {"a0.pt": (300, 320), "a1.pt": (340, 360), "b0.pt": (100, 100)}
    rows = ["method,checkpoint,segment,reward"]
    for name, values in rewards.items():
        rows += [f"ICCO,{tmp_path / name},episode,{v}" for v in values]
        rows += [f"ICCO,{tmp_path / name},quadrant 1,{10**6}"]  # not an episode row
    rows += [f'"{BEST_SCRIPTED_LABEL} (x)",,episode,{v}' for v in (400, 400)]
    (tmp_path / "quadrants_trials.csv").write_text("\n".join(rows) + "\n")
    mi = {"a0.pt": 2.0, "a1.pt": 4.0, "b0.pt": -1.0}
    entries = [
        {
            "path": str(tmp_path / n),
            "coordination": {"mi_bound": v, "mi_null": 0.0, "consistency": 0.5},
        }
        for n, v in mi.items()
    ]
    (tmp_path / "quadrants.json").write_text(json.dumps({"checkpoints": entries}))
    res = where.setting_results(tmp_path, "eval", teams)
    assert res["best_scripted"]["mean"] == 400
    assert res["ce1"]["reward"]["mean"] == 330 and res["ce1"]["reward"]["n"] == 4
    assert res["ce1"]["reward"]["share_of_best_scripted"] == 330 / 400
    assert res["ce1"]["mi_bound"]["mean"] == 3.0 and res["ce1"]["mi_bound"]["std"] == 1.0
    assert res["wo_ce"]["reward"]["mean"] == 100 and res["wo_ce"]["mi_bound"]["mean"] == -1.0
    verdict = where.verdicts({"team 5": res}, "ce1")["team 5"]
    assert verdict["reward"].startswith("ahead")


def test_where_reads_an_evaluation_made_in_another_clone_and_never_writes_nothing(tmp_path):
    """The evaluation names policies by the clone it ran in; the report matches them by screen,
    run and file. A report with no evaluation to read stops in one line and keeps the results."""
    where = _load(ROOT / "experiments" / "consistency" / "where.py")
    ran, here = tmp_path / "ran" / "records", tmp_path / "here" / "records"
    rows = ["method,checkpoint,segment,reward"]
    rows += [f"ICCO,{ran / s / 'seed0' / 'policy.pt'},episode,{v}" for s, v in (("a", 7), ("b", 5))]
    rows += [f'"{BEST_SCRIPTED_LABEL} (x)",,episode,10']
    (tmp_path / "quadrants_trials.csv").write_text("\n".join(rows) + "\n")
    entries = [{"path": str(ran / s / "seed0" / "policy.pt")} for s in "ab"]
    (tmp_path / "quadrants.json").write_text(json.dumps({"checkpoints": entries}))
    teams = {s: [here / s / "seed0" / "policy.pt"] for s in "ab"}
    res = where.setting_results(tmp_path, "eval", teams)
    assert (res["a"]["reward"]["mean"], res["b"]["reward"]["mean"]) == (7, 5)

    results = tmp_path / "where.json"
    results.write_text('{"chosen": "a"}')
    for s in ("a", "wo_ce"):
        (here / s / "seed0").mkdir(parents=True)
        (here / s / "seed0" / "policy.pt").write_bytes(b"")
    argv = ["--report-only", "--records", str(here), "--out", str(tmp_path / "none")]
    with pytest.raises(SystemExit, match="no evaluations here"):
        where.main([*argv, "--results", str(results)])
    assert results.read_text() == '{"chosen": "a"}'


def test_the_consistency_page_reads_a_bound_gain_only_beyond_the_seeds_spread():
    run = _load(ROOT / "experiments" / "consistency" / "run.py")

    def screen(method, reward, bound, null, std):
        return {
            "method": method,
            "quadrants": {"reward": {"mean": reward}},
            "coordination": {
                "mi_bound": {"mean": bound, "std": std},
                "mi_null": {"mean": null, "std": std},
            },
        }

    text = run.reading(
        {
            "wo_ce": screen("icco_wo_ce", 300.0, -1.5, -2.0, 0.1),  # gain 0.5, spread 0.2
            "ce1": screen("icco", 250.0, 0.0, -2.0, 0.2),  # gain 2.0 - 0.4 > 0.7: above
            "ce1e-4": screen("icco", 280.0, -1.2, -2.0, 0.1),  # gain 0.8 - 0.2 < 0.7: not above
        }
    )
    assert "Highest four-quadrant reward: `wo_ce` (300.0)" in text
    assert "Of ICCO's weights, the highest: `ce1e-4` (280.0)" in text
    assert "`ce1`: bound above its floor by +2.00 nats (ICCO w/o CE: +0.50); above" in text
    assert "`ce1e-4`: bound above its floor by +0.80 nats (ICCO w/o CE: +0.50); not above" in text


def test_route_screens_compose_and_the_page_judges_each_instruction_against_80_percent():
    routes = _load(ROOT / "experiments" / "language" / "routes" / "run.py")
    default = compose_config(routes.BUDGET_5M)
    for name, overrides in routes.SCREENS.items():
        cfg = compose_config([*routes.SCALE.get(name, routes.BUDGET), *overrides])
        weights = (cfg.method.ce_coef, cfg.method.entropy_coef, cfg.train.ce_clamp)
        if name in routes.SCALE:  # the four-quadrant 5M page's ICCO: today's default weight
            assert cfg.train.total_frames == 5_000_000, name
            d = default
            assert weights == (d.method.ce_coef, d.method.entropy_coef, d.train.ce_clamp), name
        else:  # at the 2M control's consistency weight (1e-4, unclamped), whatever the default
            assert cfg.train.total_frames == 2_000_000, name
            assert weights == (1e-4, 1e-4, False), name
        p = cfg.env.params
        no_route = ("control", "control_5m")
        routes_prob = {
            "hold_routes_0.2": 0.2,
            "hold_routes_all_soft": 1.0,
            **dict.fromkeys(no_route, 0.0),
        }
        routes_prob = routes_prob.get(name, 0.5)
        assert p.waypoint_route_prob == routes_prob, name
        assert p.inst_hold == ("hold" in name), name
    cells = lambda places, **ep: {  # noqa: E731  (one team's language row)
        **{i: {"in_place": v} for i, v in zip(routes.serving.INSTRUCTIONS, places)},
        "episode": {"reward": 300.0, "time_to_slot": 30.0, **ep},
    }
    results = {
        "trials": 20,
        "machine": "x",
        "seeds": [0, 1],
        "screens": {
            "control": {
                "language": cells([0.5, 0.9, 1.0, 0.85]),
                "quadrants": {"mean": 330.0, "std": 20.0, "share_of_best_scripted": 0.83},
            },
            "progress": {
                "language": cells([0.8, 0.95, 1.0, 0.9]),
                "quadrants": {"mean": 360.0, "std": 10.0, "share_of_best_scripted": 0.9},
            },
        },
        "references": {
            label: cells([1.0, 1.0, 1.0, 1.0], reward=400.0) for label in routes.REFERENCES
        },
        "quadrants_best_scripted": {"mean": 400.0},
    }
    results["references"]["follower (progress r_inst)"] = cells([1.0] * 4, reward=900.0)
    page = routes.render(results)
    assert "- ICCO (make train): below 80% on Go right;" in page
    assert "- ICCO, progress r_inst: in place at least 80% on every instruction;" in page
    assert "language reward 75% of the best scripted team's, four quadrants 90%" in page
    assert "| ICCO, progress r_inst (*not kept*) | 80 % | 95 % | 100 % | 90 % |" in page
    places = "| 100 % | 100 % | 100 % | 100 % | 30 |"
    assert f"| follower (progress r_inst) {places} other units |" in page
    assert f"| follower (cosine r_inst) {places} 400.0 (100%) |" in page
    assert not set(routes.RETIRED) & set(routes.SCREENS)
    # the 5M control replays the four-quadrant 5M page's ICCO policies, not its other methods
    control = routes.records_of(ROOT / "nowhere", "control_5m")
    assert [p.name for p in control] == ["icco_seed0", "icco_seed1", "icco_seed2"]
    assert not routes.records_of(ROOT / "nowhere", "hold_routes_5m")


def test_a_kept_run_carries_its_policy_weights_and_no_training_state(tmp_path):
    """``jobs.keep_run`` files a run with its policy (any protocol can be played again without
    retraining): the networks' weights as they were, no optimizer, no target copies."""
    import shutil

    import torch

    from icco_torchrl.training.checkpoint import load_checkpoint

    jobs = _load(ROOT / "experiments" / "jobs.py")
    run = tmp_path / "icco_seed0"
    run.mkdir()
    shutil.copyfile(ROOT / "assets" / "demo_icco.pt", run / "checkpoint.pt")
    (run / "config.yaml").write_text("seed: 0\n")
    dest = jobs.keep_run(run, tmp_path / "records" / run.name)
    assert sorted(p.name for p in dest.iterdir()) == ["config.yaml", jobs.POLICY]
    kept, source = load_checkpoint(dest / jobs.POLICY), load_checkpoint(run / "checkpoint.pt")
    assert kept["policy_only"] and "optimizer" not in kept
    assert not any(k.startswith("target_") for k in kept["loss"])
    for name, tensor in source["loss"].items():
        if not name.startswith("target_"):
            assert torch.equal(kept["loss"][name], tensor), name
    empty = jobs.keep_run(tmp_path / "no_checkpoint", tmp_path / "records" / "none")
    assert list(empty.iterdir()) == []  # nothing to keep, nothing invented


def test_the_consistency_rule_takes_the_reward_winner_or_at_equal_reward_the_larger_bound():
    run = _load(ROOT / "experiments" / "consistency" / "run.py")

    def screen(reward, bound):
        return {
            "method": "icco",
            "quadrants": {"reward": {"mean": reward, "std": 20.0, "n": 40}},  # 2 SE = 8.9
            "coordination": {
                "mi_bound": {"mean": bound, "std": 0.1},
                "mi_null": {"mean": -2.0, "std": 0.1},
            },
        }

    def gain(entry):
        c = entry["coordination"]
        return c["mi_bound"]["mean"] - c["mi_null"]["mean"], 0.2

    # b: 2.0 +- 0.2 above its floor against a's 0.5 +- 0.2, beyond the spread: b wins on MI.
    level = {"a": screen(360.0, -1.5), "b": screen(355.0, 0.0), "c": screen(300.0, 1.0)}
    assert "`b`, of the weights at equal reward (`a`, `b`)" in run.decision(level, "a", gain)
    clear = {"a": screen(360.0, -1.5), "b": screen(340.0, 0.0)}  # b is behind: a wins outright
    assert run.decision(clear, "a", gain).endswith("`a`, the highest reward.")
    # b's bound is higher on the mean (0.8 against 0.5) but within the spread: a stays.
    close = {"a": screen(360.0, -1.5), "b": screen(355.0, -1.2)}
    assert "`a`, the highest reward; no weight at equal reward (`b`)" in run.decision(
        close, "a", gain
    )


def test_the_language_protocol_replays_kept_policies_or_names_what_trains_them(tmp_path):
    """``--records``: the agents are the policies kept there; a missing one stops the run in one
    line with the command that trains and files it (nothing is trained behind the user's back)."""
    run = _load(ROOT / "experiments" / "language" / "run.py")
    for seed in (0, 1):
        (tmp_path / f"icco_seed{seed}").mkdir()
        (tmp_path / f"icco_seed{seed}" / "policy.pt").write_bytes(b"weights")
    (tmp_path / "qmix_full_seed0").mkdir()  # a record without its policy (trained before)
    budget = ["experiment=repro_5m"]
    assert run.from_records(tmp_path, ["icco"], [0, 1], budget) == {
        "icco": [str(tmp_path / f"icco_seed{s}" / "policy.pt") for s in (0, 1)]
    }
    with pytest.raises(SystemExit, match=r"^no kept policy for qmix_full at seeds \[0, 1\]") as e:
        run.from_records(tmp_path, ["icco", "qmix_full"], [0, 1], budget)
    assert "four_quadrants/run.py --methods qmix_full --seeds 0 1 --records" in str(e.value)
    assert str(e.value).endswith("--budget experiment=repro_5m") and "\n" not in str(e.value)
    assert run.kept(tmp_path, "icco", [0, 2]) is None
    # --kept-only: each method at the seeds kept, a method with none left out, none at all refused
    (tmp_path / "qmix_full_seed1").mkdir()
    (tmp_path / "qmix_full_seed1" / "policy.pt").write_bytes(b"weights")
    some = run.from_records(tmp_path, ["icco", "qmix_full", "qmix"], [0, 1, 2], budget, True)
    assert some == {
        "icco": [str(tmp_path / f"icco_seed{s}" / "policy.pt") for s in (0, 1)],
        "qmix_full": [str(tmp_path / "qmix_full_seed1" / "policy.pt")],
    }
    with pytest.raises(SystemExit, match=r"^no kept policy for qmix at seeds \[0\]"):
        run.from_records(tmp_path, ["qmix"], [0], budget, True)
    with pytest.raises(SystemExit, match="--kept-only replays kept policies: give --records"):
        run.main(["--kept-only", "--methods", "icco"])


def test_the_language_protocols_scripted_rows_compose_as_one_override():
    """Fig. 5b's references reach ``icco instruct`` whole, a blend with its commas included."""
    run = _load(ROOT / "experiments" / "language" / "run.py")
    references = (*run.REFERENCES, "blend(defend=inf, collect=1, deliver=2, follow=pursuit)")
    run.REFERENCES = references
    cfg = compose_config([run.references_override()])
    assert list(cfg.eval.references) == list(references)


def test_the_language_protocol_trains_its_agents_through_the_four_quadrant_script(monkeypatch):
    """One code path for training: the four-quadrant script, ``--jobs`` runs side by side."""
    run = _load(ROOT / "experiments" / "language" / "run.py")
    calls = []
    monkeypatch.setattr(run, "run", lambda *command: calls.append(command))
    run.train(Path("sweep"), ["qmix"], [0, 1, 2], ["experiment=repro_5m"], False, 3)
    (command,) = calls
    assert command[1].endswith("four_quadrants/run.py") and command[2] == "--train-only"
    words = " ".join(command[3:])
    assert "--jobs 3" in words and "--methods qmix --seeds 0 1 2" in words
    assert words.endswith("--budget experiment=repro_5m")


def test_the_language_page_shows_where_the_robots_are_per_instruction():
    report = _load(ROOT / "experiments" / "language" / "report.py")
    rows = [
        {"method": "ICCO", "segment": "Go right", "in_place": 0.75},
        {"method": "ICCO", "segment": "Move top", "in_place": float("nan")},
        {"method": "ICCO", "segment": report.EPISODE, "at_slot": 0.5, "formation": 0.25,
         "time_to_slot": 82.4},
    ]  # fmt: skip
    table = report.placement(rows).splitlines()
    assert (
        table[0] == "| method | Go right | Move top | at slot | formation | time to slot (steps) |"
    )
    assert table[2] == "| ICCO | 75 % | – | 50 % | 25 % | 82 |"
    assert "given once" not in report.PLAN_TEXT["served"] and "fixed" in report.PLAN_TEXT["fixed"]


def test_the_language_page_says_what_being_in_place_earns_from_the_path_follower():
    report = _load(ROOT / "experiments" / "language" / "report.py")
    best = report.BEST_SCRIPTED_LABEL + " (defend=inf)"
    rows = [
        {"method": "pursuit", "segment": "Go right", "in_place": 1.0},
        {"method": "pursuit", "segment": "Move top", "in_place": 0.96},
        {"method": "pursuit", "segment": report.EPISODE, "reward": -2.0},
        {"method": best, "segment": "Go right", "in_place": 0.47},
        {"method": best, "segment": "Move top", "in_place": 0.375},
        {"method": best, "segment": report.EPISODE, "reward": 400.0},
    ]
    (line,) = report.following_costs(rows)
    assert "in place 100/96 % (Go right, Move top) and earns -2.0, 0 % of" in line
    assert "the best scripted team's 400.0; the best scripted team is in place 47/38 %" in line
    assert report.following_costs(rows[3:]) == []  # no path follower: no bullet
    assert report.following_costs(rows[:3]) == []  # no best scripted team: no bullet
    assert "highest reward in place" not in line  # no searched team on this page
    placed = "blend (defend=inf, collect=1, deliver=2 m; follow=pursuit)"
    rows += [
        {"method": placed, "segment": "Go right", "in_place": 0.92},
        {"method": placed, "segment": "Move top", "in_place": 0.97},
        {"method": placed, "segment": report.EPISODE, "reward": 220.0},
    ]
    (line,) = report.following_costs(rows)
    assert f"on every instruction (searched in experiments/language/frontier), `{placed}`" in line
    assert "is in place 92/97 % and earns 220.0, 55 %." in line


def test_the_arrival_check_names_a_robot_kept_at_home_as_what_breaks_the_formation():
    from types import SimpleNamespace

    import numpy as np

    go_right = _load(ROOT / "experiments" / "jobs.py").script(ROOT / "assets" / "go_right.py", "gr")
    slots = np.array([[2.3, 1.6], [2.3, 0.0], [2.3, -1.6]])

    def state(positions, intercepting=(False, False, False), formation=False):
        positions = np.asarray(positions, dtype=float)
        return SimpleNamespace(
            formation=formation,
            positions=positions,
            slot_distance=np.linalg.norm(positions - slots, axis=-1),
            intercepting=np.array(intercepting),
            present=np.ones(3, dtype=bool),
        )

    keeper = [[2.3, 1.6], [2.3, 0.0], [0.1, -0.2]]  # two at their slots, one at home
    assert go_right.kept_home(state(keeper))
    assert not go_right.kept_home(state(keeper, intercepting=(False, False, True)))  # excused
    assert not go_right.kept_home(state([[2.3, 1.6], [0.0, 0.0], [0.1, -0.2]]))  # two off
    assert not go_right.kept_home(state([[2.3, 1.6], [2.3, 0.0], [1.0, -1.0]]))  # off, not home
    assert not go_right.kept_home(state(slots, formation=True))
    # With --grace N the robot back from an interception is excused N ticks, then judged again.
    grace = go_right.RETURN_TICKS
    since = None
    for intercepting in [(False, False, True), (False, False, False)]:
        since = go_right.ticks_since(since, np.array(intercepting))
    assert since.tolist() == [10**6 + 1, 10**6 + 1, 1]
    on_way_back = state([[2.3, 1.6], [2.3, 0.0], [1.0, -1.0]])  # robot 2 off its slot
    assert go_right.in_formation(on_way_back, since <= grace)
    assert not go_right.in_formation(on_way_back, since <= go_right.GRACE)  # the default: 0
    for _ in range(grace):
        since = go_right.ticks_since(since, np.zeros(3, bool))
    assert not go_right.in_formation(on_way_back, since <= grace)  # 11 ticks later
    assert not go_right.kept_home(state(keeper), np.array([False, False, True]))  # excused


def test_the_consistency_page_holds_icco_against_wo_ce_at_5m_from_where_5m(tmp_path):
    run = _load(ROOT / "experiments" / "consistency" / "run.py")
    assert run.five_m_section(tmp_path / "where_5m.json") == ""  # nothing before it is measured
    mean = lambda m, s, n: {"mean": m, "std": s, "n": n}  # noqa: E731
    res = {
        "chosen": "icco_5m",
        "baseline": "wo_ce",
        "trials": 20,
        "settings": {
            "as trained": {
                "icco_5m": {"reward": mean(380.0, 20.0, 60), "mi_bound": mean(-1.0, 0.2, 3)},
                "wo_ce": {"reward": mean(385.0, 20.0, 60), "mi_bound": mean(-2.0, 0.2, 3)},
            }
        },
        "verdicts": {"as trained": {"reward": "within", "mi_bound": "ahead (+1.0)"}},
    }
    (tmp_path / "where_5m.json").write_text(json.dumps(res))
    text = run.five_m_section(tmp_path / "where_5m.json")
    assert "## At 5M: the reproduction's ICCO against ICCO w/o CE" in text
    assert "| as trained | mi_bound | -1.0 ± 0.2 | -2.0 ± 0.2 | ahead (+1.0) |" in text
    reading = run.where_reading(
        {
            **res,
            "settings": {
                "team 5": {
                    "icco_5m": {"mi_bound": mean(-1.0, 0, 3), "mi_null": mean(-1.5, 0, 3)},
                    "wo_ce": {"mi_bound": mean(-2.0, 0, 3), "mi_null": mean(-1.0, 0, 3)},
                },
            },
            "verdicts": {
                "team 5": {"reward": "behind (-9)", "consistency": "within the spread (0)"},
                "team 6": {"reward": "within the spread (1)", "mi_bound": "ahead (+1)"},
                "ambiguous": {"reward": "behind (-2)", "in_place: Spread out": "ahead (+0.1)"},
            },
        }
    ).splitlines()
    assert reading == [
        "- `icco_5m` against `wo_ce`, reward: behind in team 5, ambiguous; within the spread in "
        "team 6.",
        "- `icco_5m` against `wo_ce`, swap consistency: within the spread in team 5.",
        "- `icco_5m` against `wo_ce`, in place: ahead in ambiguous (Spread out).",
        "- The bound above its floor (nats, `icco_5m` against `wo_ce`): team 5 +0.5 against -1.0.",
    ]
    where = _load(ROOT / "experiments" / "consistency" / "where.py")
    assert where.SETTINGS["as trained"] == ("eval", [])
    assert all(p.parent.name.startswith("icco_seed") for p in where.five_m_policies("icco"))


def test_no_experiment_waits_forever_on_zero_jobs_or_trains_for_zero_trials():
    """``--jobs 0`` ran nothing and waited for it forever, ``--trials 0`` failed only after the
    training: every script that trains takes counts of at least 1, refused in one line
    otherwise, and the runner refuses 0 jobs too."""
    import argparse
    import re

    jobs = _load(ROOT / "experiments" / "jobs.py")
    assert jobs.positive("3") == 3
    for bad, said in (("0", "0: must be at least 1"), ("-2", "-2: must be"), ("x", "'x' is not")):
        with pytest.raises(argparse.ArgumentTypeError, match=re.escape(said)):
            jobs.positive(bad)
    with pytest.raises(ValueError, match="at least 1 run"):
        jobs.train_runs({ROOT / "never": (["method=icco"], 10)}, jobs=0)
    options = []
    for path in sorted((ROOT / "experiments").rglob("*.py")):
        text = path.read_text()
        if "train_runs" not in text and "--train-only" not in text:
            continue  # evaluates only: `icco eval` refuses a bad count at once
        pattern = r'"--(jobs|trials|steps)",\s*type=([\w.]+)'
        options += [(path.name, m.group(1), m.group(2)) for m in re.finditer(pattern, text)]
    assert len(options) >= 16, options
    assert all(kind.endswith("positive") for *_, kind in options), options


def test_long_training_reports_each_runs_frames_and_minutes_left(tmp_path):
    """A sweep of 100-minute runs prints where each run is: its last complete train.csv row (not
    a row still being written), its share of the budget and, at its pace so far, what is left."""
    jobs = _load(ROOT / "experiments" / "jobs.py")
    run = tmp_path / "qmix_seed0"
    run.mkdir()
    assert jobs.frames_logged(run) is None  # no train.csv yet
    (run / "train.csv").write_text("frames,updates\n")
    assert jobs.frames_logged(run) is None  # a header, no row
    (run / "train.csv").write_text("frames,updates\n512,0\n1024,3\n15")  # "15..." being written
    assert jobs.frames_logged(run) == 1024
    # The one reader of a log's last row: header from the top, row from the tail, however long.
    rows = "".join(f"{f},{f % 7},x{f}\n" for f in range(0, 2_000_000, 1000))
    (run / "eval.csv").write_text("frames,seed,name\n" + rows + "2000000,1")
    assert jobs.last_row(run / "eval.csv") == {"frames": "1999000", "seed": "3", "name": "x1999000"}
    (run / "eval.csv").write_text("frames,seed")  # a header still being written
    assert jobs.last_row(run / "eval.csv") is None
    assert jobs.last_row(run / "missing.csv") is None
    other = tmp_path / "icco_seed1"
    # qmix: 1,000 frames in 100 s since first seen (10/s), 3,000 to go: 300 s, 5 min.
    line = jobs.progress_line(
        {run: (5000, 1000, 2000, 100.0), other: (5000, 4096, 4096, 30.0)}, waiting=2
    )
    assert line == (
        "progress: qmix_seed0 2,000 of 5,000 frames (40 %), about 5 min left; "
        "icco_seed1 4,096 of 5,000 frames (82 %); 2 queued"
    )


def test_the_job_runner_prints_progress_while_its_runs_train(tmp_path, monkeypatch, capsys):
    """The runner's loop itself: a run that logs a row per poll shows up in a progress line."""
    jobs = _load(ROOT / "experiments" / "jobs.py")
    run = tmp_path / "icco_seed0"

    class Child:  # stands in for `icco train`: one more train.csv row at each poll, done at 4
        def __init__(self, command, **_):
            assert f"hydra.run.dir={run}" in command
            run.mkdir(parents=True, exist_ok=True)
            self.rows, self.returncode = 0, None

        def poll(self):
            self.rows += 1
            rows = "".join(f"{512 * k},0\n" for k in range(1, self.rows + 1))
            (run / "train.csv").write_text("frames,updates\n" + rows)
            if self.rows >= 4:
                self.returncode = 0
            return self.returncode

    monkeypatch.setattr(jobs.subprocess, "Popen", Child)
    monkeypatch.setattr(jobs.time, "sleep", lambda seconds: None)
    jobs.train_runs({run: (["method=icco"], 4096)}, jobs=1, report_every=0.0)
    out = capsys.readouterr().out
    assert "progress: icco_seed0 " in out and " of 4,096 frames (" in out
    assert out.rstrip().endswith("icco_seed0: done")


def test_the_in_place_frontier_picks_the_best_team_in_place_and_says_what_it_earns(tmp_path):
    frontier = _load(ROOT / "experiments" / "language" / "frontier" / "run.py")
    assert len(frontier.grid()) == 24 and all("follow=pursuit" in t for t in frontier.grid())
    row = lambda places, reward: {  # noqa: E731  (one team's row)
        "in_place": dict(zip(frontier.serving.INSTRUCTIONS, places)),
        "reward": reward,
        "formation": 0.5,
    }
    teams = {
        "a": row([0.9, 0.9, 0.9, 0.9], 200.0),
        "b": row([0.9, 0.79, 1.0, 1.0], 300.0),  # more reward, below 80 % on one instruction
        "c": row([0.8, 0.8, 0.8, 0.8], 210.0),  # exactly at the bar: in place
    }
    assert frontier.best_in_place(teams) == "c"
    assert frontier.best_in_place({"b": teams["b"]}) is None
    # A real run of one pursuing blend on one trial: it plays, files, and the page reads it back.
    team = "blend(defend=inf, follow=pursuit)"
    frontier.main(["--teams", team, "--trials", "1", "--out", str(tmp_path)])
    results = json.loads((tmp_path / "results.json").read_text())
    assert list(results["teams"]) == [*frontier.REFERENCES, team]
    assert results["teams"]["pursuit"]["in_place"]["Go right"] == 1.0  # the path follower
    page = (tmp_path / "README.md").read_text()
    assert f"`{team}`" in page and "| team | Go right |" in page
    (tmp_path / "README.md").unlink()
    frontier.main(["--report-only", "--out", str(tmp_path)])
    assert (tmp_path / "README.md").read_text() == page
