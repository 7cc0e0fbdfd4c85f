"""The experiment scripts' run lists compose into valid configs (a typo there would only show
after hours), and the README's count of the VMAS example's ICCO lines is the example's."""

from __future__ import annotations

import importlib.util
from pathlib import Path

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
