"""The robot bridge: DWA commands within limits, the protocol, and bridge + simulated fleet over
loopback."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
from conftest import bridge_with_fleet

from icco_torchrl.envs import ResourceCollectionEnv
from icco_torchrl.envs.reference_policies import make_reference_policy
from icco_torchrl.live import LiveLoop
from icco_torchrl.live.bridge import Bridge
from icco_torchrl.live.dwa import RobotLimits, dwa_command
from icco_torchrl.live.fleet import SimulatedFleet
from icco_torchrl.live.wire import MAX_MESSAGE, ProtocolError, parse_message
from icco_torchrl.modules.policy import make_policy
from icco_torchrl.training.build import build_components, compose_config, make_env

LIMITS = RobotLimits()


def test_dwa_drives_toward_the_target_within_its_limits():
    v, w = dwa_command((0, 0, 0), (0.3, 0.0), (2.0, 0.0), LIMITS, 0.1)
    assert v > 0.3 and abs(w) < 0.25  # straight ahead: speed up, hardly turn
    v, w = dwa_command((0, 0, 0), (0.0, 0.0), (-2.0, 0.1), LIMITS, 0.1)
    assert abs(w) > 0.2 and v <= LIMITS.max_accel * 0.1 + 1e-9  # behind: turn, creep
    for _ in range(50):
        pose, vel = (
            np.random.uniform(-3, 3, 3),
            (np.random.uniform(0, 0.5), np.random.uniform(-2, 2)),
        )
        v, w = dwa_command(pose, vel, np.random.uniform(-3, 3, 2), LIMITS, 0.1)
        assert 0 <= v <= LIMITS.max_speed and abs(w) <= LIMITS.max_turn
        assert (
            abs(v - vel[0]) <= LIMITS.max_accel * 0.1 + 1e-9
            and abs(w - vel[1]) <= LIMITS.max_turn_accel * 0.1 + 1e-9
        )
    assert dwa_command((1, 1, 0), (0, 0), (1.0, 1.005), LIMITS, 0.1) == (0.0, 0.0)  # arrived: stay


def test_dwa_keeps_clear_of_another_robot():
    # Another robot right ahead: going straight would hit it within the horizon.
    v, w = dwa_command((0, 0, 0), (0.5, 0.0), (2.0, 0.0), LIMITS, 0.1, others=[[0.45, 0.0]])
    assert abs(w) > 0.1 or v < 0.45  # swerves or slows down
    with pytest.raises(ValueError, match="max_speed"):
        RobotLimits(max_speed=0)


@pytest.mark.parametrize(
    "data, message",
    [
        (b"\xff\xfe", "not UTF-8 JSON"),
        (b"[1, 2]", "JSON object"),
        (b'{"type": "dance"}', "type"),
        (b'{"type": "state", "robots": [{"id": -1, "pose": [0, 0, 0]}]}', "integer 'id'"),
        (b'{"type": "state", "robots": [{"id": 2147483648, "pose": [0, 0, 0]}]}', "2147483647"),
        (b'{"type": "state", "robots": [{"id": 0, "pose": [0, "a", 0]}]}', "pose"),
        (b'{"type": "state", "robots": [], "resources": [[0]]}', "resources"),
        (b'{"type": "instruct", "text": ""}', "non-empty"),
        # The safety contract's checks (docs/live.md, "Bridge safety contract").
        (b'{"type": "state", "robots": [{"id": true, "pose": [0, 0, 0]}]}', "integer 'id'"),
        (b'{"type": "state", "robots": [{"id": 0.0, "pose": [0, 0, 0]}]}', "integer 'id'"),
        (b'{"type": "state", "robots": [{"id": 0, "pose": [NaN, 0, 0]}]}', "NaN is not"),
        (b'{"type": "state", "robots": [{"id": 0, "pose": [1e999, 0, 0]}]}', "out of range"),
        (b'{"type": "state", "robots": [{"id": 0, "pose": [1e5, 0, 0]}]}', "at most 10000"),
        (b'{"type": "state", "time": 1' + b"0" * 399 + b"}", "a number of 400 characters"),
        (b'{"type": "state", "time": true}', "'time'"),
        (b"[" * 5_000, "nested too deeply"),
        (b" " * (MAX_MESSAGE + 1), f"at most {MAX_MESSAGE}"),
        (b'{"type": "instruct", "text": "' + b"a" * 201 + b'"}', "too long: 201 characters"),
        (b'{"type": "instruct", "text": "go \\ud800"}', "not valid unicode"),
    ],
)
def test_malformed_messages_are_refused_in_one_line(data, message):
    with pytest.raises(ProtocolError, match=message):
        parse_message(data)


def _heuristic_loop():
    env = ResourceCollectionEnv(num_envs=1, seed=0, waypoint_mode="external", max_steps=10**6)
    return LiveLoop(env, make_reference_policy("heuristic", env))


def test_act_on_measured_positions_carries_a_trained_policys_memory():
    cfg = compose_config(["experiment=smoke"])
    parts = build_components(cfg)
    env = make_env(cfg, num_envs=1, waypoint_mode="external", max_steps=10**6)
    loop = LiveLoop(
        env, make_policy(parts["agent"], env.full_action_spec_unbatched, parts["coordinator"])
    )
    for _ in range(6):
        actions, targets = loop.act_on([[0.0, 0.0], [1.0, 1.0], [-1.0, 1.0]])
        assert actions.shape == (3,) and targets.shape == (3, 2)
        step = np.linalg.norm(targets - [[0.0, 0.0], [1.0, 1.0], [-1.0, 1.0]], axis=-1)
        assert np.all((step < 1e-6) | (np.abs(step - 0.19) < 1e-4))  # one move (or no-op) away
    assert int(loop.td["step_count"]) == 6 and loop.td["agents", "rnn_hidden"].abs().sum() > 0


def test_bridge_and_simulated_fleet_over_loopback():
    loop = _heuristic_loop()
    bridge = Bridge(loop, rate_hz=10, timeout=0.5, limits=LIMITS)
    fleet = SimulatedFleet(bridge.address, rate_hz=20, latency=0.05, limits=LIMITS, seed=1)
    start = fleet.poses[:, :2].copy()
    with bridge_with_fleet(bridge, fleet, 6.0):
        time.sleep(2.5)
        for junk in (b"not json", b'{"type": "state", "robots": [{"id": 9}]}', b"{}"):
            fleet.send_raw(junk)
        fleet.silence(1)
        time.sleep(1.5)
    assert bridge.stats["malformed"] == 3 and bridge.stats["commands"] >= 25
    for msg in fleet.commands:
        for r in msg["robots"]:
            assert 0 <= r["v"] <= LIMITS.max_speed and abs(r["w"]) <= LIMITS.max_turn
    last = fleet.commands[-1]["robots"]
    assert last[1]["stopped"] and last[1]["reason"] == "stale" and last[1]["v"] == 0 == last[1]["w"]
    assert not last[0]["stopped"] and bridge.stats["stale_stops"] == 1
    moved = np.linalg.norm(fleet.poses[:, :2] - start, axis=-1)
    assert moved[0] > 0.2 and moved[2] > 0.2, moved  # driven by the commands
    assert fleet.velocity[1].tolist() == [0.0, 0.0]  # the silenced robot was stopped
    assert np.median(bridge.stats["latency_ms"]) < 100  # state in -> command out


def _until(predicate, seconds: float = 5.0) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end and not predicate():
        time.sleep(0.01)
    return predicate()


def _entries(msg: dict) -> dict:
    return {r["id"]: r for r in msg["robots"]}


def test_the_team_is_the_robots_that_report(caplog):
    """A silent robot leaves the team after the timeout and the others are still driven; it joins
    again when it reports again; a new id joins while there is room; one too many is refused in
    one line and commanded to stop."""
    caplog.set_level(logging.INFO, logger="icco.bridge")
    env = ResourceCollectionEnv(
        num_envs=1, n_agents=4, seed=0, waypoint_mode="external", max_steps=10**6
    )
    loop = LiveLoop(env, make_reference_policy("heuristic", env), team=[0, 1, 2])
    bridge = Bridge(loop, rate_hz=20, timeout=0.3, limits=LIMITS)
    fleet = SimulatedFleet(bridge.address, rate_hz=20, latency=0.02, limits=LIMITS, seed=1)
    with bridge_with_fleet(bridge, fleet, 20.0):
        assert _until(lambda: bridge.team() == [0, 1, 2] and len(fleet.commands) > 5)
        fleet.silence(1)
        assert _until(lambda: loop.team == [0, 2]), loop.team  # out of the env's team
        assert _until(lambda: _entries(fleet.commands[-1])[1]["stopped"])  # commands in flight
        n = len(fleet.commands)
        assert _until(lambda: len(fleet.commands) > n + 8)
        after = fleet.commands[n:]
        for msg in after:  # it is stopped while known; the others are still commanded
            robots = _entries(msg)
            assert robots[1]["stopped"] and robots[1]["reason"] == "stale"
            assert not robots[0]["stopped"] and not robots[2]["stopped"]
        assert any(r["v"] > 0 for m in after for r in m["robots"] if r["id"] in (0, 2))
        assert fleet.velocity[fleet.row(1)].tolist() == [0.0, 0.0]
        panel = bridge.fleet()
        assert panel["team"] == [0, 2] and not _entries(panel)[1]["in_team"]
        fleet.resume(1)  # it comes back: in the team again, in its own place
        assert _until(lambda: loop.team == [0, 1, 2] and bridge.team() == [0, 1, 2])
        fleet.join(7)  # a new id: the free place
        assert _until(lambda: bridge.team() == [0, 1, 2, 7] and loop.team == [0, 1, 2, 3])
        fleet.join(8)  # one too many for n_agents=4
        assert _until(lambda: 8 in _entries(fleet.commands[-1]))
        n = len(fleet.commands)
        assert _until(lambda: len(fleet.commands) > n + 4)
        for msg in fleet.commands[n:]:
            robots = _entries(msg)
            assert robots[8]["stopped"] and robots[8]["reason"] == "team full"
            assert robots[8]["v"] == 0 == robots[8]["w"]
            assert not any(robots[i]["stopped"] for i in (0, 1, 2, 7))
        assert fleet.velocity[fleet.row(8)].tolist() == [0.0, 0.0]
        assert bridge.team() == [0, 1, 2, 7] and loop.team == [0, 1, 2, 3]
        panel = _entries(bridge.fleet())
        assert panel[8]["in_team"] is False and panel[7]["slot"] == 3
    s = bridge.stats
    assert (s["dropped"], s["refused_robots"], s["malformed"]) == (1, 1, 0)
    refused = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert len(refused) == 1 and "robot 8 refused: the team is full" in refused[0]
    assert len(refused[0]) <= 300 and "\n" not in refused[0]
    left = [r.getMessage() for r in caplog.records if "out of the team" in r.getMessage()]
    assert len(left) == 1 and left[0].startswith("bridge: robot 1 sent no pose")


def test_a_port_in_use_is_one_clear_line():
    loop = _heuristic_loop()
    first = Bridge(loop)
    try:
        with pytest.raises(OSError, match=f"cannot listen on udp 127.0.0.1:{first.address[1]}"):
            Bridge(loop, port=first.address[1])
    finally:
        first.close()


def test_icco_bridge_with_the_simulated_fleet_through_the_cli(tmp_path, trained):
    import socket

    from conftest import copy_run, run_cli

    # test_train_cli.py's qmix smoke run (trained once a session)
    run = trained("method=qmix", "experiment=smoke", "logger.progress=false")
    ckpt = copy_run(run, tmp_path / "run") / "checkpoint.pt"
    proc = run_cli(
        "bridge",
        f"checkpoint={ckpt}",
        "live.fleet=true",
        "live.seconds=3",
        "live.port=0",
        timeout=120,
    )
    assert "listening on udp 127.0.0.1:" in proc.stdout and " 0 malformed" in proc.stdout
    commands = int(proc.stdout.split(" commands,")[0].rsplit(" ", 1)[-1])
    assert commands >= 20  # ~10 Hz for 3 s
    actual = float(proc.stdout.split(" Hz actual of 10 nominal")[0].rsplit(" ", 1)[-1])
    assert 7.0 <= actual <= 10.5, actual
    # live.seconds ran out: the fleet was sent a stop command before the socket closed.
    assert "bridge: sent a stop command (v = w = 0) to all 3 robots at 1 address" in proc.stdout
    # A busy port, in this process (the one-line exit 2 is the command's, as for `icco live`).
    from icco_torchrl.live.cli import run_bridge
    from icco_torchrl.training.build import compose_config

    busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    busy.bind(("127.0.0.1", 0))
    try:
        port = busy.getsockname()[1]
        cfg = compose_config([f"checkpoint={ckpt}", f"live.port={port}", "live.seconds=1"])
        with pytest.raises(OSError, match=f"cannot listen on udp 127.0.0.1:{port}"):
            run_bridge(cfg)
    finally:
        busy.close()


def test_icco_bridge_without_a_checkpoint_uses_the_demo_policy():
    """The shipped demo policy loads with today's networks (regenerate it when they change)."""
    from conftest import run_cli

    proc = run_cli(
        "bridge",
        "live.fleet=true",
        "live.seconds=1.5",
        "live.port=0",
        "live.web=true",  # and the page watching the fleet, closed when live.seconds runs out
        "live.web_port=0",
        "live.token=fleet-s3cret",  # the fleet's states carry it: none refused
        timeout=120,
    )
    assert "using the demo policy" in proc.stdout and " 0 malformed" in proc.stdout
    commands = int(proc.stdout.split(" commands,")[0].rsplit(" ", 1)[-1])
    assert commands >= 5
    assert "icco bridge: watch it at http://127.0.0.1:" in proc.stdout
