"""The live page: its WebSocket protocol with several tabs, its bad input, the server's guards
(Host, Origin, token, rate limit, bounded planner output and threads), and the page itself in a
real headless browser (Chromium through the DevTools protocol), a page from another origin
among them."""

from __future__ import annotations

import asyncio
import contextlib
import http.server
import json
import logging
import queue
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import aiohttp
import numpy as np
import pytest

from icco_torchrl.instructions import LLMPlanner
from icco_torchrl.instructions.llm import MAX_REQUESTS
from icco_torchrl.live import LiveLoop
from icco_torchrl.live.web import BURST, RATE_LIMIT, LiveServer
from icco_torchrl.modules.policy import make_policy
from icco_torchrl.training.build import build_components, compose_config, make_env

DEMO = Path(__file__).resolve().parents[1] / "assets" / "demo_icco.pt"


def smoke_team(seed=3):
    cfg = compose_config(["method=icco", "experiment=smoke"])
    parts = build_components(cfg)
    # Episodes as long as a live run's (LiveLoop.from_checkpoint): a plan is not reset mid-test.
    env = make_env(cfg, num_envs=1, seed=seed, max_steps=10**6, waypoint_mode="external")
    policy = make_policy(parts["agent"], env.full_action_spec_unbatched, parts["coordinator"])
    return LiveLoop(env, policy, LLMPlanner())


class Tab:
    """A WebSocket client as the page is one: collects what the server sends."""

    def __init__(self, session, url):
        self.session, self.url = session, url
        self.ticks, self.errors, self.planner, self.hello = [], [], [], None
        self.oks, self.end, self.frames, self.arrivals = 0, None, [], []

    async def __aenter__(self):
        self.ws = await self.session.ws_connect(self.url)
        self._reader = asyncio.create_task(self._read())
        return self

    async def _read(self):
        async for msg in self.ws:
            self.frames.append(msg.data)
            data = json.loads(msg.data)
            if data["type"] == "hello":
                self.hello = data
            elif data["type"] == "tick":
                self.ticks.append(data)
                self.arrivals.append(time.monotonic())
            elif data["type"] == "planner":
                self.planner.append(data)
            elif data["type"] == "ok":
                self.oks += 1
            elif data["type"] == "end":
                self.end = data
            else:
                self.errors.append(data["message"])

    async def send(self, **request):
        await self.ws.send_str(json.dumps(request))

    async def until(self, predicate, timeout=20.0):
        end = time.monotonic() + timeout
        while not predicate():
            assert time.monotonic() < end, "timed out waiting for the live page"
            await asyncio.sleep(0.02)

    async def applied(self):
        """Until the plan the planner just reported is in the ticks (the tick after the one in
        progress when it arrived applies it)."""
        n = len(self.ticks)
        await self.until(lambda: len(self.ticks) >= n + 2)

    async def __aexit__(self, *exc):
        await self.ws.close()
        self._reader.cancel()


@pytest.fixture
def served():
    servers = []

    def serve(loop, **kwargs):
        server = LiveServer(loop, **{"rate_hz": 50.0, **kwargs})
        host, port = server.start_in_thread()
        servers.append(server)
        return server, f"http://{host}:{port}"

    yield serve
    for server in servers:
        server.close()


def test_two_tabs_watch_one_loop_and_either_can_instruct(served):
    server, url = served(smoke_team())

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with Tab(session, url + "/ws") as a, Tab(session, url + "/ws") as b:
                await a.until(lambda: a.hello and b.hello and len(a.ticks) > 3 and len(b.ticks) > 3)
                assert a.hello["n_agents"] == 3 and a.hello["field_size"] == pytest.approx(6.5)
                assert a.ticks[-1]["clients"] == 2
                await b.send(type="instruct", text="Go right")
                for tab in (a, b):  # both tabs see the plan arrive, and the waypoints move right
                    await tab.until(lambda t=tab: t.planner[-1]["state"] == "used")
                    await tab.applied()
                slots = np.asarray(a.ticks[-1]["slots"])
                assert (slots[:, 0] > 1).all()  # the robots' slots are on the right
                assert a.planner[-1]["instruction"] == "Go right" and b.oks == 1 and a.oks == 0
                assert a.planner[-1]["reading"].startswith("line at the right side")
                ticks = [t["tick"] for t in a.ticks]
                assert ticks == sorted(ticks) and len(set(ticks)) == len(ticks)  # newest, in order
                # The planner's status is sent once per change of its state, never per tick;
                # ticks name the instruction whose plan is in use.
                n = len(a.ticks)
                await a.until(lambda: len(a.ticks) > n + 5)
                status = [json.loads(f) for f in a.frames if '"type": "planner"' in f]
                states = [m["state"] for m in status if m["instruction"] == "Go right"]
                assert states[-1] == "used" and len(states) <= 2  # thinking (may be superseded
                assert all("planner" not in t for t in a.ticks)  # before it is sent)
                assert all(t["plan"] == "Go right" for t in a.ticks[n:])
            assert a.errors == [] and b.errors == []

    asyncio.run(scenario())


def test_bad_requests_get_one_line_errors_and_the_team_keeps_its_plan(served):
    server, url = served(smoke_team())

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with Tab(session, url + "/ws") as a, Tab(session, url + "/ws") as b:
                await a.send(type="instruct", text="Go right")
                await a.until(lambda: a.planner and a.planner[-1]["state"] == "used")
                await a.applied()
                planned = np.asarray(a.ticks[-1]["slots"])
                await a.send(type="instruct", text="   ")
                await a.ws.send_str("not json")
                await a.send(type="dance")
                await a.send(type="speed", value=3)
                await a.until(lambda: len(a.errors) == 4)
                assert "empty instruction" in a.errors[0] and "JSON" in a.errors[1]
                assert (
                    "unknown request type 'dance'" in a.errors[2]
                    and "speed must be one of" in a.errors[3]
                )
                assert (
                    all("\n" not in e for e in a.errors) and b.errors == []
                )  # only the sender hears of it
                # An instruction over the limit is refused with a message; the tab stays
                # connected and is heard afterwards.
                limit = a.hello["max_instruction"]
                await a.send(type="instruct", text="go right " * (limit // 9 + 1))
                await a.until(lambda: len(a.errors) == 5)
                assert f"at most {limit}" in a.errors[4] and "too long" in a.errors[4]
                await a.send(type="instruct", text="make me a sandwich")  # not understood
                await a.until(lambda: a.planner[-1]["state"] == "fell back")
                assert a.planner[-1]["error"] and a.planner[-1]["reading"] is None
                assert "spread out" in a.planner[-1]["understood"]  # what it does understand
                assert np.allclose(a.ticks[-1]["slots"], planned)  # the plan in use stays
                # The planner's reading of an instruction it maps to something else.
                await a.send(type="instruct", text="flank the intruder")
                await a.until(lambda: a.planner[-1]["state"] == "used")
                assert a.planner[-1]["reading"] == "defend home" and not a.ws.closed
                assert a.planner[-1]["unused"] == ["flank"] and a.planner[-1]["understood"] is None

    asyncio.run(scenario())


def test_pause_step_speed_reset_and_a_vanished_tab_never_stop_the_loop(served):
    loop = smoke_team()
    server, url = served(loop)

    async def scenario():
        async with aiohttp.ClientSession() as session:
            gone = await session.ws_connect(url + "/ws")  # a tab that will vanish without closing
            async with Tab(session, url + "/ws") as a:
                await a.until(lambda: len(a.ticks) > 5)
                await a.send(type="instruct", text="Go right")
                await a.until(lambda: a.planner and a.planner[-1]["state"] == "used")
                await a.applied()
                assert a.ticks[-1]["plan"] == "Go right"
                await a.send(type="pause")
                await a.until(lambda: a.ticks[-1]["paused"])
                await asyncio.sleep(0.2)
                frozen = loop.ticks
                await asyncio.sleep(0.3)
                assert loop.ticks == frozen  # paused: no ticks
                await a.send(type="step")
                await a.until(lambda: loop.ticks == frozen + 1)  # exactly one
                await a.send(type="reset")
                await a.until(
                    lambda: a.ticks[-1]["totals"]["reward"] == 0.0 and a.ticks[-1]["step"] == 0
                )
                # A reset keeps the instruction: it is planned again for the new positions (one
                # request per episode) and goes on driving the team.
                await a.until(lambda: a.planner[-1]["state"] == "used")
                assert a.ticks[-1]["plan"] == "Go right"
                assert (np.asarray(a.ticks[-1]["slots"])[:, 0] > 1).all()
                await a.send(type="speed", value=2.0)
                await a.send(type="resume")
                gone._response.connection.transport.abort()  # the other tab drops off the network
                start = loop.ticks
                await a.until(lambda: not a.ticks[-1]["paused"] and loop.ticks > start + 20)
                assert a.ticks[-1]["speed"] == 2.0 and a.ticks[-1]["clients"] == 1
        await asyncio.sleep(0.3)
        start = loop.ticks
        await asyncio.sleep(0.3)
        assert loop.ticks > start  # no tab at all: it keeps going

    asyncio.run(scenario())
    assert server.stats["connections"] == 2


def test_a_tab_adds_and_removes_robots_and_a_bad_change_is_answered(served):
    # The demo policy (trained on 3) in a loop that holds 4; episodes longer than the test.
    loop = LiveLoop.from_checkpoint(DEMO, seed=1, max_robots=4, episode_steps=10**6)
    server, url = served(loop)

    def moved(ticks, robots):  # each robot's farthest from where it was at the first tick
        if not ticks:
            return np.zeros(len(robots))
        pos = np.asarray([t["positions"] for t in ticks])
        return np.linalg.norm(pos - pos[0], axis=-1).max(0)[robots]

    async def scenario():
        async with aiohttp.ClientSession() as http:
            async with Tab(http, url + "/ws") as a, Tab(http, url + "/ws") as b:
                await a.until(lambda: a.hello and len(a.ticks) > 2)
                assert a.hello["n_agents"] == 4 and a.hello["team"] == [0, 1, 2]
                assert a.ticks[-1]["present"] == [True, True, True, False]
                await a.send(type="add_robot")
                await b.until(lambda: b.ticks[-1]["present"] == [True] * 4)  # every tab sees it
                assert a.oks == 1 and loop.team == [0, 1, 2, 3]
                n = len(b.ticks)  # the four are driven (a robot holding its slot rests a while)
                await b.until(lambda: (moved(b.ticks[n:], [0, 1, 2, 3]) > 0).all())
                await b.send(type="remove_robot", robot=1)
                await a.until(lambda: a.ticks[-1]["present"] == [True, False, True, True])
                n = len(a.ticks)
                await a.until(lambda: (moved(a.ticks[n:], [0, 2, 3]) > 0).all())
                assert moved(a.ticks[n:], [1])[0] == 0  # the one removed stays where it was
                # Bad changes: an error to the sender only, and the loop goes on.
                await a.send(type="remove_robot", robot=1)  # not in the team
                await a.send(type="add_robot", robot=0)  # already in
                await a.send(type="remove_robot")  # which one?
                await a.send(type="remove_robot", robot="x")
                await a.send(type="add_robot")  # robot 1 again: the team is full after it
                await a.send(type="add_robot")
                await a.until(lambda: len(a.errors) == 5)
                assert "robot 1 is not in the team" in a.errors[0]
                assert "robot 0 is already in the team" in a.errors[1]
                assert "needs the robot to remove" in a.errors[2]
                assert "robot must be an integer in 0..3" in a.errors[3]
                assert "the team is full: 4 robots" in a.errors[4]
                assert all("\n" not in e for e in a.errors) and b.errors == []
                ticks = loop.ticks
                await a.until(
                    lambda: loop.ticks > ticks + 5 and a.ticks[-1]["present"] == [True] * 4
                )
                for robot in (0, 1, 2):
                    await a.send(type="remove_robot", robot=robot)
                await a.send(type="remove_robot", robot=3)  # the last one stays
                await a.until(lambda: len(a.errors) == 6)
                assert "robot 3 is the last robot" in a.errors[5]
                await a.until(lambda: a.ticks[-1]["present"] == [False, False, False, True])
                ticks = loop.ticks
                await a.until(lambda: loop.ticks > ticks + 5)

    asyncio.run(scenario())


def test_when_live_seconds_run_out_every_tab_is_told_the_run_ended():
    loop = smoke_team()
    server, started = LiveServer(loop, rate_hz=50.0), queue.Queue()
    thread = threading.Thread(
        target=server.serve, kwargs={"max_seconds": 1.5, "on_start": started.put}, daemon=True
    )
    thread.start()
    host, port = started.get(timeout=30)

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with Tab(session, f"http://{host}:{port}/ws") as tab:
                await tab.until(lambda: tab.end is not None)
                assert tab.end["reason"] == "live.seconds=1.5 ran out"
                assert tab.end["ticks"] == loop.ticks >= tab.ticks[-1]["tick"]
                await tab.until(lambda: tab.ws.closed)
                assert tab.ws.close_code == 1000  # a normal close, not a dropped connection

    asyncio.run(scenario())
    thread.join(10)
    assert not thread.is_alive()


def test_a_busy_port_is_one_line_naming_it():
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    port = busy.getsockname()[1]
    try:
        with pytest.raises(
            OSError, match=f"cannot listen on http://127.0.0.1:{port}.*live.web_port"
        ):
            LiveServer(smoke_team(), port=port).start_in_thread()
        cli = [
            sys.executable,
            "-m",
            "icco_torchrl",
            "live",
            f"live.web_port={port}",
            "live.seconds=5",
        ]
        out = subprocess.run(cli, capture_output=True, text=True, timeout=120)
    finally:
        busy.close()
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [out.stderr.strip()] and f":{port}" in out.stderr


# ---------------------------------------------------------------------------------- the guards
def _raw(port, lines, timeout=5.0):
    """``(status, head, body)`` of one HTTP/1.1 request sent over a plain socket as ``lines``."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        sock.sendall(("\r\n".join([*lines, "", ""])).encode())
        data, end = b"", time.monotonic() + timeout
        while b"\r\n\r\n" not in data and time.monotonic() < end:
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
        head, _, body = data.partition(b"\r\n\r\n")
        status = int(head.split(b" ", 2)[1])
        length = [int(v) for k, v in _headers(head) if k == "content-length"]
        if status != 101:  # a refusal: read its one-line body
            while length and len(body) < length[0] and time.monotonic() < end:
                chunk = sock.recv(65536)
                if not chunk:
                    break
                body += chunk
    return status, head.decode("latin-1"), body.decode("utf-8", "replace")


def _headers(head):
    lines = head.decode("latin-1").split("\r\n")[1:]
    return [(k.strip().lower(), v.strip()) for k, _, v in (line.partition(":") for line in lines)]


def _get(port, path="/", host=None):
    host = f"127.0.0.1:{port}" if host is None else host
    return _raw(port, [f"GET {path} HTTP/1.1", f"Host: {host}", "Connection: close"])


def _upgrade(port, path="/ws", host=None, origin=None):
    """A WebSocket handshake, as a browser on ``origin`` (None: a client that sends none)."""
    lines = [
        f"GET {path} HTTP/1.1",
        f"Host: {f'127.0.0.1:{port}' if host is None else host}",
        "Upgrade: websocket",
        "Connection: Upgrade",
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
        "Sec-WebSocket-Version: 13",
    ]
    return _raw(port, lines + ([f"Origin: {origin}"] if origin is not None else []))


def test_only_requests_naming_this_server_and_sockets_from_its_own_page_are_answered(served):
    loop = smoke_team()
    server, url = served(loop)
    port = int(url.rsplit(":", 1)[1])
    assert _get(port)[0] == 200 and _get(port, host=f"localhost:{port}")[0] == 200
    assert "icco live" in _get(port)[2]
    # DNS rebinding: a page of attacker.example whose name now points at 127.0.0.1.
    for host in (f"attacker.example:{port}", "attacker.example", ""):
        status, _, body = _get(port, host=host)
        assert status == 403 and "is not this server's address" in body
        assert body.strip().count("\n") == 0
    status, _, body = _upgrade(
        port, host=f"attacker.example:{port}", origin=f"http://attacker.example:{port}"
    )
    assert status == 403 and "Host" in body
    # Its own page (and a client that sends no Origin, not a web page) may open the socket.
    assert _upgrade(port, origin=f"http://127.0.0.1:{port}")[0] == 101
    assert _upgrade(port, host=f"localhost:{port}", origin=f"http://localhost:{port}")[0] == 101
    assert _upgrade(port)[0] == 101
    # Any other origin may not: another port is another origin, so are another name and "null".
    for origin in (f"http://127.0.0.1:{port + 1}", f"http://localhost:{port}",
                   "http://attacker.example", "null"):  # fmt: skip
        status, _, body = _upgrade(port, origin=origin)
        assert status == 403 and f"a page from {origin!r} may not drive" in body, origin
    assert server.stats["forbidden"] == 8 and not server.paused


def test_a_token_is_asked_of_every_request(served):
    server, url = served(smoke_team(), token="s3cret")
    port = int(url.rsplit(":", 1)[1])
    for path in ("/", "/?token=wrong", "/?token=", "/ws"):
        status, _, body = (_upgrade if path == "/ws" else _get)(port, path)
        assert status == 403 and "needs its token" in body and "s3cret" not in body
    assert _get(port, "/?token=s3cret")[0] == 200
    assert _upgrade(port, "/ws?token=s3cret", origin=f"http://127.0.0.1:{port}")[0] == 101
    with pytest.raises(ValueError, match="live.token"):
        LiveServer(server.loop, token=" ")


def test_a_burst_of_requests_is_cut_off_and_the_loop_keeps_ticking(served):
    loop = smoke_team()
    server, url = served(loop)

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with Tab(session, url + "/ws") as a, Tab(session, url + "/ws") as b:
                await b.until(lambda: len(b.ticks) > 5)
                episodes, begin = loop.episode, time.monotonic()
                for _ in range(3000):  # 3,000 resets at once
                    await a.ws.send_str('{"type": "reset"}')
                sent = time.monotonic() - begin
                n = len(b.ticks)
                await b.until(lambda: len(b.ticks) >= n + 25, timeout=10)
                # The other tab kept getting ticks: no gap of a second (the queued resets of
                # an unbounded queue stopped every tab for 20 s).
                gaps = np.diff([t for t in b.arrivals if t >= begin])
                assert gaps.max() < 1.0 and time.monotonic() - begin < sent + 3.0
                await a.until(lambda: any("too many requests" in e for e in a.errors))
                admitted = BURST + RATE_LIMIT * (time.monotonic() - begin)
                assert server.stats["refused"] >= 3000 - admitted
                assert loop.episode - episodes <= admitted  # resets coalesce: at most one each
                warned = [e for e in a.errors if "too many requests" in e]
                assert len(warned) <= 2 + time.monotonic() - begin  # one a second at most
                await asyncio.sleep(1.0)  # the allowance refills: the tab is heard again
                oks = a.oks
                await a.send(type="pause")
                await a.until(lambda: a.oks > oks and a.ticks[-1]["paused"])
                assert not a.ws.closed and b.errors == []

    asyncio.run(scenario())


def test_deep_json_gets_an_error_reply_and_the_tab_stays(served):
    server, url = served(smoke_team())

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with Tab(session, url + "/ws") as a:
                await a.ws.send_str("[" * 30_000)
                await a.ws.send_str('{"type": ' * 5_000 + '"pause"' + "}" * 5_000)
                await a.until(lambda: len(a.errors) == 2)
                assert all("nested" in e and "\n" not in e for e in a.errors)
                await a.send(type="pause")
                await a.until(lambda: a.oks == 1)
                assert not a.ws.closed and server.paused

    asyncio.run(scenario())


class HugeReply(LLMPlanner):
    """A model that answers every request with 300,000 points (2.4 MB)."""

    REPLY = json.dumps({"agent_0": [[1.0, 2.0]] * 300_000, "agent_1": [], "agent_2": []})

    def __init__(self):
        super().__init__(model="openai/gpt-4o", api_base="http://127.0.0.1:9", backoff_s=0.0)

    def _complete(self, *args, **kwargs):  # the provider's reply text
        return self.REPLY


def test_a_huge_llm_reply_is_one_short_message_and_a_few_log_lines(served, caplog):
    server, url = served(smoke_team())
    server.loop.planner = HugeReply()

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with Tab(session, url + "/ws") as a, Tab(session, url + "/ws") as b:
                await a.send(type="instruct", text="Go right")
                for tab in (a, b):
                    await tab.until(lambda t=tab: t.planner[-1]["state"] == "fell back")
                status = b.planner[-1]
                assert status["error"].startswith("reply too long") and len(status["error"]) < 80
                assert max(len(f) for f in a.frames + b.frames if '"planner"' in f) < 600

    with caplog.at_level(logging.WARNING, logger="icco_torchrl.instructions.llm"):
        asyncio.run(scenario())
    assert 0 < len(caplog.text) < 4_000  # 3 attempts and the fallback, a line each


class SlowModel:
    """A litellm custom provider that answers after ``delay`` s with the rule planner's reply
    (its requests cannot be interrupted, as a real HTTP request cannot)."""

    def __init__(self, monkeypatch, delay=0.6):
        from icco_torchrl.instructions.llm import _litellm
        from icco_torchrl.instructions.planner import reply_to

        litellm, self.calls, self.release = _litellm(), [], threading.Event()
        model = self

        class Handler(litellm.CustomLLM):
            def completion(self, *args, **kwargs):
                model.calls.append(time.monotonic())
                model.release.wait(delay)  # bounded: a slow model, not a hung test
                message = {"role": "assistant", "content": reply_to(kwargs["messages"])}
                choice = {"index": 0, "finish_reason": "stop", "message": message}
                return litellm.ModelResponse(choices=[choice])

        entry = {"provider": "slowweb", "custom_handler": Handler()}
        monkeypatch.setattr(litellm, "custom_provider_map", [*litellm.custom_provider_map, entry])
        self.planner = LLMPlanner(model="slowweb/x", deadline_s=10.0, max_retries=0)


def _planner_threads() -> tuple[int, int]:
    names = [t.name for t in threading.enumerate()]
    return names.count("icco-live-planner"), names.count("llm-request")


def test_newer_instructions_supersede_older_ones_with_bounded_threads(served, monkeypatch):
    model = SlowModel(monkeypatch)
    loop = smoke_team()
    loop.planner, loop._cancellable = model.planner, True
    server, url = served(loop)

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with (
                Tab(session, url + "/ws") as a,
                Tab(session, url + "/ws") as b,
                Tab(session, url + "/ws") as c,
            ):
                tabs = [a, b, c]  # 100 instructions, each tab within its burst allowance
                most = (0, 0)
                for i in range(100):
                    await tabs[i % 3].send(type="instruct", text=f"go to ({i % 3}, 1)")
                    await asyncio.sleep(0.003)
                    most = tuple(map(max, most, _planner_threads()))
                await a.until(lambda: a.oks + b.oks + c.oks == 100)
                await a.until(lambda: a.planner[-1]["state"] == "used", timeout=10)
                last = a.planner[-1]
                assert last["instruction"] == "go to (0, 1)" and last["requests"] == 100
                # One planner thread; its requests, abandoned ones included, at most
                # MAX_REQUESTS (2 threads an instruction before: 202 for 100).
                assert most[0] <= 1 and most[1] <= MAX_REQUESTS
                assert len(model.calls) <= 6  # the superseded ones never reached the model
                assert a.errors == b.errors == c.errors == []

    try:
        asyncio.run(scenario())
    finally:
        model.release.set()


def test_a_tab_opened_late_sees_this_episodes_totals_and_the_actual_tick_rate(served):
    cfg = compose_config(["method=icco", "experiment=smoke"])
    parts = build_components(cfg)
    env = make_env(cfg, num_envs=1, seed=3, max_steps=30, waypoint_mode="external")
    policy = make_policy(parts["agent"], env.full_action_spec_unbatched, parts["coordinator"])
    loop = LiveLoop(env, policy, LLMPlanner())
    server, url = served(loop, rate_hz=50.0)

    async def scenario():
        await asyncio.sleep(1.5)  # 75 ticks: the tab opens in the third episode or later
        async with aiohttp.ClientSession() as session:
            async with Tab(session, url + "/ws") as tab:
                await tab.until(lambda: len(tab.ticks) > 40)
                first = tab.ticks[0]
                assert first["episode"] >= 2 and first["step"] <= first["episode_steps"] == 30
                starts = [t for t in tab.ticks if t["step"] == 1]
                assert starts  # an episode began while the tab watched: its totals restarted
                # Beside them, the mean of the episodes that ran to their end.
                assert first["finished"] >= 1 and set(first["finished_mean"]) == set(
                    first["totals"]
                )
                assert tab.ticks[-1]["finished"] > first["finished"]
                assert first["slot_distance"] is None and first["plan"] is None  # no plan yet
                for t in starts:
                    assert t["totals"] == pytest.approx(t["events"], abs=1e-5)
                rates = [t["tick_rate"] for t in tab.ticks[-10:]]
                assert all(r is not None and 0 < r < 80 for r in rates)
                assert tab.ticks[-1]["nominal_rate"] == 50.0
                await tab.send(type="speed", value=2.0)
                await tab.until(lambda: tab.ticks[-1]["nominal_rate"] == 100.0)
                await tab.send(type="pause")
                await tab.until(lambda: tab.ticks[-1]["paused"])
                assert tab.ticks[-1]["tick_rate"] is None

    asyncio.run(scenario())


# ---------------------------------------------------------------------------------- real browser
def _chromium() -> str | None:
    return next(
        (
            shutil.which(n)
            for n in ("chromium", "chromium-browser", "google-chrome")
            if shutil.which(n)
        ),
        None,
    )


class DevTools:
    """The few DevTools-protocol calls the browser test needs (one page target)."""

    def __init__(self, ws):
        self.ws, self.next_id = ws, 0

    async def call(self, method, **params):
        self.next_id += 1
        await self.ws.send_str(json.dumps({"id": self.next_id, "method": method, "params": params}))
        async for msg in self.ws:
            data = json.loads(msg.data)
            if data.get("id") == self.next_id:
                if "error" in data:
                    raise RuntimeError(f"{method}: {data['error']}")
                return data.get("result", {})
        raise RuntimeError("the browser closed the DevTools connection")

    async def js(self, expression):
        result = await self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    async def until(self, expression, timeout=30.0):
        end = time.monotonic() + timeout
        while not await self.js(expression):
            assert time.monotonic() < end, f"timed out waiting in the page for: {expression}"
            await asyncio.sleep(0.05)


@pytest.fixture(scope="module")
def browser():
    """One headless Chromium for the module's browser tests; yields its DevTools port."""
    exe = _chromium()
    if exe is None:
        pytest.skip("no Chromium installed (apt-get install chromium; .ci/run installs it)")
    profile = tempfile.mkdtemp(prefix="icco-chromium-")
    proc = subprocess.Popen(
        [
            exe,
            "--headless=new",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-dev-shm-usage",
            "--no-first-run",
            "--remote-debugging-port=0",
            f"--user-data-dir={profile}",
            "about:blank",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    port_file = Path(profile) / "DevToolsActivePort"
    end = time.monotonic() + 60
    while not port_file.is_file() or not port_file.read_text().strip():
        if proc.poll() is not None or time.monotonic() > end:
            proc.kill()
            pytest.fail("Chromium did not start (no DevToolsActivePort)")
        time.sleep(0.1)
    yield int(port_file.read_text().split()[0])
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
    shutil.rmtree(profile, ignore_errors=True)


def _lab(color: str) -> np.ndarray:
    """CIE L*a*b* (D65) of a ``#rrggbb`` or ``rgb(r, g, b)`` colour."""
    if color.startswith("#"):
        rgb = np.array([int(color[i : i + 2], 16) for i in (1, 3, 5)]) / 255
    else:
        rgb = np.array([float(v) for v in color[color.index("(") + 1 : -1].split(",")[:3]]) / 255
    rgb = np.where(rgb > 0.04045, ((rgb + 0.055) / 1.055) ** 2.4, rgb / 12.92)
    m = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    xyz = m @ rgb / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > 0.008856, np.cbrt(xyz), 7.787 * xyz + 16 / 116)
    return np.array([116 * f[1] - 16, 500 * (f[0] - f[1]), 200 * (f[1] - f[2])])


def _delta_e(a: str, b: str) -> float:
    """CIE76 colour difference: about 2.3 is just noticeable, above 50 another colour family."""
    return float(np.linalg.norm(_lab(a) - _lab(b)))


@contextlib.asynccontextmanager
async def _browser_tab(session, browser):
    """The browser's page, driven through :class:`DevTools`."""
    async with session.get(f"http://127.0.0.1:{browser}/json/list") as r:
        page = next(t for t in await r.json() if t["type"] == "page")
    async with session.ws_connect(page["webSocketDebuggerUrl"], max_msg_size=0) as ws:
        yield DevTools(ws)


@contextlib.asynccontextmanager
async def _page(session, browser, url, path="/"):
    """The browser's page, opened at ``url + path`` (the live page), driven through
    :class:`DevTools`."""
    async with _browser_tab(session, browser) as tools:
        await tools.call("Page.navigate", url=url + path)
        await tools.until("window.icco && icco.connected && icco.ticks > 5")
        yield tools


async def _type_and_send(tools, text):
    """A person clicks the box, types ``text`` and presses Send."""
    await tools.js("document.getElementById('instruction').value = ''")
    await tools.js("document.getElementById('instruction').focus()")
    await tools.call("Input.insertText", text=text)
    await tools.js("document.getElementById('send').click()")


def _text(element_id):
    return f"document.getElementById('{element_id}').textContent"


def test_the_page_in_a_real_browser_go_right_moves_waypoints_and_robots(served, browser):
    """What a first-time user meets: a legend, colours that are told apart, the planner's
    reading, a stated instruction limit, errors that clear, and a run that ends cleanly."""
    # Episodes longer than the trained 145 steps (test_live checks that default): an episode
    # that ends mid-test would move the robots back before they reach the right half.
    loop = LiveLoop.from_checkpoint(DEMO, planner=LLMPlanner(), seed=1, episode_steps=400)
    server, url = served(loop, rate_hz=40.0, policy="demo_icco.pt")

    async def scenario():
        async with aiohttp.ClientSession() as session, _page(session, browser, url) as tools:
            assert await tools.js("document.title") == "icco live"
            assert "demo_icco.pt" in await tools.js(_text("policy"))
            assert (await tools.js(_text("plan"))).startswith("none yet")  # no instruction yet
            # No yardstick given: its column and note are not shown.
            assert await tools.js("[...document.querySelectorAll('.ref')].every(e => e.hidden)")
            # The legend names every robot and each thing on the field, in the drawn colours.
            legend = await tools.js(_text("legend"))
            for name in ("robot 0", "robot 1", "robot 2", "resource", "home", "invader"):
                assert name in legend
            colors = await tools.js("icco.colors")
            swatches = await tools.js(
                "[...document.querySelectorAll('#legend li')].slice(0, 3)"
                ".map(li => getComputedStyle(li.querySelector('.sw')).backgroundColor)"
            )
            robots = colors["robots"][:3]
            assert all(_delta_e(a, b) < 1 for a, b in zip(swatches, robots, strict=True))
            for robot in colors["robots"]:  # no robot colour is a resource's, home's or invader's
                for thing in ("resource", "invader", "home", "homeEdge"):
                    assert _delta_e(robot, colors[thing]) > 50, (robot, thing)
            assert min(_delta_e(a, b) for a in robots for b in robots if a != b) > 40
            # The instruction limit is stated, and a longer instruction gets a message; the
            # connection stays up (no new socket) and the next instruction is heard.
            assert await tools.js(
                "document.querySelector('#instruct-form + div').textContent.trim()"
                ".startsWith('at most 200 characters')"
            )
            await tools.js("icco.wsBefore = icco.ws")
            long = "go right, " * 7000  # 70 000 characters: over the WebSocket's 64 KiB frame
            await _type_and_send(tools, long)
            message = await tools.js(_text("message"))
            assert f"too long: {len(long.strip())} characters, at most 200" in message
            await tools.until("document.getElementById('count').className === 'over'")
            # The planner's reading of an instruction it maps to something else is shown.
            await _type_and_send(tools, "flank the intruder")
            await tools.until("icco.planner && icco.planner.state === 'used'")
            assert await tools.js(_text("reading")) == "read as: defend home"
            assert await tools.js(_text("unused")) == "not understood (ignored): flank"
            # Where the waypoints lead under "defend home" (slots at home, the field's centre).
            await tools.until("icco.state.plan === 'flank the intruder'")
            mean_x = "icco.state.waypoints.flat().reduce((s, w) => s + w[0], 0) / 12"
            before = await tools.js(mean_x)
            # A sentence it reads in part is read as what it understood, never as another intent,
            # with a warning (amber, not green) naming the words it did not understand.
            await _type_and_send(tools, "Go right avoiding the invader")
            await tools.until("icco.planner.instruction === 'Go right avoiding the invader'")
            await tools.until("icco.planner.state === 'used'")
            assert await tools.js(_text("reading")) == "read as: line at the right side"
            assert await tools.js(_text("unused")) == "not understood (ignored): avoiding, invader"
            # The waypoints, served from each robot at the next refresh, now lead right.
            await tools.until(f"{mean_x} > {before}")
            assert await tools.js("document.getElementById('planner').className") == "warned"
            assert "warning" in await tools.js(_text("planner"))
            assert await tools.js("icco.ws === icco.wsBefore && icco.connected")
            assert await tools.js(_text("message")) == ""  # the success cleared the error
            # A server-side error is shown, then cleared by the next request that succeeds.
            await tools.js("icco.send({type: 'speed', value: 3})")
            await tools.until("document.getElementById('message').className === 'error'")
            assert "speed must be one of" in await tools.js(_text("message"))
            await _type_and_send(tools, "Go right")
            await tools.until("icco.planner.instruction === 'Go right'")
            await tools.until("icco.planner.state === 'used'")
            await tools.until("document.getElementById('message').textContent === ''")
            assert "Go right" in await tools.js(_text("planner"))
            assert (await tools.js(_text("reading"))).startswith("read as: line at the right")
            assert await tools.js(_text("unused")) == ""
            await tools.until("icco.state.slots && icco.state.slots.every(s => s[0] > 1)")
            # The plan in use, and each robot's distance to its slot, in the page.
            await tools.until("icco.state.plan === 'Go right'")
            assert "\u201cGo right\u201d" in await tools.js(_text("plan"))
            shown = await tools.js(
                "(() => { const s = icco.state; return [...document.querySelectorAll("
                "'#team-list li')].map(li => [li.querySelector('.dist').textContent, "
                "s.slot_distance[+li.dataset.robot].toFixed(2) + ' m']); })()"
            )
            assert len(shown) == 3 and all(a.startswith(b) for a, b in shown), shown
            assert "its slot" in await tools.js(_text("team-controls"))
            start = await tools.js("icco.state.tick")
            # Within 60 ticks the team is in the right half of the field: at least two of its three
            # robots (the demo policy sends one to intercept the invader, wherever it is).
            await tools.until("icco.state.positions.filter(p => p[0] > 0).length >= 2", timeout=10)
            assert await tools.js("icco.state.tick") - start <= 60
            # The panel shows the running counts; an empty instruction is reported in the page.
            assert await tools.js("document.getElementById('tick').textContent.length > 0")
            await tools.js("document.getElementById('instruction').value = '   '")
            await tools.js("document.getElementById('send').click()")
            assert "type an instruction" in await tools.js(_text("message"))
            # The field is drawn: some pixels are neither white nor transparent.
            drawn = await tools.js(
                "(() => { const c = document.getElementById('field'); const d = "
                "c.getContext('2d').getImageData(0, 0, c.width, c.height).data; let n = 0; "
                "for (let i = 0; i < d.length; i += 4) if (d[i+3] && (d[i] < 200)) n++; "
                "return n; })()"
            )
            assert drawn > 500
            # A request over the WebSocket limit (not one the page sends) closes the socket with
            # 1009: the page says so and reconnects.
            await tools.js("icco.ws.send('x'.repeat(icco.hello.max_message + 1))")
            await tools.until("document.getElementById('message').textContent.includes('large')")
            await tools.until("icco.connected && icco.ws !== icco.wsBefore")
            await tools.js("icco.wsBefore = icco.ws")
            # What the panel's numbers cover: this episode, its step of the episode's length,
            # the tick rate measured beside the nominal one.
            assert "this episode" in await tools.js(_text("team-panel"))
            episode = await tools.js(_text("episode"))
            assert episode.split(": ")[1].startswith("step ") and episode.endswith(" of 400")
            measured, nominal = (await tools.js(_text("rate"))).split(" of ")
            assert 0 < float(measured) < 80 and float(nominal) == 40
            # At an 800-pixel window, with a fall-back and a long error on show, the field stays
            # square and whole, its legend in view, and the fall-back's reason is short.
            await tools.call(
                "Emulation.setDeviceMetricsOverride",
                width=800,
                height=800,
                deviceScaleFactor=1,
                mobile=False,
            )
            await _type_and_send(tools, "make me a sandwich")
            await tools.until("icco.planner.state === 'fell back'")
            assert len((await tools.js(_text("planner"))).split()) <= 20
            # An unknown instruction: the page lists what the offline planner understands.
            assert await tools.js("!document.getElementById('understood').hidden")
            understood = await tools.js(_text("understood"))
            assert understood.startswith("The offline planner understands: directions")
            assert "spread out" in understood and "quadrant 1-4" in understood
            await tools.js("showMessage('refused: ' + 'a long message '.repeat(30), 'error')")
            box = await tools.js(
                "(() => { const c = document.getElementById('field').getBoundingClientRect(), "
                "l = document.getElementById('legend').getBoundingClientRect(); "
                "return {w: c.width, h: c.height, right: Math.max(c.right, l.right), "
                "bottom: l.bottom, iw: innerWidth, ih: innerHeight}; })()"
            )
            assert abs(box["w"] - box["h"]) < 1 and box["w"] >= 400, box
            assert box["right"] <= box["iw"] and box["bottom"] <= box["ih"], box
            # A reason that names the task-aligned prompt says how to turn it on.
            await _type_and_send(tools, "collect the resources")
            await tools.until("icco.planner.instruction === 'collect the resources'")
            await tools.until("icco.planner.state === 'fell back'")
            assert "task-aligned prompt" in await tools.js(_text("planner"))
            assert "llm.prompt=tap" in await tools.js(_text("hint"))
            assert await tools.js("document.getElementById('understood').hidden")
            await tools.call("Emulation.clearDeviceMetricsOverride")
            # The run ends: the page says so, why, turns its controls off and stops retrying.
            await asyncio.to_thread(server.close, reason="live.seconds=30 ran out")
            await tools.until("icco.ended !== null")
            assert await tools.js(_text("connection")) == "run ended"
            assert "live.seconds=30 ran out" in await tools.js(_text("ended-reason"))
            assert await tools.js("!document.getElementById('ended').hidden")
            assert await tools.js("document.getElementById('send').disabled")
            await asyncio.sleep(1.5)  # a retrying page would have opened a new socket by now
            assert await tools.js("icco.ws === icco.wsBefore && !icco.connected")

    asyncio.run(scenario())
    assert server.stats["connections"] == 2


def test_the_page_in_a_real_browser_adds_a_robot_and_removes_the_one_clicked(served, browser):
    loop = LiveLoop.from_checkpoint(DEMO, seed=1, max_robots=4, episode_steps=10**6)
    server, url = served(loop, rate_hz=20.0)
    team = "[...document.querySelectorAll('#team-list li')].map(li => +li.dataset.robot)"

    async def scenario():
        async with aiohttp.ClientSession() as http, _page(http, browser, url) as tools:
            assert await tools.js(team) == [0, 1, 2]
            assert "3 of at most 4" in await tools.js(_text("team-count"))
            assert "robot 3" not in await tools.js(_text("legend"))
            await tools.js("document.getElementById('add-robot').click()")
            await tools.until(f"{team}.length === 4 && icco.state.present.every(Boolean)")
            assert "robot 3" in await tools.js(_text("legend"))
            assert await tools.js("document.getElementById('add-robot').disabled")  # full
            hint = "document.getElementById('add-hint')"
            assert await tools.js(f"!{hint}.hidden") and "live.max_robots" in await tools.js(
                _text("add-hint")
            )
            # A click on robot 1 on the field selects it; the button takes it out of the team.
            await tools.js("icco.send({type: 'pause'})")
            await tools.until("icco.state.paused")
            x, y = await tools.js(
                "(() => { const c = document.getElementById('field').getBoundingClientRect(), "
                "h = icco.hello, p = icco.state.positions[1], k = c.width / h.field_size; "
                "return [c.left + (p[0] + h.field_size / 2) * k, "
                "c.top + (h.field_size / 2 - p[1]) * k]; })()"
            )
            for kind in ("mousePressed", "mouseReleased"):
                await tools.call(
                    "Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1
                )
            await tools.until("icco.selected === 1")
            assert await tools.js(_text("remove-robot")) == "Remove robot 1"
            await tools.js("document.getElementById('remove-robot').click()")
            await tools.until(f"{team}.join() === '0,2,3' && !icco.state.present[1]")
            assert "robot 1" not in await tools.js(_text("legend"))
            assert await tools.js("icco.selected") is None and loop.team == [0, 2, 3]
            # The labels follow the team: nothing is selected, so no robot is named.
            assert await tools.js(_text("remove-robot")) == "Remove selected"
            assert await tools.js("document.getElementById('remove-robot').disabled")
            assert await tools.js(f"{hint}.hidden")  # room again: no hint
            # The server's answer to a bad change is shown; the page stays connected.
            await tools.js("icco.send({type: 'remove_robot', robot: 1})")
            await tools.until("document.getElementById('message').className === 'error'")
            assert "robot 1 is not in the team" in await tools.js(_text("message"))
            # Robot 1 back: the buttons still name nobody, and the full team's hint is back.
            await tools.js("document.getElementById('add-robot').click()")
            await tools.until(f"{team}.join() === '0,1,2,3'")
            assert await tools.js(_text("remove-robot")) == "Remove selected"
            assert await tools.js("document.getElementById('remove-robot').disabled")
            assert await tools.js(f"!{hint}.hidden")
            await tools.js("icco.send({type: 'resume'})")
            ticks = loop.ticks
            await tools.until(f"icco.connected && icco.state.tick > {ticks + 5}")

    asyncio.run(scenario())


def test_the_page_in_a_real_browser_shows_its_totals_at_800_by_600_and_a_reset_keeps_the_plan(
    served, browser
):
    """The totals above the fold of a small window, beside their mean over finished episodes;
    a reset starts an episode and keeps the instruction."""
    cfg = compose_config(["method=icco", "experiment=smoke"])
    parts = build_components(cfg)
    env = make_env(cfg, num_envs=1, seed=3, max_steps=20, waypoint_mode="external")
    policy = make_policy(parts["agent"], env.full_action_spec_unbatched, parts["coordinator"])
    # A yardstick as scripted_yardstick gives it (its numbers made up here: the page shows them).
    reference = dict(label="best scripted (x)", episodes=16, steps=145, pick=2.0, collect=1.5)
    reference.update(defense=9.25, invasion=0.75, reward=101.04, inst_reward=52.0)
    server, url = served(LiveLoop(env, policy, LLMPlanner()), rate_hz=50.0, reference=reference)
    metrics = dict(width=800, height=600, deviceScaleFactor=1, mobile=False)

    async def scenario():
        async with aiohttp.ClientSession() as http, _page(http, browser, url) as tools:
            await tools.call("Emulation.setDeviceMetricsOverride", **metrics)
            await _type_and_send(tools, "make me a sandwich")  # a long list on show too
            await tools.until("!document.getElementById('understood').hidden")
            box = await tools.js(
                "(() => { const b = document.getElementById('team-panel')"
                ".getBoundingClientRect(); return {top: b.top, bottom: b.bottom, "
                "right: b.right, iw: innerWidth, ih: innerHeight}; })()"
            )
            assert box["ih"] == 600 and 0 <= box["top"] and box["bottom"] <= box["ih"], box
            assert box["right"] <= box["iw"], box
            # The best scripted team beside the mean, with what its numbers are.
            assert await tools.js(_text("ref-head")) == "best scripted"
            assert await tools.js(_text("ref-reward")) == "101.0"
            assert await tools.js(_text("ref-defense")) == "9.3"  # toFixed(1) of 9.25
            note = await tools.js(_text("ref-note"))
            assert "best scripted (x), the mean of 16 episodes of 145 steps" in note
            assert "not this page's" in note
            # Episodes of 20 steps at 50 Hz: finished ones come, and their mean is shown.
            await tools.until("icco.state.finished >= 2")
            shown = await tools.js(
                "(() => { const s = icco.state, t = (id) => document.getElementById(id)"
                ".textContent; return {head: t('mean-head'), n: s.finished, reward: "
                "t('mean-reward'), want: s.finished_mean.reward.toFixed(1), note: "
                "t('mean-note')}; })()"
            )
            assert shown["head"] == f"mean of {shown['n']} finished", shown
            assert shown["reward"] == shown["want"] and "ran to their end" in shown["note"]
            # A reset keeps the instruction: the plan in use still drives the team.
            await _type_and_send(tools, "Go right")
            await tools.until("icco.planner.instruction === 'Go right'")
            await tools.until("icco.state.plan === 'Go right'")
            await tools.js("icco.send({type: 'pause'})")  # no episode ends on its own meanwhile
            await tools.until("icco.state.paused")
            episode = await tools.js("icco.state.episode")
            await tools.js("document.getElementById('reset').click()")
            await tools.until(f"icco.state.episode === {episode + 1} && icco.state.step === 0")
            assert "Go right" in await tools.js(_text("plan"))
            await tools.until("icco.planner.state === 'used'")  # planned again for the episode
            assert await tools.js("icco.state.slots.every(s => s[0] > 1)")

    asyncio.run(scenario())


@contextlib.contextmanager
def _another_origin(html: str):
    """A page served from another origin (another port on 127.0.0.1); yields its URL."""

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 (http.server's name)
            body = html.encode()
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05})
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5)


def test_a_page_from_another_origin_cannot_drive_the_team(served, browser):
    """The attack of the issue: another page, opened in the same browser, opens the WebSocket,
    reads ``hello`` and sends "go left" and "pause". It is refused before any of that."""
    loop = smoke_team()
    server, url = served(loop)
    port = int(url.rsplit(":", 1)[1])
    evil = f"""<!DOCTYPE html><script>
      window.result = {{opened: false, messages: [], closed: false}};
      const ws = new WebSocket("ws://127.0.0.1:{port}/ws");
      ws.onopen = () => {{
        result.opened = true;
        ws.send(JSON.stringify({{type: "instruct", text: "go left"}}));
        ws.send(JSON.stringify({{type: "pause"}}));
      }};
      ws.onmessage = (event) => result.messages.push(event.data);
      ws.onclose = (event) => {{ result.closed = true; result.code = event.code; }};
    </script>"""

    async def scenario():
        async with aiohttp.ClientSession() as session, _browser_tab(session, browser) as tools:
            with _another_origin(evil) as page:
                await tools.call("Page.navigate", url=page)
                await tools.until("window.result && result.closed")
                result = await tools.js("result")
            assert not result["opened"] and result["messages"] == [] and result["code"] == 1006
            assert server.stats["forbidden"] == 1 and server.stats["connections"] == 0
            assert not server.paused and loop.status.instruction is None
            # The server's own page, in the same browser, is let in.
            await tools.call("Page.navigate", url=url + "/")
            await tools.until("window.icco && icco.connected && icco.ticks > 3")

    asyncio.run(scenario())


def test_the_page_passes_its_token_on_to_the_socket(served, browser):
    server, url = served(smoke_team(), token="s3cret")

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with _page(session, browser, url, path="/?token=s3cret") as tools:
                assert await tools.js("icco.hello.mode") == "live"
        assert server.stats["connections"] == 1 and server.stats["forbidden"] == 0

    asyncio.run(scenario())


def test_the_page_in_a_real_browser_shows_a_bridge_driven_fleet(served, browser):
    from conftest import bridge_with_fleet

    from icco_torchrl.envs import ResourceCollectionEnv
    from icco_torchrl.envs.reference_policies import make_reference_policy
    from icco_torchrl.live.bridge import Bridge
    from icco_torchrl.live.fleet import SimulatedFleet

    env = ResourceCollectionEnv(num_envs=1, seed=0, waypoint_mode="external", max_steps=10**6)
    loop = LiveLoop(env, make_reference_policy("follower", env), LLMPlanner())
    server, url = served(loop, drive=False, policy="follower")
    bridge = Bridge(loop, rate_hz=20, timeout=0.5)
    server.watch(bridge)
    fleet = SimulatedFleet(bridge.address, rate_hz=20, latency=0.02, seed=1)

    async def scenario():
        async with aiohttp.ClientSession() as session, _page(session, browser, url) as tools:
            assert (await tools.js("document.title")).startswith("icco bridge")
            assert (await tools.js(_text("title"))).startswith("icco bridge")
            assert await tools.js("document.getElementById('team-panel').hidden")
            assert not await tools.js("document.getElementById('fleet-panel').hidden")
            await tools.until("document.querySelectorAll('#fleet tr.moving').length === 3")
            rows = await tools.js(
                "[...document.querySelectorAll('#fleet tr')].map(r => r.innerText)"
            )
            assert [r.split()[:4] for r in rows] == [
                ["robot", str(i), "in", "moving"] for i in range(3)
            ]
            summary = await tools.js(_text("fleet-summary"))
            assert "3 of 3 robots moving" in summary and "0 malformed" in summary
            assert "team: robot 0, robot 1, robot 2 (3 of at most 3)" in summary
            assert int(summary.split(" commands")[0].rsplit(" ", 1)[-1]) > 0
            actual = float(summary.split(" of 20 Hz")[0].rsplit(" ", 1)[-1])  # beside nominal
            assert 0 < actual < 40
            fleet.silence(2)  # robot 2 drops off the network: its row says it is stopped
            await tools.until("document.querySelectorAll('#fleet tr.stopped').length === 1")
            row = await tools.js("document.querySelectorAll('#fleet tr')[2].innerText")
            assert "stopped: no pose for" in row and row.split()[2] == "out"  # it left the team
            summary = await tools.js(_text("fleet-summary"))
            assert "2 of 3 robots moving" in summary and "team: robot 0, robot 1 (2 of" in summary
            await asyncio.to_thread(server.close, reason="the bridge stopped")
            await tools.until("icco.ended !== null")
            assert "the bridge stopped" in await tools.js(_text("ended-reason"))
            # A fleet whose run ended reads as stopped, none of its robots as moving.
            assert await tools.js("document.querySelectorAll('#fleet tr.moving').length") == 0
            assert (await tools.js(_text("fleet-summary"))).startswith("stopped")

    with bridge_with_fleet(bridge, fleet, 30.0):
        asyncio.run(scenario())


def test_the_page_watches_a_bridge_driven_fleet_and_relays_instructions(served):
    from conftest import bridge_with_fleet

    from icco_torchrl.envs import ResourceCollectionEnv
    from icco_torchrl.envs.reference_policies import make_reference_policy
    from icco_torchrl.live.bridge import Bridge
    from icco_torchrl.live.fleet import SimulatedFleet

    env = ResourceCollectionEnv(num_envs=1, seed=0, waypoint_mode="external", max_steps=10**6)
    loop = LiveLoop(env, make_reference_policy("follower", env), LLMPlanner())
    server, url = served(loop, drive=False)
    bridge = Bridge(loop, rate_hz=20, timeout=0.5)
    server.watch(bridge)
    fleet = SimulatedFleet(bridge.address, rate_hz=20, latency=0.02, seed=1)

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with Tab(session, url + "/ws") as tab:
                await tab.until(lambda: tab.hello and len(tab.ticks) > 5)
                assert tab.hello["drive"] is False and tab.hello["mode"] == "bridge"
                shown, real = np.asarray(tab.ticks[-1]["positions"]), fleet.poses[:, :2]
                assert np.abs(shown - real).max() < 0.5  # the page shows the robots where they are
                # The fleet as the bridge sees it: every robot driven, the counts going up.
                f = tab.ticks[-1]["fleet"]
                assert [r["id"] for r in f["robots"]] == [0, 1, 2] and f["malformed"] == 0
                assert not any(r["stopped"] for r in f["robots"]) and f["commands"] > 3
                assert all(r["age_s"] < 0.5 and len(r["pose"]) == 3 for r in f["robots"])
                await tab.send(type="pause")
                await tab.until(lambda: tab.errors)
                assert "driven by the bridge" in tab.errors[0]
                await tab.send(type="instruct", text="Go right")
                await tab.until(lambda: tab.planner[-1]["state"] == "used")
                x0 = np.mean(tab.ticks[-1]["positions"], axis=0)[0]
                await tab.until(
                    lambda: np.mean(tab.ticks[-1]["positions"], axis=0)[0] > x0 + 0.5, timeout=7
                )
                # A loaded machine may have let a pose come late before: count from here.
                stale_before = tab.ticks[-1]["fleet"]["stale_stops"]
                fleet.silence(1)  # robot 1 drops off the network: the page says it is stopped
                await tab.until(lambda: tab.ticks[-1]["fleet"]["robots"][1]["stopped"])
                robots = tab.ticks[-1]["fleet"]["robots"]
                assert robots[1]["reason"] == "stale" and robots[1]["age_s"] > 0.5
                assert tab.ticks[-1]["fleet"]["stale_stops"] > stale_before
                # It left the team: the page draws the other two, the fleet says who is in.
                await tab.until(lambda: tab.ticks[-1]["present"] == [True, False, True])
                assert tab.ticks[-1]["fleet"]["team"] == [0, 2] and not robots[1]["in_team"]

    with bridge_with_fleet(bridge, fleet, 30.0):  # stopped on leaving
        asyncio.run(scenario())


def test_icco_live_through_the_cli_serves_the_demo_policy_and_refuses_a_bad_checkpoint(tmp_path):
    from conftest import run_cli

    run = tmp_path / "run"
    token = "cli-s3cret-token"
    proc = run_cli(
        "live",
        "live.seconds=2",
        "live.web_port=0",
        f"live.token={token}",
        f"hydra.run.dir={run}",
        timeout=120,
    )
    assert "using the demo policy" in proc.stdout and "open http://127.0.0.1:" in proc.stdout
    assert f"?token={token}" in proc.stdout  # printed, never written: Hydra's files redacted
    files = [p for p in run.rglob("*") if p.is_file()]
    assert (run / ".hydra" / "config.yaml") in files
    for path in [run, *run.rglob("*")]:
        assert (path.stat().st_mode & 0o077) == 0, path  # its owner's only
        assert path.is_dir() or token not in path.read_text(errors="replace"), path
    ticks = int(proc.stdout.split("icco live: ")[-1].split(" ticks")[0])
    # 2 s at 10 Hz in real time, after a start-up of unknown length: ticking, and not as fast as
    # it can (a loaded 2-core machine ran 9 ticks, so the floor leaves room)
    assert 5 <= ticks <= 25
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    proc = run_cli("live", f"checkpoint={bad}", "live.seconds=1", check=False, timeout=120)
    assert (
        proc.returncode == 2
        and proc.stderr.strip().count("\n") == 0
        and "not a checkpoint" in proc.stderr
    )
