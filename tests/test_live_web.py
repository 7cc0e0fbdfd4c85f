"""The live page: its WebSocket protocol with several tabs, its bad input, and the page itself in a
real headless browser (Chromium through the DevTools protocol)."""

from __future__ import annotations

import asyncio
import json
import shutil
import socket
import subprocess
import sys
import tempfile
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
    env = make_env(cfg, num_envs=1, seed=seed, max_steps=40, waypoint_mode="external")
    policy = make_policy(parts["agent"], env.full_action_spec_unbatched, parts["coordinator"])
    return LiveLoop(env, policy, LLMPlanner())


class Tab:
    """A WebSocket client as the page is one: collects what the server sends."""

    def __init__(self, session, url):
        self.session, self.url = session, url
        self.ticks, self.errors, self.hello = [], [], None

    async def __aenter__(self):
        self.ws = await self.session.ws_connect(self.url)
        self._reader = asyncio.create_task(self._read())
        return self

    async def _read(self):
        async for msg in self.ws:
            data = json.loads(msg.data)
            if data["type"] == "hello":
                self.hello = data
            elif data["type"] == "tick":
                self.ticks.append(data)
            else:
                self.errors.append(data["message"])

    async def send(self, **request):
        await self.ws.send_str(json.dumps(request))

    async def until(self, predicate, timeout=10.0):
        end = time.monotonic() + timeout
        while not predicate():
            assert time.monotonic() < end, "timed out waiting for the live page"
            await asyncio.sleep(0.02)

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
                    await tab.until(lambda t=tab: t.ticks[-1]["planner"]["state"] == "used")
                wp = np.asarray(a.ticks[-1]["waypoints"])
                assert (wp[:, -1, 0] > 1).all() and a.ticks[-1]["planner"][
                    "instruction"
                ] == "Go right"  # paths end right
                ticks = [t["tick"] for t in a.ticks]
                assert ticks == sorted(ticks) and len(set(ticks)) == len(
                    ticks
                )  # newest only, in order
            assert a.errors == [] and b.errors == []

    asyncio.run(scenario())


def test_bad_requests_get_one_line_errors_and_the_team_keeps_its_plan(served):
    server, url = served(smoke_team())

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with Tab(session, url + "/ws") as a, Tab(session, url + "/ws") as b:
                await a.send(type="instruct", text="Go right")
                await a.until(lambda: a.ticks and a.ticks[-1]["planner"]["state"] == "used")
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
                await a.send(
                    type="instruct", text="make me a sandwich"
                )  # not understood by the planner
                await a.until(lambda: a.ticks[-1]["planner"]["state"] == "fell back")
                assert a.ticks[-1]["planner"]["error"]
                assert np.allclose(a.ticks[-1]["waypoints"], planned)

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


@pytest.fixture
def browser():
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


def test_the_page_in_a_real_browser_go_right_moves_waypoints_and_robots(served, browser):
    loop = LiveLoop.from_checkpoint(DEMO, planner=LLMPlanner(), seed=1)
    server, url = served(loop, rate_hz=40.0, policy="demo_icco.pt")

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with session.get(f"http://127.0.0.1:{browser}/json/list") as r:
                page = next(t for t in await r.json() if t["type"] == "page")
            async with session.ws_connect(page["webSocketDebuggerUrl"], max_msg_size=0) as ws:
                tools = DevTools(ws)
                await tools.call("Page.navigate", url=url + "/")
                await tools.until("window.icco && icco.connected && icco.ticks > 5")
                assert await tools.js(
                    "document.getElementById('policy').textContent.includes('demo_icco.pt')"
                )
                before = await tools.js(
                    "icco.state.waypoints.flat().reduce((s, w) => s + w[0], 0) / 12"
                )
                # A person clicks the box, types and presses Send.
                await tools.js("document.getElementById('instruction').focus()")
                await tools.call("Input.insertText", text="Go right")
                await tools.js("document.getElementById('send').click()")
                await tools.until("icco.state.planner.state === 'used'")
                assert "Go right" in await tools.js(
                    "document.getElementById('planner').textContent"
                )
                after = await tools.js(
                    "icco.state.waypoints.flat().reduce((s, w) => s + w[0], 0) / 12"
                )
                assert after > before + 0.3  # the waypoints moved right
                assert await tools.js(
                    "icco.state.waypoints.every(path => path[path.length - 1][0] > 1)"
                )
                start = await tools.js("icco.state.tick")
                # Within 60 ticks every robot is in the right half of the field.
                await tools.until("icco.state.positions.every(p => p[0] > 0)", timeout=10)
                assert await tools.js("icco.state.tick") - start <= 60
                # The panel shows the running counts; an empty instruction is reported in the page.
                assert await tools.js("document.getElementById('tick').textContent.length > 0")
                await tools.js("document.getElementById('instruction').value = '   '")
                await tools.js("document.getElementById('send').click()")
                assert "type an instruction" in await tools.js(
                    "document.getElementById('message').textContent"
                )
                # The field is drawn: some pixels are neither white nor transparent.
                drawn = await tools.js(
                    "(() => { const c = document.getElementById('field'); const d = "
                    "c.getContext('2d').getImageData(0, 0, c.width, c.height).data; let n = 0; "
                    "for (let i = 0; i < d.length; i += 4) if (d[i+3] && (d[i] < 200)) n++; "
                    "return n; })()"
                )
                assert drawn > 500

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
    bridge.on_command = lambda _: server.publish(loop.snapshot())
    fleet = SimulatedFleet(bridge.address, rate_hz=20, latency=0.02, seed=1)

    async def scenario():
        async with aiohttp.ClientSession() as session:
            async with Tab(session, url + "/ws") as tab:
                await tab.until(lambda: tab.hello and len(tab.ticks) > 5)
                assert tab.hello["drive"] is False
                shown, real = np.asarray(tab.ticks[-1]["positions"]), fleet.poses[:, :2]
                assert np.abs(shown - real).max() < 0.5  # the page shows the robots where they are
                await tab.send(type="pause")
                await tab.until(lambda: tab.errors)
                assert "driven by the bridge" in tab.errors[0]
                await tab.send(type="instruct", text="Go right")
                await tab.until(lambda: tab.ticks[-1]["planner"]["state"] == "used")
                x0 = np.mean(tab.ticks[-1]["positions"], axis=0)[0]
                await tab.until(
                    lambda: np.mean(tab.ticks[-1]["positions"], axis=0)[0] > x0 + 0.5, timeout=7
                )

    with bridge_with_fleet(bridge, fleet, 8.0):
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
