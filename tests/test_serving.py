"""Plans served as training-like walks, and the person's judgements of where the robots are."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from icco_torchrl.envs import ResourceCollectionEnv
from icco_torchrl.envs.reference_policies import make_reference_policy
from icco_torchrl.envs.routes import routes_from_plan, serve_routes
from icco_torchrl.evaluation import placement
from icco_torchrl.evaluation.metrics import time_to_slot, trial_rows
from icco_torchrl.evaluation.protocols import run_schedule
from icco_torchrl.instructions import LLMPlanner
from icco_torchrl.instructions.planner import how_read, parse, rule_plan, unread_words
from icco_torchrl.instructions.serving import PlanServer
from icco_torchrl.instructions.sources import language_schedule


def reference_serve(pos, route, k, step):
    """One robot, in plain Python: the nearest route point's segment, then walk from pos."""
    best, seg = math.inf, 0
    for j in range(len(route) - 1):
        a, b = np.array(route[j]), np.array(route[j + 1])
        t = np.clip(np.dot(pos - a, b - a) / max(np.dot(b - a, b - a), 1e-12), 0, 1)
        gap = np.linalg.norm(a + t * (b - a) - pos)
        if gap <= best:  # the later segment wins a tie
            best, seg = gap, j
    path = [np.array(pos)] + [np.array(p) for p in route[seg + 1 :]]
    out = []
    for i in range(1, k + 1):
        left, point = i * step, path[-1]
        for a, b in zip(path[:-1], path[1:]):
            length = np.linalg.norm(b - a)
            if left <= length:
                point = a + (b - a) * (left / length if length else 0.0)
                break
            left -= length
        out.append(point)
    return np.array(out)


def test_a_straight_route_is_served_a_step_at_a_time_and_collapses_on_the_slot():
    routes = torch.tensor([[[0.0, 0.0], [1.0, 0.0]]])
    near = serve_routes(torch.tensor([[0.0, 0.0]]), routes, 4, step=0.25)
    assert torch.allclose(near[0, :, 0], torch.tensor([0.25, 0.5, 0.75, 1.0]))
    there = serve_routes(torch.tensor([[0.9, 0.0]]), routes, 4, step=0.25)
    assert torch.allclose(there, torch.tensor([1.0, 0.0]).expand(1, 4, 2))  # K copies of the slot
    one_point = serve_routes(torch.tensor([[0.3, 0.3]]), routes[:, 1:], 3, step=0.25)
    assert torch.allclose(one_point, torch.tensor([1.0, 0.0]).expand(1, 3, 2))


def test_a_robot_past_a_corner_is_not_sent_back_and_batches_match_a_reference():
    route = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [1.0, 2.0]]
    at_corner = serve_routes(torch.tensor([[1.0, 0.0]]), torch.tensor([route]), 2, step=0.5)
    assert torch.allclose(at_corner, torch.tensor([[[1.0, 0.5], [1.0, 1.0]]]))
    gen = torch.Generator().manual_seed(0)
    routes = torch.rand(5, 3, 4, 2, generator=gen) * 4 - 2  # [B, N, R, 2]
    pos = torch.rand(5, 3, 2, generator=gen) * 4 - 2
    served = serve_routes(pos, routes, 4, step=0.3)
    for b in range(5):
        for n in range(3):
            want = reference_serve(pos[b, n].numpy(), routes[b, n].tolist(), 4, 0.3)
            assert np.allclose(served[b, n].numpy(), want, atol=1e-5), (b, n)


def test_the_server_holds_a_plan_and_refuses_bad_settings():
    server = PlanServer(4)
    assert server.slots is None
    with pytest.raises(RuntimeError, match="no plan"):
        server.serve(torch.zeros(1, 2, 2))
    start = torch.zeros(1, 2, 2)
    planned = torch.tensor([[[[1.0, 0.0]] * 4, [[0.0, -2.0]] * 4]])
    server.set_plan(start, planned)
    assert torch.equal(server.slots, torch.tensor([[[1.0, 0.0], [0.0, -2.0]]]))
    assert torch.equal(server.routes, routes_from_plan(start, planned))
    for bad in (0, -0.1, float("nan"), True, "0.25"):
        with pytest.raises(ValueError, match="serving step"):
            PlanServer(4, step=bad)
    with pytest.raises(ValueError, match="n_waypoints"):
        PlanServer(1)


def test_judgements_of_arrival_interception_formation_and_place():
    pos = torch.tensor([[[2.0, 0.0], [0.1, 0.1], [2.1, 1.0]]])
    slots = torch.tensor([[[2.2, 0.0], [2.3, -1.0], [2.3, 1.0]]])
    present = torch.ones(1, 3, dtype=torch.bool)
    at = placement.at_slot(pos, slots)
    assert at.tolist() == [[True, False, True]]  # 0.2 m, 2.4 m, 0.2 m from their slots
    invader = torch.tensor([[[0.5, 0.5]]])
    excused = placement.intercepting(pos, present, invader, torch.tensor([[True]]))
    assert excused.tolist() == [[False, True, False]]  # the robot nearest it, within 1.75 m
    assert placement.formation(at, present, excused).tolist() == [True]
    inactive = placement.intercepting(pos, present, invader, torch.tensor([[False]]))
    assert not inactive.any() and placement.formation(at, present, inactive).tolist() == [False]
    far = placement.intercepting(
        pos, present, torch.tensor([[[-3.0, -3.0]]]), torch.ones(1, 1).bool()
    )
    assert not far.any()  # nobody within 1.75 m of it: nobody is excused
    right = placement.region("Go right", 3.25)(pos, present)
    assert right.tolist() == [[True, False, True]]  # x > 1.625
    assert placement.in_place(right, present).tolist() == [True]  # 2 of 3
    assert placement.in_place(right & torch.tensor([[True, False, False]]), present).tolist() == [
        False
    ]


def test_regions_follow_the_instructions_words_and_nobody_at_home_is_in_place():
    half, present = 3.25, torch.ones(1, 3, dtype=torch.bool)
    home = torch.zeros(1, 3, 2) + torch.tensor([[[0.2, 0.0], [-0.2, 0.0], [0.0, 0.2]]])
    for text in ("Go right", "Move top", "Spread out", "Go to the top left corner"):
        judge = placement.region(text, half)
        assert not placement.in_place(judge(home, present), present).any(), text
    assert placement.in_place(placement.region("Gather center", half)(home, present), present).all()
    corner = torch.tensor([[[-2.0, 2.0], [-2.9, 2.5], [-1.7, 1.7]]])
    assert placement.region("Go to the top left corner", half)(corner, present).all()
    spread = torch.tensor([[[2.0, 0.0], [-1.0, 1.7], [-1.0, -1.7]]])
    assert placement.region("Spread out", half)(spread, present).all()
    for text in ("stop", "defend home", "make me a sandwich"):
        assert placement.region(text, half) is None


def test_time_to_slot_and_second_half_means_are_hand_computed():
    assert time_to_slot(np.array([0, 0, 1, 0, 1.0])) == 3.0
    assert time_to_slot(np.zeros(7)) == 7.0  # never: the segment's length
    assert math.isnan(time_to_slot(np.full(4, np.nan)))
    steps = {k: np.zeros((8, 1)) for k in ("reward", "task_reward", "inst_reward")}
    steps.update({k: np.zeros((8, 1)) for k in ("pick", "collect", "defense", "invasion")})
    steps.update(
        {k: np.full((8, 1), np.nan) for k in ("waypoint_dist", "in_quadrant", "broadcast_rate")}
    )
    steps["in_place"] = np.array([[1, 1, 0, 0, 1, 0, 1, 1.0]]).T  # second halves: [0, 0], [1, 1]
    steps["at_slot"] = steps["in_place"].copy()
    steps["formation"] = np.array([[0, 0, 1, 1, 0, 0, 0, 1.0]]).T
    rows = trial_rows(steps, ["a", "b"], [(0, 4), (4, 8)])
    by = {r["segment"]: r for r in rows}
    assert by["a"]["in_place"] == 0.0 and by["b"]["in_place"] == 1.0
    assert by["episode"]["in_place"] == 0.5  # both second halves together
    assert by["a"]["time_to_slot"] == 3.0 and by["b"]["time_to_slot"] == 4.0
    assert by["episode"]["time_to_slot"] == 3.5


def test_the_planner_reads_what_it_can_and_names_what_it_cannot():
    line = parse("Form a line along the bottom edge while avoiding the invader", 3.25)
    assert line.kind == "line" and line.direction == (0.0, -1.0)  # never "defend home"
    assert unread_words("Form a line along the bottom edge while avoiding the invader", 3.25) == [
        "along", "while", "avoiding", "invader"
    ]  # fmt: skip
    assert unread_words("Gather center", 3.25) == [] and unread_words("Defend home", 3.25) == []
    assert parse("Defend home", 3.25).kind == "task"
    assert unread_words("Stay put", 3.25) == [] and parse("Stay put", 3.25).kind == "hold"
    assert how_read("Spread out", 3.25) == '"Spread out": spread radially away from the centre'
    assert how_read("Dance please", 3.25).startswith('"Dance please": not understood')
    corner = rule_plan("Go to the top left corner", np.zeros((3, 2)), n_waypoints=4, half=3.25)[0]
    assert ((corner[:, -1, 0] < -1.625) & (corner[:, -1, 1] > 1.625)).all()  # in the corner


def test_a_path_follower_is_in_place_on_every_protocol_instruction_under_served_plans():
    """The interface's own check: a perfect path follower gets there, and the planner is asked
    once per instruction and episode."""
    instructions = ["Go right", "Move top", "Gather center", "Spread out"]

    def shares(plan):
        env = ResourceCollectionEnv(num_envs=4, max_steps=4 * 60, waypoint_mode="external", seed=5)
        schedule = language_schedule(LLMPlanner(), instructions, 60, plan=plan)
        run = run_schedule(env, make_reference_policy("pursuit", env), schedule, 4)
        assert sum(s["plans"] for s in run.sources) == 4 * len(instructions)  # one per episode
        rows = [r for r in run.rows if r["segment"] != "episode"]
        return {
            i: np.mean([r["in_place"] for r in rows if r["segment"] == i]) for i in instructions
        }

    served = shares("served")
    assert all(v == 1.0 for v in served.values()), served


def test_a_kept_reproduction_policy_is_evaluated_without_retraining():
    """Every 5M reproduction run keeps its policy beside its records, so a new protocol needs
    no retraining: one of them restores and drives a team under a served plan."""
    from pathlib import Path

    from icco_torchrl.evaluation.protocols import schedule_env
    from icco_torchrl.training.checkpoint import load_checkpoint

    records = Path(__file__).resolve().parents[1] / "experiments/four_quadrants/5m/records"
    kept = sorted(records.glob("icco_seed*/policy.pt"))
    assert [p.parent.name for p in kept] == ["icco_seed0", "icco_seed1", "icco_seed2"]
    saved = load_checkpoint(kept[0])
    assert saved["policy_only"] and saved["frames"] >= 5_000_000
    run = schedule_env(kept[0], 40, 2, seed=0)
    schedule = language_schedule(LLMPlanner(), ["Go right"], 40)
    result = run_schedule(run["env"], run["policy"], schedule, 2, method="ICCO")
    start, end = result.trajectory["pos"][0], result.trajectory["pos"][-1]
    assert (np.abs(end - start).sum(-1) > 0.1).all()  # every robot moved
    assert sum(s["plans"] for s in result.sources) == 2  # one request per episode
