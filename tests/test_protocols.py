"""Instruction-schedule protocols: metrics reward following the instruction, segments add up
to the episode, and bad input fails before any work."""

import math

import numpy as np
import pytest
import torch

from icco_torchrl.envs import FixedSource, QuadrantSource, RandomWalkSource, ResourceCollectionEnv
from icco_torchrl.envs.reference_policies import reference_label
from icco_torchrl.evaluation import metrics
from icco_torchrl.evaluation.metrics import (
    ADDITIVE,
    EPISODE,
    METRICS,
    SHARE,
    SHARE_KEY,
    best_scripted_shares,
    markdown_table,
    results_json,
    summarize,
)
from icco_torchrl.evaluation.protocols import quadrant_schedule, run_schedule

TRIALS, STEPS = 6, 30


def quadrant_env(steps=STEPS, trials=TRIALS, seed=0):
    return ResourceCollectionEnv(
        num_envs=trials, seed=seed, max_steps=4 * steps, waypoint_mode="external"
    )


def follower(env):
    """Heads for each robot's second waypoint along its larger axis gap: follows the instruction."""

    def policy(td):
        gap = env.waypoints[:, :, 1] - env.pos
        along_x = torch.where(gap[..., 0] > 0, 2, 1)
        along_y = torch.where(gap[..., 1] > 0, 4, 3)
        td.set(
            ("agents", "action"),
            torch.where(gap[..., 0].abs() > gap[..., 1].abs(), along_x, along_y),
        )
        return td

    return policy


def random_policy(env, seed=0):
    gen = torch.Generator().manual_seed(seed)

    def policy(td):
        td.set(
            ("agents", "action"), torch.randint(0, 5, (env.num_envs, env.n_agents), generator=gen)
        )
        return td

    return policy


@pytest.fixture(scope="module")
def runs():
    out = {}
    for name, make in (("follower", follower), ("random", random_policy)):
        env = quadrant_env()
        out[name] = run_schedule(env, make(env), quadrant_schedule(STEPS), TRIALS, method=name)
    return out


def episode(run, metric):
    return np.array([r[metric] for r in run.rows if r["segment"] == EPISODE])


def test_following_the_instruction_scores_better_than_acting_at_random(runs):
    follow, rand = runs["follower"], runs["random"]
    assert episode(follow, "in_quadrant").mean() > episode(rand, "in_quadrant").mean() + 0.2
    assert episode(follow, "waypoint_dist").mean() < episode(rand, "waypoint_dist").mean() - 0.3
    assert episode(follow, "inst_reward").mean() > episode(rand, "inst_reward").mean()


def test_segments_add_up_to_the_episode(runs):
    run = runs["follower"]
    assert run.names == ["quadrant 1", "quadrant 2", "quadrant 3", "quadrant 4"]
    assert run.bounds == [(0, 30), (30, 60), (60, 90), (90, 120)]
    for trial in range(TRIALS):
        rows = [r for r in run.rows if r["trial"] == trial]
        segments, whole = rows[:-1], rows[-1]
        assert (
            whole["segment"] == EPISODE
            and whole["steps"] == sum(r["steps"] for r in segments) == 120
        )
        for key in ADDITIVE:
            assert math.isclose(
                sum(r[key] for r in segments), whole[key], rel_tol=1e-5, abs_tol=1e-4
            ), key
        for key in ("waypoint_dist", "in_quadrant"):  # step-weighted means
            weighted = sum(r[key] * r["steps"] for r in segments) / whole["steps"]
            assert math.isclose(weighted, whole[key], rel_tol=1e-5), key
        # ...and the episode totals are the env's own step values.
        assert math.isclose(
            whole["reward"], float(run.per_step["reward"][:, trial].sum()), rel_tol=1e-5
        )
        assert math.isclose(
            whole["task_reward"] + whole["inst_reward"], whole["reward"], rel_tol=1e-5, abs_tol=1e-4
        )


def test_trajectories_are_recorded_for_figures(runs):
    traj, (T, B) = runs["random"].trajectory, (4 * STEPS, TRIALS)
    assert traj["pos"].shape == (T + 1, B, 3, 2) and traj["waypoints"].shape == (T, B, 3, 4, 2)
    assert traj["carry"].shape == traj["defended"].shape == (T + 1, B, 3)
    assert traj["res_pos"].shape == (T + 1, B, 6, 2) and traj["inv_active"].shape == (T + 1, B, 1)
    # the waypoints in force during quadrant 3 lie in quadrant 3
    assert (traj["waypoints"][2 * STEPS : 3 * STEPS] < 0).all()


def test_schedules_mix_sources_and_metrics_skip_quadrant_where_there_is_none():
    env = ResourceCollectionEnv(num_envs=2, seed=1, max_steps=12, waypoint_mode="external")
    schedule = [
        ("walk", RandomWalkSource(), 5),
        ("hold", FixedSource(torch.zeros(3, 4, 2)), 4),
        ("q2", QuadrantSource(2), 3),
    ]
    run = run_schedule(env, random_policy(env), schedule, trials=2, method="x")
    rows = {(r["trial"], r["segment"]): r for r in run.rows}
    assert math.isnan(rows[0, "walk"]["in_quadrant"]) and not math.isnan(
        rows[0, "q2"]["in_quadrant"]
    )
    assert rows[0, EPISODE]["in_quadrant"] == rows[0, "q2"]["in_quadrant"]
    assert np.allclose(run.trajectory["waypoints"][5:9], 0.0)


@pytest.mark.parametrize("trials", [0, -1, 2.0, True])
def test_zero_trials_fail_fast(trials):
    with pytest.raises(ValueError, match="trials"):
        run_schedule(quadrant_env(trials=2), None, quadrant_schedule(5), trials)


def test_zero_steps_and_empty_schedules_fail_fast_naming_the_segment():
    env = quadrant_env(steps=5, trials=2)
    with pytest.raises(ValueError, match="'quadrant 1' has steps=0"):
        run_schedule(env, None, quadrant_schedule(0), 2)
    with pytest.raises(ValueError, match="empty"):
        run_schedule(env, None, [], 2)


def test_an_env_unfit_for_the_schedule_is_refused():
    schedule = quadrant_schedule(5)
    with pytest.raises(ValueError, match="num_envs=trials"):
        run_schedule(quadrant_env(steps=5, trials=3), None, schedule, 2)
    with pytest.raises(ValueError, match="max_steps=20"):
        run_schedule(
            ResourceCollectionEnv(num_envs=2, max_steps=10, waypoint_mode="external"),
            None,
            schedule,
            2,
        )
    with pytest.raises(ValueError, match="external"):
        run_schedule(ResourceCollectionEnv(num_envs=2, max_steps=20), None, schedule, 2)


def test_summary_table_has_a_row_per_method_and_reports_missing_ones(runs):
    summary = summarize(runs["follower"].rows + runs["random"].rows)
    table = markdown_table(summary, ("reward", "in_quadrant"), missing=["ICCO"])
    lines = table.splitlines()
    assert len(lines) == 2 + 3
    assert lines[2].startswith("| follower | 6 (1 seed) | ") and " ± " in lines[2]
    assert lines[4] == "| ICCO | missing | – | – |"


def test_reports_state_each_team_reward_as_a_share_of_the_best_scripted_team():
    best = reference_label("best_scripted")
    rows = [
        dict(
            method=method,
            seed=seed,
            trial=t,
            segment=EPISODE,
            steps=4,
            **dict.fromkeys(METRICS, 0.0),
        )
        for method, seed, reward in (("ICCO", 0, 300.0), (best, -1, 400.0), ("follower", -1, 280.0))
        for t in range(2)
    ]
    for row, reward in zip(rows, [300.0, 300.0, 400.0, 400.0, 280.0, 280.0]):
        row["reward"] = reward
    summary = summarize(rows)
    assert best_scripted_shares(summary) == {"ICCO": 0.75, best: 1.0, "follower": 0.7}
    lines = markdown_table(summary, ("reward",), missing=["QMIX"]).splitlines()
    assert lines[0] == f"| method | trials | reward | {SHARE} |"
    assert lines[2].endswith("| 300.0 ± 0.0 | 75 % |") and lines[5] == "| QMIX | missing | – | – |"
    report = results_json(summary, protocol="quadrants", steps=4, trials=2)["methods"]
    assert set(report) == {"icco", "best_scripted", "follower"}
    assert report["icco"][SHARE_KEY] == 0.75 and report["icco"]["seeds"] == 1
    assert report["best_scripted"]["label"] == best and report["best_scripted"]["seeds"] == 0
    # without a best scripted row, no share column and no share key
    plain = [r for r in summary if r["method"] != best]
    assert SHARE not in markdown_table(plain, ("reward",))
    assert SHARE_KEY not in results_json(plain, protocol="q", steps=4, trials=2)["methods"]["icco"]
    # a team just below zero (a path follower that ignores the task) reads 0 %, never -0 %
    assert [metrics.share_text(v) for v in (-0.004, -0.006, 0.995)] == ["0 %", "-1 %", "100 %"]


def test_trajectory_figure_titles_clear_the_row_above(runs, tmp_path, monkeypatch):
    """Each row's panel titles sit below the panels of the row above (three-line first-row
    titles once overlapped the second row's with tight_layout)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from icco_torchrl.evaluation import plots

    figures, save = [], plots.save
    monkeypatch.setattr(plots, "save", lambda fig, stem: figures.append(fig) or save(fig, stem))
    # six columns and two rows, as `icco instruct` draws one method and its five references
    six = {f"{name} {i}": run for i in range(3) for name, run in runs.items()}
    plots.plot_trajectories(six, tmp_path / "trajectories", segments=(0, 1))
    fig = figures[0]
    FigureCanvasAgg(fig).draw()
    renderer = fig.canvas.get_renderer()
    axes = np.array(fig.axes).reshape(2, len(six))
    for above, below in zip(axes[:-1], axes[1:]):
        for top, bottom in zip(above, below):
            title = bottom.title.get_window_extent(renderer)
            assert title.y1 < top.get_window_extent(renderer).y0, bottom.get_title()


def test_learning_curve_states_the_last_reward_as_a_share_of_the_best_scripted_team(
    tmp_path, monkeypatch
):
    from icco_torchrl.evaluation import plots

    columns = ("frames", "reward", "reward_std", "task_reward", "task_reward_std")
    rows = ["1000,200,10,50,5", "2000,300,10,80,5"]
    (tmp_path / "eval.csv").write_text("\n".join([",".join(columns), *rows]) + "\n")
    titles = []
    monkeypatch.setattr(
        plots.Figure,
        "savefig",
        lambda fig, *a, **k: titles.extend(ax.get_title() for ax in fig.axes),
    )
    refs = {reference_label("best_scripted"): {"reward": 400.0, "task_reward": 190.0}}
    plots.plot_learning_curve(tmp_path, refs)
    assert titles[0].endswith("last: 75 % of the best scripted team's")
