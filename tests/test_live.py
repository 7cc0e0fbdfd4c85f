"""The live loop: it ticks in real time, takes instructions without blocking, reports what it
does; the live settings' ranges."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from icco_torchrl.instructions import LLMPlanner
from icco_torchrl.live import LiveLoop
from icco_torchrl.live.loop import MAX_INSTRUCTION, TOTALS, scripted_yardstick
from icco_torchrl.live.reading import (
    MAX_REASON,
    TAP_HINT,
    planner_reading,
    short_reason,
    understood_phrases,
    unused_words,
)
from icco_torchrl.modules.policy import make_policy
from icco_torchrl.training.build import build_components, compose_config, make_env
from icco_torchrl.training.config import ConfigError, validate

DEMO = Path(__file__).resolve().parents[1] / "assets" / "demo_icco.pt"


def team(method="icco", planner=None):
    cfg = compose_config([f"method={method}", "experiment=smoke"])
    parts = build_components(cfg)
    env = make_env(cfg, num_envs=1, seed=3, max_steps=40, waypoint_mode="external")
    policy = make_policy(parts["agent"], env.full_action_spec_unbatched, parts["coordinator"])
    return LiveLoop(env, policy, planner)


class SlowPlanner:
    """Answers after ``delay`` seconds with fixed waypoints (or fails)."""

    def __init__(self, delay, ok=True):
        self.delay, self.ok = delay, ok
        self.calls = 0

    def plan(self, instruction, positions, previous=None, **kwargs):
        from icco_torchrl.instructions.llm import PlanResult

        self.calls += 1
        time.sleep(self.delay)
        wp = np.full(previous.shape, 1.5, dtype=np.float32)
        return PlanResult(
            wp if self.ok else previous,
            self.ok,
            1,
            None if self.ok else "previous",
            None if self.ok else "not understood",
        )


def test_ticks_step_the_team_and_report_it():
    loop = team()
    states = [
        loop.tick() for _ in range(45)
    ]  # past max_steps: a new episode starts, the loop goes on
    assert [s.tick for s in states] == list(range(1, 46))
    assert states[39].step == 40 and states[40].step == 1  # a new episode after the env's last step
    s = states[-1]
    assert s.positions.shape == (3, 2) and s.waypoints.shape == (3, 4, 2) and s.z.shape[0] == 3
    assert set(s.totals) >= {"pick", "collect", "defense", "invasion", "inst_reward", "reward"}
    # The totals are the episode's: the last step of one holds its sums, then they restart.
    first, second = states[:40], states[40:]
    assert [x.episode for x in (first[0], first[-1], second[0])] == [1, 1, 2]
    assert s.episode_steps == 40 and loop.episode == 2
    for episode in (first, second):
        total = sum(x.events["reward"] for x in episode)
        assert episode[-1].totals["reward"] == pytest.approx(total, abs=1e-4)
    assert second[0].totals["invasion"] == second[0].events["invasion"]
    assert isinstance(s.to_dict()["positions"], list)  # JSON-ready


def test_the_instruction_outlasts_the_episode_and_is_planned_once_per_episode():
    planner = SlowPlanner(delay=0.0)
    loop = team(planner=planner)
    assert loop.snapshot().plan is None and loop.snapshot().slots is None  # no instruction yet
    loop.instruct("Go right")
    assert loop.wait_for_plan(5).state == "used"
    states = []
    for _ in range(45):
        states.append(loop.tick())
        loop.wait_for_plan(5)  # a new episode asks the planner again: let it answer
    assert states[39].episode == 1 and states[40].episode == 2
    assert all(np.allclose(x.slots, 1.5) for x in states)  # every plan's slots: (1.5, 1.5)
    assert all(x.plan == "Go right" for x in states)
    assert planner.calls == 2  # one request per instruction and episode
    # The waypoints are served from where the robots are, toward their slots: never the plan's
    # points as given (all at (1.5, 1.5)), except for a robot within a step of its slot.
    far = [x for x in states if (x.slot_distance > 1.0).all()]
    assert far and all(not np.allclose(x.waypoints, 1.5) for x in far)
    state = loop.reset()  # a reset is a new episode too: the instruction stays, planned again
    loop.wait_for_plan(5)
    assert state.episode == 3 and state.plan == "Go right" and np.allclose(state.slots, 1.5)
    assert planner.calls == 3 and loop.status.instruction == "Go right"
    assert state.totals["reward"] == 0.0 and loop.status.state == "used"


def test_each_state_says_how_far_each_robot_is_from_its_slot():
    loop = team(planner=SlowPlanner(delay=0.0))
    loop.instruct("Go right")
    loop.wait_for_plan(5)
    for s in (loop.tick(), loop.snapshot()):  # every slot at (1.5, 1.5): the distance to it
        want = np.linalg.norm(s.positions - 1.5, axis=1)
        assert np.allclose(s.slot_distance, want, atol=2e-3) and (want > 0.01).any()
        assert np.array_equal(s.at_slot, want <= 0.5)
    assert isinstance(s.to_dict()["slot_distance"], list)
    assert isinstance(s.to_dict()["formation"], bool)


def test_the_mean_over_finished_episodes_leaves_out_one_cut_short():
    loop = team()  # episodes of 40 steps
    first = [loop.tick() for _ in range(40)]
    assert first[-1].finished == 0 and first[-1].finished_mean == {}
    second = [loop.tick() for _ in range(40)]
    after = loop.tick()
    assert second[0].finished == 1 and after.finished == 2
    want = {k: (first[-1].totals[k] + second[-1].totals[k]) / 2 for k in first[-1].totals}
    assert after.finished_mean == pytest.approx(want)
    loop.tick()
    state = loop.reset()  # the episode under way was cut short: not a finished one
    assert state.finished == 2 and state.finished_mean == pytest.approx(want)


def test_a_checkpoint_plays_episodes_as_long_as_it_was_trained_on():
    # An endless episode would show totals nobody watched and step counts the policy never saw.
    loop = LiveLoop.from_checkpoint(DEMO, planner=None, seed=0)
    assert loop.raw.max_steps == 145 and loop.tick().episode_steps == 145
    assert LiveLoop.from_checkpoint(DEMO, episode_steps=20).raw.max_steps == 20


def test_an_instruction_is_planned_beside_the_loop_and_applied_on_the_next_tick():
    loop = team(planner=SlowPlanner(delay=0.5))
    before = loop.tick().waypoints
    start = time.perf_counter()
    loop.instruct("Go right")
    assert time.perf_counter() - start < 0.1  # returns at once
    during = [loop.tick() for _ in range(3)]  # the team keeps moving on its old plan meanwhile
    assert time.perf_counter() - start < 0.45
    assert all(s.planner["state"] == "thinking" for s in during)
    assert np.allclose(during[-1].waypoints, before)
    assert loop.wait_for_plan(5).state == "used"
    after = loop.tick()
    assert np.allclose(after.slots, 1.5) and after.planner["instruction"] == "Go right"
    # Served from where each robot was: its first waypoint one step toward (1.5, 1.5).
    first = after.waypoints[:, 0] - during[-1].positions
    toward = 1.5 - during[-1].positions
    cos = (
        (first * toward).sum(-1) / np.linalg.norm(first, axis=-1) / np.linalg.norm(toward, axis=-1)
    )
    assert (cos > 0.99).all()


def test_an_unknown_instruction_is_reported_and_the_last_plan_kept():
    loop = team(planner=LLMPlanner(fallback_on_error=True))  # the offline rule planner
    loop.instruct("Go right")
    assert loop.wait_for_plan(30).state == "used"
    planned = loop.tick().slots
    loop.instruct("make me a sandwich")
    status = loop.wait_for_plan(30)
    assert status.state == "fell back" and status.error
    # The offline planner's list of what it understands comes with it, in full.
    assert status.understood == understood_phrases("anything else", 3.25)
    assert "spread out" in status.understood and "quadrant 1-4" in status.understood
    assert status.unused is None and status.hint is None
    assert np.allclose(loop.tick().slots, planned)  # the plan in use stays
    with pytest.raises(ValueError, match="non-empty"):
        loop.instruct("   ")
    with pytest.raises(ValueError, match=f"too long: {MAX_INSTRUCTION + 1} characters"):
        loop.instruct("x" * (MAX_INSTRUCTION + 1))
    # The status says how the planner read an instruction it understood.
    seen = []
    loop.on_status = seen.append
    loop.instruct("flank the intruder")
    assert loop.wait_for_plan(30).reading == "defend home"
    assert [s.state for s in seen] == ["thinking", "used"] and seen[-1] is loop.status
    # Words the reading did not rest on are named, and never silently another intent: the
    # invader is the object of "avoiding", which the planner cannot do.
    loop.instruct("Go right avoiding the invader")
    status = loop.wait_for_plan(30)
    assert status.reading == "line at the right side" and status.unused == ["avoiding", "invader"]
    loop.instruct("Gather center")
    assert loop.wait_for_plan(30).unused == []  # "gather" is read: a cluster, not a line
    loop.instruct("Defend home")
    assert loop.wait_for_plan(30).unused == []  # "home" is what is defended
    loop.instruct("Go right")
    assert loop.wait_for_plan(30).unused == [] and loop.status.understood is None


def test_words_are_unused_when_the_reading_does_not_rest_on_them():
    assert unused_words("flank the intruder", 3.25) == ["flank"]
    assert unused_words("gather at the top, quickly!", 3.25) == ["quickly"]
    assert unused_words("collect the resources", 3.25) == []  # either word alone would do
    assert unused_words("make me a sandwich", 3.25) == []  # not understood at all
    assert understood_phrases("Go right", 3.25) is None
    assert understood_phrases("don't go left", 3.25) is None  # refused for its negation


def test_a_reason_naming_the_task_aligned_prompt_says_how_to_turn_it_on():
    loop = team(planner=LLMPlanner(fallback_on_error=True))  # the paper's plain prompt
    loop.instruct("collect the resources")
    status = loop.wait_for_plan(30)
    assert status.state == "fell back" and "task-aligned prompt" in status.error
    assert status.hint == TAP_HINT and "llm.prompt=tap" in status.hint
    loop = team(planner=LLMPlanner(fallback_on_error=True, prompt="tap"))
    loop.instruct("collect the resources")
    assert loop.wait_for_plan(30).state == "used" and loop.status.hint is None
    other = team(planner=SlowPlanner(delay=0.0))  # not the rule planner: no word lists
    other.instruct("Go right")
    assert other.wait_for_plan(5).unused is None


def test_a_fall_back_reason_is_short():
    loop = team(planner=LLMPlanner(fallback_on_error=True))
    loop.instruct("make me a sandwich")
    status = loop.wait_for_plan(30)
    assert status.state == "fell back" and status.error == "unknown instruction"
    long = "planner declined: " + "x" * 5000 + "; understood: everything"
    assert len(short_reason(long)) == MAX_REASON and short_reason(long).endswith("...")
    assert short_reason("planner declined: no plan 'Go up'; understood: a", "Go up") == "no plan"


def test_the_planner_reading_is_its_replys_movement_strategy():
    reply = '{"movement_strategy": "Rule planner (not an LLM): gather at the centre.", "a": 1}'
    assert planner_reading(reply) == "gather at the centre"
    assert planner_reading('Sure! {"movement_strategy": "  sweep   east  "}') == "sweep east"
    assert planner_reading('{"movement_strategy": "' + "a" * 500 + '"}').endswith("...")
    assert planner_reading('{"agent_0": []}') is None and planner_reading(None) is None


def test_a_newer_instruction_supersedes_one_still_being_planned():
    planner = SlowPlanner(delay=0.3)
    loop = team(planner=planner)
    loop.instruct("Go right")
    loop.instruct("Move top")
    assert loop.wait_for_plan(5).instruction == "Move top"
    time.sleep(0.4)  # the first answer arrives late and is dropped
    # "Go right" was planned, or replaced before the planner thread took it.
    assert loop.status.instruction == "Move top" and planner.calls in (1, 2)
    assert loop.status.state == "used" and np.allclose(loop.tick().slots, 1.5)


@pytest.fixture
def slow_llm(monkeypatch):
    """An LLMPlanner whose model answers after ``delay`` s (a litellm custom provider); yields
    ``(planner, calls)``. Its requests cannot be interrupted, as a real HTTP request cannot."""
    from icco_torchrl.instructions.llm import _litellm

    litellm = _litellm()
    calls, release = [], threading.Event()

    class Slow(litellm.CustomLLM):
        delay = 0.6  # a test may make it slower

        def completion(self, *args, **kwargs):
            from icco_torchrl.instructions.planner import reply_to

            calls.append(time.monotonic())
            release.wait(Slow.delay)  # bounded: a slow model, not a hung test
            message = {"role": "assistant", "content": reply_to(kwargs["messages"])}
            return litellm.ModelResponse(
                choices=[{"index": 0, "finish_reason": "stop", "message": message}]
            )

    entry = {"provider": "slowtest", "custom_handler": Slow()}
    monkeypatch.setattr(litellm, "custom_provider_map", [*litellm.custom_provider_map, entry])
    planner = LLMPlanner(model="slowtest/x", deadline_s=10.0, max_retries=0)
    planner.slow_model = Slow
    yield planner, calls
    release.set()


def test_a_newer_instruction_cancels_the_request_in_flight(slow_llm):
    planner, calls = slow_llm
    planner.slow_model.delay = 4.0  # far longer than any scheduling delay on a loaded machine
    loop = team(planner=planner)
    loop.instruct("Go right")
    deadline = time.monotonic() + 5
    while not calls and time.monotonic() < deadline:  # its request is on its way
        time.sleep(0.01)
    loop.instruct("Move top")
    status = loop.wait_for_plan(8)
    # Without the cancel the second request would start only when the first one answers (4 s).
    assert len(calls) == 2 and calls[1] - calls[0] < 2.0
    assert status.state == "used" and status.instruction == "Move top"


def test_a_hundred_instructions_against_a_slow_model_keep_the_threads_bounded(slow_llm):
    from icco_torchrl.instructions.llm import MAX_REQUESTS

    planner, calls = slow_llm
    loop = team(planner=planner)
    before, most = threading.active_count(), 0
    for i in range(100):
        loop.instruct(f"go to ({i % 3}, 1)")
        most = max(most, threading.active_count() - before)
        time.sleep(0.005)
    status = loop.wait_for_plan(10)
    assert most <= 1 + MAX_REQUESTS  # the planner thread and its requests, not 2 per instruction
    assert status.state == "used" and status.instruction == "go to (0, 1)"  # the last one
    assert status.requests == 100 and len(calls) <= 6  # superseded ones never reached the model
    time.sleep(0.7)  # the abandoned requests end at their own pace
    assert threading.active_count() <= before


class RecordingPlanner:
    """Plans every present robot to the right edge; records how many robots each plan was for."""

    def __init__(self):
        self.teams = []

    def plan(self, instruction, positions, previous=None, **kwargs):
        from icco_torchrl.instructions.llm import PlanResult

        self.teams.append(len(positions))
        return PlanResult(np.full(previous.shape, 2.0, dtype=np.float32), True, 1, "{}")


def test_robots_join_and_leave_between_ticks_and_the_team_keeps_acting():
    """The demo policy (trained on 3) in a loop that holds 5: the team grows and shrinks between
    ticks, the others keep their memory, the new one starts from zero, the plan follows the
    team, and every robot of the team keeps moving."""
    planner = RecordingPlanner()
    loop = LiveLoop.from_checkpoint(DEMO, planner=planner, seed=0, max_robots=5)
    assert loop.raw.n_agents == 5 and loop.team == [0, 1, 2]
    for _ in range(6):
        state = loop.tick()
    assert state.present.tolist() == [True, True, True, False, False]
    loop.instruct("Go right")
    assert loop.wait_for_plan(5).state == "used" and planner.teams == [3]
    loop.tick()
    hidden = loop.td["agents", "rnn_hidden"][0].clone()
    assert hidden[:3].abs().sum() > 0
    assert loop.add_robot() == 3 and loop.team == [0, 1, 2, 3]
    held = loop.td["agents", "rnn_hidden"][0]
    assert torch.equal(held[:3], hidden[:3]) and not held[3].any()  # theirs kept, its own zero
    assert not loop.td["agents", "z"][0, 3].any() and loop.td["agents", "present"][0, 3, 0]
    assert loop.wait_for_plan(5).state == "used" and planner.teams == [3, 4]  # planned again
    start = loop.tick()
    assert np.allclose(start.slots[:4], 2.0) and start.present[3]
    for _ in range(15):
        state = loop.tick()
    moved = np.linalg.norm(state.positions - start.positions, axis=-1)
    assert (moved[:4] > 0.1).all() and moved[4] == 0, moved  # the policy drives all four
    loop.remove_robot(1)
    assert loop.wait_for_plan(5).state == "used" and planner.teams == [3, 4, 3]
    hidden = loop.td["agents", "rnn_hidden"][0].clone()
    before = loop.tick()
    assert before.present.tolist() == [True, False, True, True, False]
    for _ in range(15):
        state = loop.tick()
    moved = np.linalg.norm(state.positions - before.positions, axis=-1)
    assert (moved[[0, 2, 3]] > 0.1).all() and moved[1] == 0, moved  # it left; they go on
    # The team outlasts the episode: the next one starts with the same robots.
    while state.episode == 1:
        state = loop.tick()
    assert state.present.tolist() == [True, False, True, True, False]
    assert loop.reset().present.tolist() == [True, False, True, True, False]


def test_a_bad_team_change_is_one_line_and_changes_nothing():
    loop = team()  # a full team of 3
    state = loop.tick()
    for change, message in [
        (loop.add_robot, "the team is full: 3 robots"),
        (lambda: loop.add_robot(1), "robot 1 is already in the team"),
        (lambda: loop.remove_robot(7), r"robot must be an integer in 0\.\.2, got 7"),
        (lambda: loop.remove_robot("1"), "robot must be an integer"),
        (lambda: loop.remove_robot(True), "robot must be an integer"),
    ]:
        with pytest.raises(ValueError, match=message) as err:
            change()
        assert "\n" not in str(err.value)
    loop.remove_robot(2)
    loop.remove_robot(0)
    with pytest.raises(ValueError, match="robot 2 is not in the team"):
        loop.remove_robot(2)
    with pytest.raises(ValueError, match="robot 1 is the last robot"):
        loop.remove_robot(1)
    assert loop.team == [1] and loop.tick().tick == state.tick + 1  # it keeps ticking
    with pytest.raises(ValueError, match="a live team needs at least one robot"):
        LiveLoop(loop.env, loop.policy, team=[])


def test_run_keeps_its_rate_and_refuses_a_batched_env():
    loop = team(method="qmix")
    start = time.perf_counter()
    latencies = loop.run(10, rate_hz=50)
    assert 0.17 < time.perf_counter() - start < 1.5 and len(latencies) == 10
    cfg = compose_config(["method=qmix", "experiment=smoke"])
    with pytest.raises(ValueError, match="num_envs=1"):
        LiveLoop(make_env(cfg, num_envs=2, waypoint_mode="external"), None)


@pytest.mark.parametrize(
    "override, message",
    [
        ({"rate_hz": 0}, "'live.rate_hz' must be > 0"),
        ({"timeout_s": -1}, "'live.timeout_s' must be > 0"),
        ({"robot_radius": 0}, "'live.robot_radius' must be > 0"),
        ({"seconds": 0}, "'live.seconds' must be > 0"),
        ({"port": -1}, "'live.port' must be >= 0"),
        ({"web_port": 70000}, "'live.web_port' must be <= 65535"),
        ({"max_robots": 0}, "'live.max_robots' must be >= 1"),
        ({"reference_episodes": -1}, "'live.reference_episodes' must be >= 0"),
    ],
)
def test_live_settings_are_range_checked_from_their_fields(override, message):
    with pytest.raises(ConfigError, match=message):
        validate({"live": override})
    assert validate({"live": {"seconds": None, "port": 0}}).live.port == 0


def test_the_yardstick_is_the_best_scripted_team_on_the_policys_training_episodes():
    """What the page shows beside its running mean: the best scripted team's mean totals over
    episodes of the checkpoint's training env, the same each time, ahead of the pure follower on
    the same episodes (the role blend defends where the follower does not)."""
    from icco_torchrl.envs.reference_policies import make_reference_policy
    from icco_torchrl.evaluation.rollout import evaluate
    from icco_torchrl.training.restore import restore

    ref = scripted_yardstick(DEMO, 4, seed=5)
    assert ref["label"].startswith("best scripted (") and (ref["episodes"], ref["steps"]) == (
        4,
        145,
    )
    assert set(TOTALS) <= set(ref) and ref == scripted_yardstick(DEMO, 4, seed=5)
    env = restore(DEMO, num_envs=4, seed=5)["env"]
    follower = evaluate(env, make_reference_policy("follower", env), seed=5)
    assert ref["reward"] > follower["reward"] and ref["defense"] > follower["defense"]
    assert scripted_yardstick(DEMO, 0) is None
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="live.reference_episodes must be an integer >= 0"):
            scripted_yardstick(DEMO, bad)


def test_the_running_mean_starts_again_with_a_new_instruction():
    planner = SlowPlanner(delay=0.0)
    loop = team(planner=planner)  # episodes of 40 steps
    loop.instruct("Go right")
    loop.wait_for_plan(5)
    for _ in range(41):
        state = loop.tick()
        loop.wait_for_plan(5)
    assert state.finished == 1 and state.finished_mean  # one episode under "Go right"
    loop.instruct("Go right")  # the same instruction again: the mean goes on
    loop.wait_for_plan(5)
    assert loop.tick().finished == 1
    loop.instruct("Move top")
    loop.wait_for_plan(5)
    state = loop.tick()
    assert state.plan == "Move top" and state.finished == 0 and state.finished_mean == {}
