"""Learning from a scripted teacher (``train.teacher``): the teacher's rows, its share of every
replayed batch, evaluations untouched by it, and bad input."""

from __future__ import annotations

import pytest
import torch
from conftest import run_cli
from torchrl.envs.utils import ExplorationType, set_exploration_type

from icco_torchrl.envs.reference_policies import make_reference_policy
from icco_torchrl.modules.policy import TeacherRows
from icco_torchrl.training.build import build, teacher_items
from icco_torchrl.training.config import check_command_line, compose_config

torch.set_num_threads(1)
ACTION = ("agents", "action")
TEACHER = ["train.teacher=best_scripted", "train.teacher_envs=3", "train.teacher_share=0.25"]


def _run(*overrides):
    torch.manual_seed(0)
    cfg = compose_config(["experiment=smoke", "env.num_envs=8", *TEACHER, *overrides])
    return build(cfg, for_training=True)


def _teacher_stage(run) -> TeacherRows:
    return next(m for m in run.policy.module if isinstance(m, TeacherRows))


def test_the_first_rows_take_the_teachers_actions_and_remember_them():
    run = _run("train.eps_init=1.0")  # the learner explores at random: its actions differ
    td = run.env.reset()
    want = make_reference_policy("best_scripted", run.env)(td.clone())[ACTION]
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        out = run.policy(td)
    assert torch.equal(out[ACTION][:3], want[:3])
    assert not torch.equal(out[ACTION][3:], want[3:])  # the learner's rows are its own
    assert torch.equal(out["next", "agents", "prev_action"], out[ACTION])
    # the learner ran in shadow on the teacher's rows: its recurrent state and z are there
    assert out["next", "agents", "rnn_hidden"][:3].abs().sum() > 0
    assert out["agents", "z"][:3].abs().sum() > 0


def test_greedy_rollouts_and_evaluations_never_call_the_teacher():
    run = _run()

    def refuse(td):
        raise AssertionError("an evaluation called the teacher")

    _teacher_stage(run).__dict__["teacher"] = refuse
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        run.eval_env.rollout(5, run.policy)
        run.policy(run.env.reset())


def test_every_batch_holds_the_teachers_fixed_share():
    run = _run("train.batch_segments=8")
    assert teacher_items(run.cfg) == 2 and run.buffer.batch_size == 6
    with torch.no_grad():
        batch = run.env.rollout(40, run.policy, break_when_any_done=False)
    batch = batch.select(*run.loss.in_keys, strict=False)
    learner = run.teacher.split(batch)
    assert learner.shape[0] == 5 and len(run.teacher.buffer) > 0
    run.buffer.extend(run.cutter(learner))
    stored = run.teacher.buffer.storage
    for _ in range(5):
        sample = run.teacher.sample(run.buffer)
        assert sample.shape[0] == 8
        index = sample["index"].reshape(8, -1)[:, 0]  # an item's index, repeated per step
        # the last two items are the teacher buffer's, the first six the learner's
        assert torch.equal(sample[6:][ACTION], stored[index[6:]][ACTION])
        assert torch.equal(sample[:6][ACTION], run.buffer.storage[index[:6]][ACTION])


@pytest.mark.parametrize(
    "override, field",
    [
        ("train.teacher_share=1.0", "train.teacher_share"),
        ("train.teacher_share=-0.1", "train.teacher_share"),
        ("train.teacher_share=half", "train.teacher_share"),
        ("train.teacher=nonsense", "train.teacher"),
        ("train.teacher=random", "train.teacher"),
        ("train.teacher='blend(defend=-1)'", "train.teacher"),
        ("train.teacher_envs=8", "train.teacher_envs"),
        ("train.teacher_share=0.01", "train.teacher_share"),  # 0 items of a batch of 4
    ],
)
def test_bad_teacher_settings_fail_in_one_line_naming_the_field(override, field):
    message = check_command_line(["experiment=smoke", "env.num_envs=8", *TEACHER, override])
    assert message is not None and f"'{field}'" in message and "\n" not in message


def test_training_with_a_teacher_through_the_cli(tmp_path):
    proc = run_cli(
        "train", "experiment=smoke", "logger.progress=false", "train.teacher=best_scripted",
        "train.teacher_envs=2", f"hydra.run.dir={tmp_path}",
    )  # fmt: skip
    assert "final greedy evaluation" in proc.stdout
    assert (tmp_path / "checkpoint.pt").is_file()
    bad = run_cli("train", "experiment=smoke", "train.teacher_share=1", check=False)
    assert bad.returncode == 2 and "train.teacher_share" in bad.stderr + bad.stdout
