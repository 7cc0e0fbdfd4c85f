"""``icco instruct`` and the LLM instruction source, on the offline rule planner (no network)."""

import json

import pytest
import torch
from fake_openai import closed_port
from test_eval_cli import icco, smoke_checkpoints
from torchrl.envs.utils import step_mdp

from icco_torchrl.commands.instruct import out_dir_name
from icco_torchrl.envs import ResourceCollectionEnv
from icco_torchrl.envs.routes import DEFAULT_STEP
from icco_torchrl.instructions import LLMPlanner, LLMSource
from icco_torchrl.instructions.sources import split_instructions


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return smoke_checkpoints(tmp_path_factory, ["icco"])["icco"]


def scene(num_envs=4, seed=0):
    env = ResourceCollectionEnv(num_envs=num_envs, seed=seed, waypoint_mode="external")
    return env, env.reset()


def test_instruct_runs_a_schedule_of_instructions_and_writes_its_outputs(
    checkpoint, tmp_path, capsys
):
    out = tmp_path / "instruct"
    code = icco(
        "instruct",
        "Go right; Move top",
        f"checkpoint={checkpoint}",
        "eval.trials=2",
        "eval.steps=8",
        "eval.episodes=2",
        "eval.gif=true",
        f"eval.out_dir={out}",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    )
    assert code == 0, capsys.readouterr().err
    report = (out / "instruct.md").read_text()
    assert (
        '"Go right" -> "Move top"' in report and "| ICCO | 4 (1 seed) |" in report
    )  # 2 trials x 2 episodes
    summary = json.loads((out / "instruct.json").read_text())
    assert (
        summary["segments"] == ["Go right", "Move top"]
        and summary["model"] == "offline/rule-planner"
    )
    # one plan per trial and instruction, counted once per episode
    assert [
        (s["episode"], s["segment"], s["plans"], s["fallbacks"]) for s in summary["sources"]
    ] == [
        (0, "Go right", 2, 0),
        (0, "Move top", 2, 0),
        (1, "Go right", 2, 0),
        (1, "Move top", 2, 0),
    ]
    for name in (
        "instruct_trials.csv",
        "instruct_summary.csv",
        "instruct_trajectories.png",
        "instruct_reward.png",
        "instruct_icco.gif",
    ):
        assert (out / name).stat().st_size > 0, name


def test_offline_go_right_is_a_line_on_the_right_side_served_from_each_robot():
    env, td = scene()
    source = LLMSource(LLMPlanner(), "Go right")
    source.reset(env, td)
    slots = source.slots
    assert slots.shape == (4, 3, 2)
    assert torch.allclose(slots[..., 0], torch.full((4, 3), 0.7 * env.half), atol=1e-2)
    gaps = slots[..., 1].sort(-1).values.diff(dim=-1)
    assert (gaps > 0.5).all()  # spread along y
    waypoints = source(env, td, 0)
    assert waypoints.shape == (4, 3, 4, 2)
    # Served: the first waypoint a step from the robot, then a step apart, toward the slot.
    steps = torch.cat([env.pos.unsqueeze(-2), waypoints], -2).diff(dim=-2).norm(dim=-1)
    far = (slots - env.pos).norm(dim=-1) > 1.0 + 1e-3
    assert torch.allclose(steps[far], torch.full_like(steps[far], DEFAULT_STEP), atol=1e-5)
    assert source.stats == {"plans": 4, "failures": 0, "fallbacks": 0, "cache_hits": 0}
    assert source.reading == "line at the right side"


def test_task_aligned_prompt_sends_the_task_and_keeps_the_given_planner():
    env, td = scene(num_envs=2, seed=3)
    planner = LLMPlanner()
    source = LLMSource(planner, "Collect the resources and defend home", prompt="tap")
    assert planner.prompt == "plain" and source.prompt == "tap"
    source.reset(env, td)
    final = source.slots
    to_resource = (final[:, :, None] - env.res_pos[:, None]).norm(dim=-1).min(-1).values
    assert (to_resource < 1e-2).any(-1).all()  # some robot is sent to a resource in every env


def test_plans_are_asked_once_and_served_on_the_env_clock_and_fallbacks_counted():
    env, td = scene(num_envs=2)
    source = LLMSource(LLMPlanner(), "Spread out")
    source.reset(env, td)
    served = []
    for step in range(9):
        waypoints = source(env, td, step)
        if waypoints is not None:
            served.append(int(env.t[0]))
            env.write_waypoints(td, waypoints)
        td = step_mdp(env.step(td.set(("agents", "action"), torch.zeros(2, 3, dtype=torch.long))))
    assert served == [0, 4, 8]  # the env's waypoint interval, as in training
    assert source.stats["plans"] == 2  # one request per env, for the whole instruction
    fixed = LLMSource(LLMPlanner(), "Spread out", plan="fixed")
    fixed.reset(env, td)
    assert torch.equal(fixed(env, td, 0), fixed.server.routes[..., 1:, :])
    assert fixed(env, td, 4) is None  # written once and kept
    lost = LLMSource(LLMPlanner(max_retries=0), "Dance please")
    lost.reset(env, td)
    assert lost.stats["fallbacks"] == 2 and "Dance please" in lost.errors[0]
    assert torch.equal(lost.slots, env.waypoints[..., -1, :])  # the previous waypoints' ends
    with pytest.raises(ValueError, match="plan must be one of"):
        LLMSource(LLMPlanner(), "Go right", plan="sometimes")


def test_unknown_instruction_is_a_clear_error_naming_it(checkpoint, tmp_path, capsys):
    code = icco(
        "instruct",
        "Go right; Dance please",
        f"checkpoint={checkpoint}",
        f"hydra.run.dir={tmp_path}",
    )
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("icco instruct: ") and "'Dance please'" in err
    env, td = scene(num_envs=1)
    with pytest.raises(ValueError, match="'Dance please'"):
        LLMSource(LLMPlanner(), "Dance please", strict=True).reset(env, td)


def test_instruction_schedules_are_split_on_semicolons():
    assert split_instructions(" Go right ;Move top") == ["Go right", "Move top"]
    for bad in ("", "Go right;", ";"):
        with pytest.raises(ValueError, match="empty part"):
            split_instructions(bad)


def test_output_folders_of_different_schedules_are_different():
    long_a, long_b = (
        "Go right " + "and keep going " * 5 + "then stop",
        "Go right " + "and keep going " * 5 + "then turn",
    )
    assert long_a[:60] == long_b[:60]
    schedules = [
        ["Go right"],
        ["Go right 🚀"],
        ["Go right!"],
        ["go right"],
        [long_a],
        [long_b],
        ["Go right", "Move top"],
        ["Go right; Move top"],
        ["🚀"],
    ]
    names = [out_dir_name(s) for s in schedules]
    assert len(set(names)) == len(names), names
    assert names[0].startswith("instruct_go_right_") and names[-1].startswith("instruct_")
    assert out_dir_name(split_instructions("Go right ;Move top")) == out_dir_name(
        ["Go right", "Move top"]
    )
    assert all(
        name == name.encode("ascii", "ignore").decode() and "/" not in name for name in names
    )


UNREACHABLE = (
    "llm=openai",
    "llm.cache_dir=null",
    "llm.timeout_s=1",
    "llm.deadline_s=20",  # litellm's first import counts against it, slow on a loaded machine
    "llm.max_retries=1",
    "llm.backoff_s=0",
    "eval.trials=1",
    "eval.episodes=1",
    "eval.steps=4",
)


def test_an_unreachable_model_stops_instruct_with_one_line(
    checkpoint, tmp_path, capsys, monkeypatch
):
    monkeypatch.setenv("OPENAI_API_KEY", "sk-test")
    code = icco(
        "instruct",
        "Go right",
        f"checkpoint={checkpoint}",
        *UNREACHABLE,
        f"llm.api_base=http://127.0.0.1:{closed_port()}/v1",
        f"eval.out_dir={tmp_path / 'out'}",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    )
    err = capsys.readouterr().err.strip()
    assert (
        code == 2
        and err.startswith("icco instruct: LLM openai/gpt-4o")
        and len(err.splitlines()) == 1
    ), err
    assert "Connection refused" in err and "llm.fallback_on_error=true" in err
    assert not (tmp_path / "out").exists()


def test_with_fallbacks_instruct_runs_on_and_counts_them(checkpoint, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("OPENAI_API_KEY", "sk-test")
    code = icco(
        "instruct",
        "Go right 🚀",
        f"checkpoint={checkpoint}",
        *UNREACHABLE,
        "llm.fallback_on_error=true",
        f"llm.api_base=http://127.0.0.1:{closed_port()}/v1",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    )
    assert code == 0, capsys.readouterr().err
    out = checkpoint.parent / out_dir_name(
        ["Go right 🚀"]
    )  # the default folder, beside the checkpoint
    summary = json.loads((out / "instruct.json").read_text())
    assert summary["sources"] and all(s["fallbacks"] == s["plans"] > 0 for s in summary["sources"])


def _instruct_two_instructions(checkpoint, folder, tmp_path, capsys, *extra):
    """``icco instruct "Go right; Spread out"``, 2 trials of 6 steps per instruction, into
    ``folder``: the smallest run a language report reads."""
    code = icco(
        "instruct",
        "Go right; Spread out",
        f"eval.checkpoints=[{checkpoint}]",
        "eval.trials=2",
        "eval.steps=6",
        *extra,
        f"eval.out_dir={folder}",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    )
    assert code == 0, capsys.readouterr().err


def test_language_report_without_table_two_runs_reports_fig5b_and_lists_qmix_tap_missing(
    checkpoint, tmp_path, capsys
):
    """``experiments/language/run.py --methods icco qmix_full`` writes no Table II runs: the report
    still renders Fig. 5b, ICCO's Table II row, and names the missing QMIX-TAP rows; its reproduce
    line carries the narrowed agents and folders."""
    import os

    from test_experiments import ROOT, _load

    report = _load(ROOT / "experiments" / "language" / "report.py")

    out = tmp_path / "language"
    _instruct_two_instructions(checkpoint, out / "fig5b", tmp_path, capsys)
    (out / "run.json").write_text(
        json.dumps(
            {
                "budget": ["experiment=repro_5m"],
                "seeds": [0],
                "llm": "offline",
                "methods": ["icco", "qmix_full"],
                "sweep": "multirun/four_quadrants_5m",
                "out": os.path.relpath(out),
            }
        )
    )
    readme = tmp_path / "5m" / "README.md"
    assert report.main([str(out), "--readme", str(readme)]) == 0
    text = readme.read_text()
    assert "| QMIX-TAP | missing |" in text and "| QMIX-TAP w/o TR | missing |" in text
    assert "| ICCO | 4 |" in text  # 2 trials x 2 instructions, seed 0
    assert "Table II: missing QMIX-TAP, QMIX-TAP w/o TR; no comparison." in text
    assert "**Recipe.**" not in text  # the default page's history only
    # its own "only rewrite this file" line writes this page, not the default one
    assert f"report.py {os.path.relpath(out)} --readme {os.path.relpath(readme)}" in text
    assert (readme.parent / "figures" / "fig5b_reward.png").stat().st_size > 0
    results = json.loads((readme.parent / "results.json").read_text())
    assert list(results["table2"]["methods"]) == ["icco"]
    words = report.run_arguments(out, None, readme)
    assert words.startswith("--budget experiment=repro_5m --seeds 0 --methods icco qmix_full")
    assert "--sweep multirun/four_quadrants_5m" in words
    assert words.endswith(f"--out {os.path.relpath(out)} --readme {os.path.relpath(readme)}")


def test_table_two_runs_join_a_page_that_has_fig5b_beside_its_icco_row(
    checkpoint, tmp_path, capsys
):
    """``run.py --methods qmix`` writes Table II's task-aligned runs alone: ``report.py --table2``
    adds their rows, the verdict and the planner's statistics to the page rendered from Fig. 5b,
    keeps its ICCO row, gives the same page when run twice, and refuses another protocol."""
    import csv
    import os

    from test_experiments import ROOT, _load

    report = _load(ROOT / "experiments" / "language" / "report.py")

    def instruct(folder, *extra):
        _instruct_two_instructions(checkpoint, folder, tmp_path, capsys, *extra)

    page = tmp_path / "language"
    instruct(page / "fig5b")
    readme = tmp_path / "5m" / "README.md"
    assert report.main([str(page), "--readme", str(readme)]) == 0
    icco_row = json.loads((readme.parent / "results.json").read_text())["table2"]["methods"]["icco"]

    tap = tmp_path / "tap"
    instruct(tap / "table2_tap", "llm.prompt=tap")
    # The smoke checkpoint is ICCO's: its rows stand in for both task-aligned agents.
    trials = tap / "table2_tap" / "instruct_trials.csv"
    rows = list(csv.DictReader(trials.open()))
    learned = [r for r in rows if r["method"] == "ICCO-TAP"]
    relabelled = [{**r, "method": m} for m in ("QMIX-TAP", "QMIX-TAP w/o TR") for r in learned]
    with trials.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(relabelled + [r for r in rows if r["method"] != "ICCO-TAP"])
    (tap / "run.json").write_text(
        json.dumps({"budget": [], "seeds": [0], "methods": ["qmix"], "out": os.path.relpath(tap)})
    )

    assert report.main(["--table2", str(tap), "--readme", str(readme)]) == 0
    text = readme.read_text()
    assert "| QMIX-TAP | 4 |" in text and "| QMIX-TAP w/o TR | 4 |" in text  # 2 trials x 2
    assert "| ICCO | 4 |" in text and "Table II: missing" not in text
    assert "- **Paper (Table II): ICCO > QMIX-TAP > QMIX-TAP w/o TR" in text
    assert "Table II: instruction segments, 4 (ICCO, QMIX-TAP, QMIX-TAP w/o TR))." in text
    assert "| table2_tap | ICCO-TAP |" in text  # the planner's statistics of the added runs
    assert "--methods qmix --out" in text  # the command that made the added rows
    results = json.loads((readme.parent / "results.json").read_text())["table2"]["methods"]
    assert results["icco"] | {"share_of_best_scripted": None} == icco_row | {
        "share_of_best_scripted": None
    }
    assert {"qmix_tap", "qmix_tap_wo_tr"} <= set(results)
    # the pooled counts are the relabelled rows' own
    picks = [float(r["pick"]) for r in learned if r["segment"] != "episode"]
    assert results["qmix_tap"]["pick"]["mean"] == pytest.approx(sum(picks) / len(picks))
    assert report.main(["--table2", str(tap), "--readme", str(readme)]) == 0
    assert readme.read_text() == text  # adding twice changes nothing

    other = tmp_path / "other"
    instruct(other / "table2_tap", "llm.prompt=tap", "eval.trials=1")
    with pytest.raises(SystemExit, match="not the page's protocol, nothing written"):
        report.main(["--table2", str(other), "--readme", str(readme)])
    assert readme.read_text() == text
