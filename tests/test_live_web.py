"""The live page: its WebSocket protocol with several tabs, its bad input, and the page itself in a
real headless browser (Chromium through the DevTools protocol)."""

from __future__ import annotations

import asyncio
import contextlib
import json
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
from icco_torchrl.live import LiveLoop
from icco_torchrl.live.web import LiveServer
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
        self.oks, self.end, self.frames = 0, None, []

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
                wp = np.asarray(a.ticks[-1]["waypoints"])
                assert (wp[:, -1, 0] > 1).all()  # paths end right
                assert a.planner[-1]["instruction"] == "Go right" and b.oks == 1 and a.oks == 0
                assert a.planner[-1]["reading"].startswith("line at the right side")
                ticks = [t["tick"] for t in a.ticks]
                assert ticks == sorted(ticks) and len(set(ticks)) == len(ticks)  # newest, in order
                # The instruction is sent once per change of the planner's state, never per tick.
                n = len(a.ticks)
                await a.until(lambda: len(a.ticks) > n + 5)
                with_text = [f for f in a.frames if "Go right" in f]
                states = [json.loads(f)["state"] for f in with_text]  # thinking (may be
                assert states[-1] == "used" and len(states) <= 2  # superseded before it is sent)
                assert all("planner" not in t for t in a.ticks)
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
                planned = np.asarray(a.ticks[-1]["waypoints"])
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
                assert np.allclose(a.ticks[-1]["waypoints"], planned)
                # The planner's reading of an instruction it maps to something else.
                await a.send(type="instruct", text="flank the intruder")
                await a.until(lambda: a.planner[-1]["state"] == "used")
                assert a.planner[-1]["reading"] == "defend home" and not a.ws.closed

    asyncio.run(scenario())


def test_pause_step_speed_reset_and_a_vanished_tab_never_stop_the_loop(served):
    loop = smoke_team()
    server, url = served(loop)

    async def scenario():
        async with aiohttp.ClientSession() as session:
            gone = await session.ws_connect(url + "/ws")  # a tab that will vanish without closing
            async with Tab(session, url + "/ws") as a:
                await a.until(lambda: len(a.ticks) > 5)
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
async def _page(session, browser, url):
    """The browser's page, opened at ``url``, driven through :class:`DevTools`."""
    async with session.get(f"http://127.0.0.1:{browser}/json/list") as r:
        page = next(t for t in await r.json() if t["type"] == "page")
    async with session.ws_connect(page["webSocketDebuggerUrl"], max_msg_size=0) as ws:
        tools = DevTools(ws)
        await tools.call("Page.navigate", url=url + "/")
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
    loop = LiveLoop.from_checkpoint(DEMO, planner=LLMPlanner(), seed=1)
    server, url = served(loop, rate_hz=40.0, policy="demo_icco.pt")

    async def scenario():
        async with aiohttp.ClientSession() as session, _page(session, browser, url) as tools:
            assert await tools.js("document.title") == "icco live"
            assert "demo_icco.pt" in await tools.js(_text("policy"))
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
            assert await tools.js("icco.ws === icco.wsBefore && icco.connected")
            assert await tools.js(_text("message")) == ""  # the success cleared the error
            # A server-side error is shown, then cleared by the next request that succeeds.
            await tools.js("icco.send({type: 'speed', value: 3})")
            await tools.until("document.getElementById('message').className === 'error'")
            assert "speed must be one of" in await tools.js(_text("message"))
            before = await tools.js(
                "icco.state.waypoints.flat().reduce((s, w) => s + w[0], 0) / 12"
            )
            await _type_and_send(tools, "Go right")
            await tools.until("icco.planner.instruction === 'Go right'")
            await tools.until("icco.planner.state === 'used'")
            await tools.until("document.getElementById('message').textContent === ''")
            assert "Go right" in await tools.js(_text("planner"))
            assert (await tools.js(_text("reading"))).startswith("read as: line at the right")
            await tools.until("icco.state.waypoints.every(path => path[path.length - 1][0] > 1)")
            after = await tools.js("icco.state.waypoints.flat().reduce((s, w) => s + w[0], 0) / 12")
            assert after > before + 0.3  # the waypoints moved right
            start = await tools.js("icco.state.tick")
            # Within 60 ticks every robot is in the right half of the field.
            await tools.until("icco.state.positions.every(p => p[0] > 0)", timeout=10)
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
            assert [r.split()[:3] for r in rows] == [["robot", str(i), "moving"] for i in range(3)]
            summary = await tools.js(_text("fleet-summary"))
            assert "3 of 3 robots moving" in summary and "0 malformed" in summary
            assert int(summary.split(" commands")[0].rsplit(" ", 1)[-1]) > 0
            fleet.silence(2)  # robot 2 drops off the network: its row says it is stopped
            await tools.until("document.querySelectorAll('#fleet tr.stopped').length === 1")
            assert "stopped: no pose for" in await tools.js(
                "document.querySelectorAll('#fleet tr')[2].innerText"
            )
            assert "2 of 3 robots moving" in await tools.js(_text("fleet-summary"))
            await asyncio.to_thread(server.close, reason="the bridge stopped")
            await tools.until("icco.ended !== null")
            assert "the bridge stopped" in await tools.js(_text("ended-reason"))

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
                fleet.silence(1)  # robot 1 drops off the network: the page says it is stopped
                await tab.until(lambda: tab.ticks[-1]["fleet"]["robots"][1]["stopped"])
                robots = tab.ticks[-1]["fleet"]["robots"]
                assert robots[1]["reason"] == "stale" and robots[1]["age_s"] > 0.5
                assert tab.ticks[-1]["fleet"]["stale_stops"] == 1 and not robots[0]["stopped"]

    with bridge_with_fleet(bridge, fleet, 30.0):  # stopped on leaving
        asyncio.run(scenario())


def test_icco_live_through_the_cli_serves_the_demo_policy_and_refuses_a_bad_checkpoint(tmp_path):
    from conftest import run_cli

    proc = run_cli("live", "live.seconds=2", "live.web_port=0", timeout=120)
    assert "using the demo policy" in proc.stdout and "open http://127.0.0.1:" in proc.stdout
    ticks = int(proc.stdout.split("icco live: ")[-1].split(" ticks")[0])
    assert 10 <= ticks <= 25  # 2 s at 10 Hz (real time), after a start-up of unknown length
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    proc = run_cli("live", f"checkpoint={bad}", "live.seconds=1", check=False, timeout=120)
    assert (
        proc.returncode == 2
        and proc.stderr.strip().count("\n") == 0
        and "not a checkpoint" in proc.stderr
    )
