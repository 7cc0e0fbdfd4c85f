"""The live loop: it ticks in real time, takes instructions without blocking, reports what it
does; the live settings' ranges."""

from __future__ import annotations

import time

import numpy as np
import pytest

from icco_torchrl.instructions import LLMPlanner
from icco_torchrl.live import LiveLoop
from icco_torchrl.live.loop import MAX_INSTRUCTION, planner_reading
from icco_torchrl.modules.policy import make_policy
from icco_torchrl.training.build import build_components, compose_config, make_env
from icco_torchrl.training.config import ConfigError, validate


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
    assert s.totals["reward"] == pytest.approx(sum(x.events["reward"] for x in states), abs=1e-4)
    assert isinstance(s.to_dict()["positions"], list)  # JSON-ready


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
    assert np.allclose(after.waypoints, 1.5) and after.planner["instruction"] == "Go right"


def test_an_unknown_instruction_is_reported_and_the_last_plan_kept():
    loop = team(planner=LLMPlanner(fallback_on_error=True))  # the offline rule planner
    loop.instruct("Go right")
    assert loop.wait_for_plan(30).state == "used"
    planned = loop.tick().waypoints
    loop.instruct("make me a sandwich")
    status = loop.wait_for_plan(30)
    assert status.state == "fell back" and status.error
    assert np.allclose(loop.tick().waypoints, planned)
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
    assert loop.status.instruction == "Move top" and planner.calls == 2


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
    ],
)
def test_live_settings_are_range_checked_from_their_fields(override, message):
    with pytest.raises(ConfigError, match=message):
        validate({"live": override})
    assert validate({"live": {"seconds": None, "port": 0}}).live.port == 0
