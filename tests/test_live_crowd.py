"""A crowd on the network: the bridge's token over UDP and its throttled team lines, and a live
server that no crowd of tabs, requests or token guesses can stall (docs/live.md).

Everything runs over 127.0.0.1, every loop bounded by a count or a deadline.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import select
import socket
import subprocess
import sys
import time

import aiohttp
import numpy as np
from conftest import ROOT
from test_bridge_safety import _bridge, _moving, _Planner, _Robots, _serving, _wait
from test_live_web import Tab, _get, _upgrade, served, smoke_team  # noqa: F401

from icco_torchrl.envs import ResourceCollectionEnv
from icco_torchrl.envs.reference_policies import make_reference_policy
from icco_torchrl.live import LiveLoop
from icco_torchrl.live.bridge import Bridge
from icco_torchrl.live.cli import _warn_if_exposed
from icco_torchrl.live.guard import (
    GUESS_BURST,
    GUESS_RATE,
    LOG_EVERY,
    TOKEN_VARIABLE,
    redact_run_folder,
    token_through_environment,
)
from icco_torchrl.live.web import CHANGE_BURST, CHANGE_RATE, MAX_IDLE_PER_IP

TOKEN = "udp-s3cret"


# ---------------------------------------------------------------------- the bridge
def _with_token(data: dict, token: str | None = TOKEN) -> bytes:
    return json.dumps({**data, **({"token": token} if token is not None else {})}).encode()


def test_with_a_token_the_bridge_takes_no_state_and_no_instruction_without_it(caplog):
    caplog.set_level(logging.INFO, logger="icco.bridge")
    planner = _Planner()
    bridge = _bridge(planner=planner, token=TOKEN)  # as icco bridge live.token=... builds it
    robots, guesser = _Robots(bridge.address), _Robots(bridge.address)

    def state() -> dict:
        poses = [{"id": i, "pose": [0.5 * i, 0.0, 0.0]} for i in range(3)]
        return {"type": "state", "time": time.time(), "robots": poses}

    go_left = {"type": "instruct", "text": "go left"}
    try:
        with _serving(bridge) as (_, errors, thread):
            for k in range(10):  # no token, then a wrong one: refused, nothing commanded
                robots.send(_with_token(state() if k % 2 else go_left, None if k < 5 else "nope"))
            assert _wait(lambda: bridge.stats["malformed"] == 10)
            assert robots.receive(0.3) == [] and planner.instructions == []
            assert bridge.team() == [] and bridge.stats["messages"] == 0
            # With the token: taken.
            robots.send(_with_token(go_left))
            assert _wait(lambda: planner.instructions == ["go left"])
            end, got = time.monotonic() + 0.5, []
            while time.monotonic() < end:
                robots.send(_with_token(state()))
                got += robots.receive(0.05)
            assert _moving(got) and bridge.team() == [0, 1, 2]
            # Guesses from another port are limited: beyond the burst they are refused unchecked,
            # even the token; the robots' address, which gave the token, is still heard.
            start = time.monotonic()
            for k in range(200):  # one at a time: none lost to a full socket buffer
                guesser.send(_with_token(state(), f"guess{k}"))
                assert _wait(lambda k=k: bridge.stats["malformed"] == 10 + k + 1)
            guesser.send(_with_token({**go_left, "text": "go right"}))
            assert _wait(lambda: bridge.stats["malformed"] == 211)
            checked = bridge.token.guesses
            assert checked <= 5 + GUESS_BURST + GUESS_RATE * (time.monotonic() - start)
            assert bridge.token.unchecked >= 180 and planner.instructions == ["go left"]
            robots.send(_with_token({**go_left, "text": "go up"}))
            assert _wait(lambda: planner.instructions == ["go left", "go up"])
            assert thread.is_alive() and not errors
        assert bridge.stats["refused_by"] == {"token": 211}
        lines = [r.getMessage() for r in caplog.records if "refused a datagram" in r.message]
        assert lines and all(TOKEN not in line and "guess" not in line for line in lines)
        assert all(len(line) <= 300 for line in lines)
    finally:
        robots.close()
        guesser.close()


def test_the_warning_says_what_the_token_guards(capsys):
    _warn_if_exposed("0.0.0.0", "T", "bridge")
    err = capsys.readouterr().err
    assert "live.token guards the page (live.web=true) and every state and instruct" in err
    _warn_if_exposed("0.0.0.0", None, "bridge")
    assert "anyone who can reach it can steer the team through the page" in capsys.readouterr().err
    _warn_if_exposed("127.0.0.1", None, "bridge")
    assert capsys.readouterr().err == ""


def test_join_and_leave_lines_are_throttled_like_refusals(caplog):
    """Robots that flicker in and out (live.timeout_s=0.05) log at most a line a second of each
    kind, however many join and leave."""
    caplog.set_level(logging.INFO, logger="icco.bridge")
    env = ResourceCollectionEnv(num_envs=1, seed=0, waypoint_mode="external", max_steps=10**6)
    loop = LiveLoop(env, make_reference_policy("heuristic", env))
    bridge = Bridge(loop, rate_hz=50, timeout=0.05)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    try:
        with _serving(bridge) as (_, errors, thread):
            start, end = time.monotonic(), time.monotonic() + 1.5
            for k in range(10_000):  # each 10 ms a few of robots 0..7, in turn
                if time.monotonic() >= end:
                    break
                ids = [(k + j) % 8 for j in range(2)] if k % 6 else [0, 4, 7]
                robots = [{"id": i, "pose": [0.3 * i, 0.0, 0.0]} for i in ids]
                sock.sendto(
                    json.dumps({"type": "state", "robots": robots}).encode(), bridge.address
                )
                time.sleep(0.01)
            seconds = time.monotonic() - start
            assert thread.is_alive() and not errors
        assert bridge.stats["joined"] >= 30 and bridge.stats["dropped"] >= 20, bridge.stats
        messages = [r.getMessage() for r in caplog.records]
        for kind in ("joined the team", "out of the team", "stopping it"):
            lines = [m for m in messages if kind in m]
            assert len(lines) <= seconds / LOG_EVERY + 2, (kind, len(lines))
            assert all(len(m) <= 300 for m in lines)
        joined = [m for m in messages if "joined the team" in m]
        assert any("more since the last line" in m for m in joined[1:])
    finally:
        sock.close()


# ---------------------------------------------------------------------- the live server
def _port(url: str) -> int:
    return int(url.rsplit(":", 1)[1])


def test_tabs_beyond_the_cap_are_refused_and_idle_connections_make_room(served):  # noqa: F811
    server, url = served(smoke_team(), max_clients=3)
    port = _port(url)

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with Tab(session, url + "/ws"), Tab(session, url + "/ws"):
                async with Tab(session, url + "/ws") as c:
                    await c.until(lambda: len(server.clients) == 3)
                    status, _, body = await asyncio.to_thread(_upgrade, port)
                    assert status == 503 and "3 tabs are open" in body
                    assert body.strip().count("\n") == 0
                await asyncio.sleep(0.2)  # one closed: room for one more
                assert (await asyncio.to_thread(_upgrade, port))[0] == 101

    asyncio.run(scenario())
    # Idle connections (no request at all) beyond what one IP may keep: its oldest are closed.
    idle = []
    try:
        for _ in range(MAX_IDLE_PER_IP + 5):
            idle.append(socket.create_connection(("127.0.0.1", port), timeout=2.0))
        assert _wait(lambda: server.stats["evicted"] == 5)
        closed = 0
        for sock in idle[:5]:
            sock.settimeout(2.0)
            with contextlib.suppress(ConnectionError):
                closed += sock.recv(1) == b""
        assert closed == 5 and server._open == MAX_IDLE_PER_IP
        # The newest stay open, and a new connection still gets the page (the oldest made room).
        assert not select.select(idle[5:], [], [], 0.2)[0]
        assert _answered(port) and server.stats["evicted"] == 6
    finally:
        for sock in idle:
            sock.close()
    assert _wait(lambda: _answered(port), 5.0)  # served again once they went


def _answered(port: int) -> bool:
    try:
        return _get(port)[0] == 200
    except OSError:
        return False


def test_a_crowd_of_tabs_adding_and_removing_robots_does_not_stall_the_loop(served):  # noqa: F811
    """100 tabs x 40 team changes at once (the loop stopped ticking for 5.45 s): the changes are
    limited across the whole server and made in the tick thread; another tab sees ticks on."""
    env = ResourceCollectionEnv(
        num_envs=1, n_agents=6, seed=0, waypoint_mode="external", max_steps=10**6
    )
    loop = LiveLoop(env, make_reference_policy("heuristic", env), _Planner(), team=[0, 1, 2])
    server, url = served(loop)
    changes = []
    add, remove = loop.add_robot, loop.remove_robot
    loop.add_robot = lambda robot=None: changes.append(1) or add(robot)
    loop.remove_robot = lambda robot: changes.append(1) or remove(robot)

    async def scenario():
        connector = aiohttp.TCPConnector(limit=0)  # 101 sockets: beyond aiohttp's default 100
        async with aiohttp.ClientSession(connector=connector) as session:
            async with Tab(session, url + "/ws") as watcher:
                await watcher.until(lambda: len(watcher.ticks) > 5)
                crowd = [await session.ws_connect(url + "/ws") for _ in range(100)]
                begin, shown = time.monotonic(), time.perf_counter()
                for k in range(40):
                    for j, ws in enumerate(crowd):
                        robot = 3 + (j + k) % 3
                        kind = "add_robot" if (j + k) % 2 else "remove_robot"
                        await ws.send_str(json.dumps({"type": kind, "robot": robot}))
                n = len(watcher.ticks)
                await watcher.until(lambda: len(watcher.ticks) >= n + 25, timeout=15)
                # It kept ticking: the server's own tick times (this client's burst of 4000 sends
                # holds its event loop, so the watcher's arrival times would count the client).
                ticked = [t for t in list(server._tick_times) if t >= shown]
                gaps = np.diff([shown, *ticked])
                assert len(ticked) >= 10 and gaps.max() < 1.0, gaps.max()
                elapsed = time.monotonic() - begin
                assert len(changes) <= CHANGE_BURST + CHANGE_RATE * elapsed + 1
                assert server.stats["busy"] > 1000
                for ws in crowd:
                    await ws.close()
                # Once the crowd has gone, a change is heard again (done, or one-line refused).
                await asyncio.sleep(2.0 / CHANGE_RATE)
                answers = watcher.oks + len(watcher.errors)
                await watcher.send(type="add_robot")
                await watcher.until(lambda: watcher.oks + len(watcher.errors) > answers)
                assert not any("busy" in e for e in watcher.errors)

    asyncio.run(asyncio.wait_for(scenario(), 60))


def test_refused_requests_are_logged_in_bounded_throttled_lines(served, caplog):  # noqa: F811
    caplog.set_level(logging.INFO, logger="icco.live")
    server, url = served(smoke_team())
    port = _port(url)
    start = time.monotonic()
    for k in range(200):
        status, _, _ = _get(port, "/" + "x" * 7_000 + str(k), host=f"attacker.example:{port}")
        assert status == 403
    seconds = time.monotonic() - start
    lines = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert 1 <= len(lines) <= seconds / LOG_EVERY + 2 and server.stats["forbidden"] == 200
    assert all(len(line) <= 300 and "\n" not in line for line in lines)
    assert sum(len(line) for line in lines) < 10_000  # 1.43 MB before


def test_a_huge_integer_in_a_request_gets_an_error_and_the_tab_stays(served, caplog):  # noqa: F811
    caplog.set_level(logging.INFO, logger="icco.live")
    server, url = served(smoke_team())
    huge = "9" * 5_000

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with Tab(session, url + "/ws") as a:
                await a.ws.send_str('{"type": "speed", "value": ' + huge + "}")
                await a.ws.send_str('{"type": "add_robot", "robot": ' + huge + "}")
                await a.ws.send_str('{"type": "speed", "value": 1' + huge + ".5}")
                await a.until(lambda: len(a.errors) == 3)
                assert all("a number of 50" in e and "\n" not in e for e in a.errors), a.errors
                await a.send(type="pause")
                await a.until(lambda: a.oks == 1)
                assert not a.ws.closed and server.paused

    asyncio.run(scenario())
    assert not [r for r in caplog.records if r.exc_info or "Traceback" in r.getMessage()]


def test_token_guesses_are_throttled(served):  # noqa: F811
    server, url = served(smoke_team(), token="s3cret-page")
    port = _port(url)
    start, answers = time.monotonic(), []
    for k in range(100):
        answers.append(_get(port, f"/?token=guess{k}")[0])
    seconds = time.monotonic() - start
    checked = answers.count(403)  # compared with the token; the others refused unchecked (429)
    assert checked <= GUESS_BURST + GUESS_RATE * seconds + 1, (checked, seconds)  # ~1,500/s before
    assert answers.count(429) == 100 - checked
    status, _, body = _get(port, "/?token=s3cret-page")  # refused unchecked while limited
    assert status == 429 and "too many wrong tokens" in body and "s3cret" not in body
    time.sleep(1.2 / GUESS_RATE)  # the allowance refills
    assert _get(port, "/?token=s3cret-page")[0] == 200


def test_the_token_is_redacted_from_the_files_hydra_wrote(tmp_path):
    """As Hydra writes them: the composed config, the overrides and Hydra's record."""
    hydra = tmp_path / ".hydra"
    hydra.mkdir()
    (hydra / "config.yaml").write_text("live:\n  token: tok-123456\n  host: 0.0.0.0\nseed: 0\n")
    (hydra / "overrides.yaml").write_text("- live.token=tok-123456\n- live.web=true\n")
    (hydra / "hydra.yaml").write_text(
        "hydra:\n  overrides:\n    task:\n    - live.token=tok-123456\n    - live.web=true\n"
        "  job:\n    override_dirname: live.token=tok-123456,live.web=true\n"
    )
    (tmp_path / "cli.log").write_text("")
    assert len(redact_run_folder(tmp_path, "tok-123456")) == 3
    for path in [tmp_path, *tmp_path.rglob("*")]:
        assert (path.stat().st_mode & 0o777) == (0o700 if path.is_dir() else 0o600), path
        if path.is_file():
            assert "tok-123456" not in path.read_text()
    assert "token: <redacted>" in (hydra / "config.yaml").read_text()
    assert "live.web=true" in (hydra / "hydra.yaml").read_text()
    assert "- live.token=<redacted>" in (hydra / "overrides.yaml").read_text()


PROBE = """
import json, sys
from pathlib import Path
import icco_torchrl.live.cli as live_cli
from icco_torchrl.cli import main

folder, token = Path(sys.argv[1]), sys.argv[2]

def probe(cfg):  # at the command's start: what Hydra has written by then
    files = []
    for path in [run, *run.rglob("*")]:
        text = path.read_text(errors="replace") if path.is_file() else ""
        files.append([str(path.relative_to(run)), path.stat().st_mode & 0o777, token in text])
    print(json.dumps({"files": files, "token": cfg.live.token == token}), flush=True)
    return 0.0

live_cli.run_live = live_cli.run_bridge = probe
for command in ("live", "bridge"):
    run = folder / command
    main([command, f"live.token={token}", f"hydra.run.dir={run}"])
"""


def test_the_token_is_never_in_a_file_others_can_read(tmp_path):
    """What Hydra wrote by the time ``icco live`` and ``icco bridge`` start (before any
    redaction): files of their owner only, none holding the token, and the command still gets
    the token (0644 files held it for about 0.3 s before)."""
    token = "tok-" + "9f3a" * 4
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop(TOKEN_VARIABLE, None)
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, str(tmp_path), token],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    runs = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    assert len(runs) == 2 and all(seen["token"] for seen in runs)
    for seen in runs:
        names = [name for name, _, _ in seen["files"]]
        assert ".hydra/config.yaml" in names and ".hydra/overrides.yaml" in names
        for name, mode, holds in seen["files"]:
            assert mode & 0o077 == 0, (name, oct(mode))
            assert not holds, name


def test_a_token_override_reaches_the_command_through_the_environment(monkeypatch):
    monkeypatch.setenv(TOKEN_VARIABLE, "before")  # put back after the test
    moved = token_through_environment(
        ["live.web=true", "++live.token='a b=c'", f"hydra.run.dir=/x/{TOKEN_VARIABLE}"]
    )
    assert moved == [
        "live.web=true",
        "++live.token=${oc.env:" + TOKEN_VARIABLE + "}",
        f"hydra.run.dir=/x/{TOKEN_VARIABLE}",
    ]
    assert os.environ[TOKEN_VARIABLE] == "a b=c"
    left = ["live.token=${oc.env:MY_TOKEN}", "live.token=null", "live.token=a,b", "~live.token"]
    assert token_through_environment(left) == left
