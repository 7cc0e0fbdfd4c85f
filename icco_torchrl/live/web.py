"""The live page: a trained team on a web page, watched by any number of browser tabs.

An aiohttp server serves one static page (``static/live.html``, no build step, no CDN) at ``/``
and a WebSocket at ``/ws``. It either drives a :class:`~icco_torchrl.live.loop.LiveLoop`
(``icco live``: one tick every ``1 / (rate_hz * speed)`` seconds, in a worker thread so the
event loop never waits on the policy) or only shows one that something else drives
(``icco bridge live.web=true``: the bridge calls :meth:`LiveServer.publish` after each command).

WebSocket protocol (JSON text frames):

* server -> page, once on connect: ``{"type": "hello", "mode", "field_size", "home_radius",
  "vision_radius", "n_agents", "dt", "rate_hz", "speed", "paused", "drive", "policy", "planner",
  "max_instruction", "max_message", "reference", ...}``; ``mode`` is ``"live"`` (this server
  drives the team) or ``"bridge"`` (robots driven by the bridge); ``reference`` is the yardstick
  beside the running mean (:func:`~icco_torchrl.live.loop.scripted_yardstick`; null: none);
* server -> page, every tick: ``{"type": "tick", ...}`` with
  :class:`~icco_torchrl.live.loop.TickState`'s fields (but ``planner``) plus ``paused``,
  ``speed``, ``clients``, ``tick_rate`` (ticks per second measured over the last 2 s; null
  while paused), ``nominal_rate`` (``rate_hz * speed``) and, in bridge mode, ``fleet``
  (:meth:`~icco_torchrl.live.bridge.Bridge.fleet`); ``totals`` are this episode's (``episode``,
  ``step`` of ``episode_steps``), ``finished_mean`` the mean totals of the ``finished`` episodes
  (those that ran to their end), ``plan`` the instruction whose plan drives the team and
  ``slot_distance`` each robot's distance to its slot in the plan (metres); a slow tab gets the
  latest tick only (older ones are dropped for it, never queued), so it can neither fall behind
  nor slow the others;
* server -> page, on connect and each time it changes (never repeated in ticks):
  ``{"type": "planner", ...}`` with :class:`~icco_torchrl.live.loop.PlannerStatus`'s fields
  (with the offline planner, ``understood`` on an unknown instruction and ``unused`` words of a
  used one; ``hint`` when the reason names a setting);
* server -> page, to the sender only: ``{"type": "ok"}`` for each request applied, or
  ``{"type": "error", "message": ...}`` for a bad one (an instruction over ``max_instruction``
  characters, JSON nested too deeply, among them: the connection stays up); over
  ``RATE_LIMIT`` requests a second (after a burst of ``BURST``) a request is dropped, counted
  in ``stats["refused"]`` and answered by one error a second at most;
* server -> page, once when the run ends (``live.seconds`` ran out, Ctrl-C, the bridge stopped):
  ``{"type": "end", "reason", "ticks"}``, then the server closes the connection (code 1000);
* page -> server: ``{"type": "instruct", "text": "Go right"}``, ``{"type": "pause"}``,
  ``{"type": "resume"}``, ``{"type": "step"}`` (one tick while paused), ``{"type": "reset"}`` (a
  new episode; the instruction stays),
  ``{"type": "speed", "value": x}`` with x in ``SPEEDS``, ``{"type": "add_robot"}`` (the
  lowest robot not in the team; ``"robot": i`` names one) and ``{"type": "remove_robot",
  "robot": i}``: the team changes between two ticks (:meth:`~icco_torchrl.live.loop.LiveLoop.
  add_robot`), up to ``n_agents`` robots (``live.max_robots``); a full team, a robot not in it,
  the last robot or a bad index is answered with an error and the loop goes on. Ticks carry
  ``present`` (``[n_agents]`` bools: the robots in the team). A request over ``max_message``
  bytes closes the connection (code 1009); the page never sends one.

A tab that disconnects or errs is dropped; the loop keeps ticking with no tab at all.

Only the server's own page can drive it. Every HTTP request must name the server in ``Host``:
``localhost`` or the bound address (on a wildcard bind, ``0.0.0.0`` or ``::``, also any IP
address and this machine's name), so a DNS-rebinding page, whose Host is its own domain, is
refused (403). A WebSocket upgrade that carries ``Origin`` (every browser sends it) must come
from the page's own origin, ``http://`` + its Host, so a page from any other origin (another
port included) is refused (403); a client without ``Origin`` is not a web page and may connect.
With a ``token`` every request must carry it (``?token=...``: the page passes it on to
``/ws``); wrong ones are limited (:class:`~icco_torchrl.live.guard.TokenCheck`: one a second
from one address after 10, ten a second from all): beyond, a request is refused unchecked (429),
the right token included, until the allowance refills.

No crowd stalls the server. At most ``max_clients`` tabs (``MAX_CLIENTS``) are served at once:
one more is refused (503, one line) until one closes. A connection that waits for a request (its
first one included, however slowly its head arrives) is closed after ``idle_timeout`` seconds
(``IDLE_TIMEOUT``); one IP may keep at most ``MAX_IDLE_PER_IP`` of them, and all connections
together are at most ``max_clients + SPARE_CONNECTIONS``: beyond either bound the oldest waiting
connection of the IP that keeps the most is closed to make room (the new one only when none
waits), so a crowd of slow or idle connections cannot lock a new tab out. A request aiohttp
itself refuses (no ``Host``, two of them, a broken request line) is answered 400 in one line,
counted (``stats["malformed"]``) and logged in one line a second at most, never a traceback.
Work a request asks of the loop is
bounded: team changes are at most ``CHANGE_RATE`` a second from all tabs together (after
``CHANGE_BURST``; beyond, an error reply), and they and instructions wait for the loop's lock in
the tick thread (a worker thread in bridge mode), never in the event loop; a reset or a redraw
waits at most once in the tick thread (requests coalesce), single steps queue at most
``MAX_STEPS``, and the planner takes one instruction at a time
(:meth:`~icco_torchrl.live.loop.LiveLoop.instruct`). A number of more than ``MAX_DIGITS``
characters in a request is refused with an error reply, and a request that fails for any other
reason is answered with a one-line error; the tab stays. Refused HTTP requests and failures are
logged in one line each (a path cut short), at most one line a second per kind, the next one
saying how many were held back.
"""

from __future__ import annotations

import asyncio
import ipaddress
import json
import logging
import socket
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

from aiohttp import WSMsgType, web
from aiohttp.http_exceptions import HttpProcessingError

from icco_torchrl.live.guard import Bucket, Throttle, TokenCheck, held, one_line
from icco_torchrl.live.loop import MAX_INSTRUCTION, LiveLoop

log = logging.getLogger("icco.live")
PAGE = Path(__file__).with_name("static") / "live.html"
OK = {"type": "ok"}
SPEEDS = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
CONTROLS = ("pause", "resume", "step", "reset", "speed", "add_robot", "remove_robot")
MAX_MESSAGE = 64 * 1024  # bytes of one page request; a larger one closes the connection (1009)
RATE_LIMIT = 20.0  # requests a second one connection may send, after a burst of BURST
BURST = 40
MAX_REPLIES = 64  # replies queued for one tab; more are dropped (counted), never queued
MAX_STEPS = 10  # single steps queued while paused
MAX_STATUS_CHARS = 400  # each text of a planner-status message is cut to this length
RATE_WINDOW_S = 2.0  # the measured tick rate is over the ticks of the last 2 s
MAX_CLIENTS = 256  # tabs (WebSockets) at once; one more is refused (503) until one closes
SPARE_CONNECTIONS = 64  # HTTP connections beyond the tabs (page loads); beyond, the idlest goes
MAX_IDLE_PER_IP = SPARE_CONNECTIONS  # connections one IP keeps waiting for a request
IDLE_TIMEOUT = 10.0  # seconds a connection may wait for a request (its head included)
CHANGE_RATE = 10.0  # team changes (add/remove a robot) a second, all tabs together, after
CHANGE_BURST = 20  # a burst of CHANGE_BURST
MAX_DIGITS = 40  # characters of one number in a request (longer ones are refused, not converted)
LOOP_REQUESTS = (
    "instruct",
    "add_robot",
    "remove_robot",
)  # run beside the ticks, not in the event loop
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")


def _hostname(host: str) -> str:
    """The name in a ``Host`` header, without its port: ``[::1]:8000`` -> ``::1``."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[1 : host.find("]")] if "]" in host else host
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


class _TooLong(ValueError):
    pass


def _bounded_int(text: str) -> int:
    if len(text) > MAX_DIGITS:
        raise _TooLong(f"a number of {len(text)} characters (at most {MAX_DIGITS})")
    return int(text)


def _bounded_float(text: str) -> float:
    if len(text) > MAX_DIGITS:
        raise _TooLong(f"a number of {len(text)} characters (at most {MAX_DIGITS})")
    return float(text)


def _parse(text: str) -> dict | str:
    """A page request as a JSON object, or one line saying what is wrong with it."""
    try:
        msg = json.loads(text, parse_int=_bounded_int, parse_float=_bounded_float)
    except _TooLong as err:
        return f"a request may not hold {err}"
    except json.JSONDecodeError:
        return "a request must be a JSON object"
    except RecursionError:
        return "a request must be a JSON object, not nested this deeply"
    except ValueError:
        return "a request must be a JSON object of plain numbers and text"
    if not isinstance(msg, dict):
        return "a request must be a JSON object"
    return msg


def _ip_of(transport) -> str:
    """The IP address a connection comes from ("?" when the socket does not say)."""
    peer = transport.get_extra_info("peername")
    return str(peer[0]) if isinstance(peer, (tuple, list)) and peer else "?"


def _waiting(handler) -> bool:
    """Whether an aiohttp connection waits for a request: none in progress (a tab's socket is
    one, for as long as it is open) and none queued. Unknown to aiohttp: never."""
    return not getattr(handler, "_request_in_progress", True) and not getattr(
        handler, "_messages", True
    )


class _ServerLog:
    """aiohttp's server logger for one :class:`LiveServer`: a request that aiohttp refuses
    itself is counted and said in one throttled line (``LiveServer._bad_request``); any other
    failure is one line too (at most one a second), never a traceback."""

    def __init__(self, server: LiveServer):
        self.server = server

    def exception(self, msg, *args, exc_info=None, **_) -> None:
        if isinstance(exc_info, HttpProcessingError):
            self.server._bad_request(args[0] if args else "?", exc_info)
        elif isinstance(exc_info, BaseException):
            self.server._failed("the HTTP server", exc_info)
        else:
            self.warning(msg, *args)

    error = exception

    def warning(self, msg, *args, **_) -> None:
        due, n = self.server._failures.due()
        if due:
            try:
                text = str(msg) % args if args else str(msg)
            except (TypeError, ValueError):
                text = str(msg)
            log.warning("live: %s%s", one_line(text), held(n))

    def debug(self, msg, *args, exc_info=None, **_) -> None:
        if isinstance(exc_info, HttpProcessingError):  # not HTTP at all (TLS, junk): counted too
            self.server._bad_request(args[0] if args else "?", exc_info)

    def info(self, *args, **kwargs) -> None:
        pass


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


class _Client:
    """One browser tab: replies to its requests (all sent, in order), the latest planner status
    and the latest tick frame (older ones of these two are replaced)."""

    def __init__(self, ws: web.WebSocketResponse):
        self.ws = ws
        self.replies: list[str] = []
        self.status: str | None = None
        self.frame: str | None = None
        self.ready = asyncio.Event()
        self.sent = self.dropped = self.refused = 0
        self.writer: asyncio.Task | None = None
        self.closing = False  # the run ended: send what is queued, then close
        self.allowance, self.checked = float(BURST), time.monotonic()  # the rate limit's bucket
        self.warned = 0.0  # when the last "too many requests" error was queued

    def admit(self) -> bool:
        """Whether one more request fits this tab's rate limit (a token bucket)."""
        now = time.monotonic()
        self.allowance = min(float(BURST), self.allowance + (now - self.checked) * RATE_LIMIT)
        self.checked = now
        if self.allowance < 1.0:
            return False
        self.allowance -= 1.0
        return True

    def offer(self, frame: str) -> None:
        if self.frame is not None:
            self.dropped += 1
        self.frame = frame
        self.ready.set()

    def offer_status(self, frame: str) -> None:
        self.status = frame
        self.ready.set()

    def reply(self, frame: str) -> None:
        if len(self.replies) >= MAX_REPLIES:
            self.dropped += 1
            return
        self.replies.append(frame)
        self.ready.set()

    def take(self) -> list[str]:
        """The frames to send now: replies first, then the planner status, then the tick."""
        frames = [*self.replies, self.status, self.frame]
        self.replies, self.status, self.frame = [], None, None
        return [f for f in frames if f is not None]


def _check_settings(rate_hz: float, token: str | None, max_clients: int) -> None:
    """Raise ``ValueError`` naming the first bad one of a server's settings."""
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
    if token is not None and not str(token).strip():
        raise ValueError("live.token must be a non-empty string, or null for none")
    if isinstance(max_clients, bool) or not isinstance(max_clients, int) or max_clients < 1:
        raise ValueError(f"max_clients must be an integer >= 1, got {max_clients!r}")


def _new_stats() -> dict:
    """A server's counters, all zero (``latency_ms``: the tick latencies, none yet)."""
    return {
        "broadcasts": 0,
        "frames": 0,
        "dropped": 0,
        "errors": 0,
        "connections": 0,
        "refused": 0,  # requests over a tab's rate limit
        "busy": 0,  # team changes over the server's CHANGE_RATE
        "forbidden": 0,  # HTTP requests and upgrades refused (Host, Origin, token)
        "full": 0,  # connections refused: max_clients tabs or all connections in use
        "evicted": 0,  # waiting connections closed to make room for a new one
        "malformed": 0,  # requests aiohttp refused (no Host, two, a broken request line): 400
        "failed": 0,  # requests whose handling raised (answered with an error)
        "latency_ms": [],
    }


class LiveServer:
    """Serve ``loop`` to browser tabs (module docstring). ``drive=False``: show a loop that
    another owner ticks, the bridge (pause/step/reset/speed are then refused with a message)."""

    def __init__(
        self,
        loop: LiveLoop,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        rate_hz: float = 10.0,
        drive: bool = True,
        policy: str = "",
        planner: str = "",
        token: str | None = None,
        max_clients: int = MAX_CLIENTS,
        reference: dict | None = None,
        idle_timeout: float = IDLE_TIMEOUT,
    ):
        _check_settings(rate_hz, token, max_clients)
        if not idle_timeout > 0:
            raise ValueError(f"idle_timeout must be > 0, got {idle_timeout!r}")
        self.idle_timeout = float(idle_timeout)
        # The yardstick beside the running mean (loop.scripted_yardstick).
        self.reference = reference
        self.max_clients = max_clients
        self.loop, self.host, self.port, self.rate_hz, self.drive = (
            loop,
            host,
            int(port),
            float(rate_hz),
            drive,
        )
        self.policy, self.planner = policy, planner
        self.token = None if token is None else str(token)
        self._tokens = None if token is None else TokenCheck(self.token)
        self._changes = Bucket(CHANGE_RATE, CHANGE_BURST)  # team changes, all tabs together
        self._refusals, self._failures = Throttle(), Throttle()  # log lines
        self._evictions, self._malformed = Throttle(), Throttle()
        # Open connections by IP (aiohttp's handler -> its transport, oldest first).
        self._by_ip: dict[str, dict] = {}
        self._ips: dict = {}  # aiohttp's handler -> its IP
        self._open = 0
        self.paused, self.speed = False, 1.0
        self.clients: set[_Client] = set()
        self.stats = _new_stats()
        self.address: tuple[str, int] | None = None
        self._steps = 0  # single steps requested while paused
        self._aio: asyncio.AbstractEventLoop | None = None
        self._runner: web.AppRunner | None = None
        self._ticker: ThreadPoolExecutor | None = None
        self._worker: ThreadPoolExecutor | None = None  # instructions, team changes
        self._drive_task: asyncio.Task | None = None
        self._thread: threading.Thread | None = None
        self._closed = threading.Event()
        self._status_frame = self._planner_frame(loop.status)
        self.end_reason = "the run was stopped"
        self._fleet: dict | None = None  # the bridge's fleet as last published
        self._show_job: str | None = None  # "reset" or "snapshot", waiting in the tick thread
        self._show_lock = threading.Lock()
        self._tick_times: deque[float] = deque(maxlen=4096)  # when the last ticks were shown
        self._names: set[str] = set()  # the Host names this server answers to

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> tuple[str, int]:
        """Bind and start serving (and ticking when ``drive``); raises ``OSError`` naming the
        port."""
        app = web.Application(middlewares=[self._guard])
        app.router.add_get("/", self._page)
        app.router.add_get("/ws", self._socket)
        self._runner = web.AppRunner(
            app,
            access_log=None,
            handle_signals=False,
            keepalive_timeout=self.idle_timeout,  # also bounds the wait for the first request
            logger=_ServerLog(self),
        )
        await self._runner.setup()
        self._cap_connections(self._runner.server)
        site = web.TCPSite(self._runner, self.host, self.port)
        try:
            await site.start()
        except OSError as err:
            await self._runner.cleanup()
            raise OSError(
                f"cannot listen on http://{self.host}:{self.port}: {err.strerror or err} "
                f"(choose another port with live.web_port=...)"
            ) from None
        self._aio = asyncio.get_running_loop()
        self.address = tuple(self._runner.addresses[0][:2])  # the bound port when port=0
        self._names = {"localhost", self.host.lower(), str(self.address[0]).lower()}
        if self.host in LOOPBACK_NAMES:
            self._names.update(LOOPBACK_NAMES)
        self._status_frame = self._planner_frame(self.loop.status)
        self.loop.on_status = self._status_changed
        if self.drive:
            self._ticker = ThreadPoolExecutor(1, thread_name_prefix="icco-live-tick")
            self._drive_task = asyncio.create_task(self._drive())
        # Requests that reach the loop wait for its lock in this thread, never in the event loop:
        # the tick thread itself when this server ticks (between two ticks), else a thread of
        # their own (the bridge ticks the loop).
        self._worker = self._ticker or ThreadPoolExecutor(1, thread_name_prefix="icco-live-req")
        return self.address

    def _cap_connections(self, server) -> None:
        """Bound the connections (module docstring): beyond ``MAX_IDLE_PER_IP`` waiting for a
        request from one IP, or ``max_clients + SPARE_CONNECTIONS`` in all, the oldest waiting
        connection of the IP that keeps the most is closed (the new one when none waits), so a
        crowd can hold neither every file descriptor nor the room a new tab needs."""
        cap, made, lost = (
            self.max_clients + SPARE_CONNECTIONS,
            server.connection_made,
            server.connection_lost,
        )

        def connection_made(handler, transport) -> None:
            made(handler, transport)
            ip = _ip_of(transport)
            self._by_ip.setdefault(ip, {})[handler] = transport
            self._ips[handler] = ip
            self._open += 1
            mine = [h for h in self._by_ip[ip] if _waiting(h)]
            if len(mine) > MAX_IDLE_PER_IP:
                self._make_room(mine[0], handler, f"{ip} keeps {MAX_IDLE_PER_IP} waiting")
            elif self._open > cap:
                self._make_room(self._idlest(), handler, f"{cap} are open")

        def connection_lost(handler, exc=None) -> None:
            lost(handler, exc)
            self._forget(handler)

        server.connection_made, server.connection_lost = connection_made, connection_lost

    def _idlest(self):
        """The oldest connection waiting for a request of the IP that keeps the most, or None."""
        most: list = []
        for connections in self._by_ip.values():
            waiting = [h for h in connections if _waiting(h)]
            if len(waiting) > len(most):
                most = waiting
        return most[0] if most else None

    def _make_room(self, victim, new, why: str) -> None:
        """Close ``victim`` (a waiting connection) for ``new``; ``new`` itself when it is the
        victim or there is none."""
        if victim is None or victim is new:
            transport = self._forget(new)
            self.stats["full"] += 1
            self._log_refusal(f"a connection: {why} (the most this server keeps)")
            if transport is not None:  # once its handler started
                asyncio.get_running_loop().call_soon(transport.close)
            return
        transport = self._forget(victim)
        self.stats["evicted"] += 1
        due, n = self._evictions.due()
        if due:
            log.warning(
                "live: closed a connection waiting for a request to make room: %s%s",
                one_line(why, 120),
                held(n),
            )
        if transport is not None:
            transport.close()

    def _forget(self, handler):
        """Stop counting ``handler``'s connection (closed, or about to be); its transport."""
        ip = self._ips.pop(handler, None)
        connections = self._by_ip.get(ip)
        if connections is None or handler not in connections:
            return None
        transport = connections.pop(handler)
        self._open -= 1
        if not connections:
            del self._by_ip[ip]
        return transport

    def _bad_request(self, remote, exc) -> None:
        """aiohttp refused a request before this server saw it (no ``Host``, two of them, a
        broken request line): counted and said in one line a second at most, no traceback."""
        self.stats["malformed"] += 1
        due, n = self._malformed.due()
        if due:
            reason = getattr(exc, "message", None) or exc or "a malformed request"
            log.warning(
                "live: refused a malformed HTTP request from %s (400): %s%s",
                one_line(remote, 60),
                one_line(reason, 120),
                held(n),
            )

    async def stop(self) -> None:
        """Stop ticking, tell every tab the run ended (``end_reason``) and close the connections."""
        if self._drive_task is not None:
            self._drive_task.cancel()
            try:
                await self._drive_task
            except asyncio.CancelledError:
                pass
            # A tick already handed to the worker thread finishes: the end frame counts it.
            await asyncio.get_running_loop().run_in_executor(self._ticker, lambda: None)
        if self.loop.on_status == self._status_changed:
            self.loop.on_status = None
        end = json.dumps({"type": "end", "reason": self.end_reason, "ticks": self.loop.ticks})
        for client in list(self.clients):
            client.reply(end)
            client.closing = True
        await asyncio.gather(*(self._close(c) for c in list(self.clients)))
        if self._runner is not None:
            await self._runner.cleanup()
        if self._ticker is not None:
            self._ticker.shutdown(wait=True)
        if self._worker is not None and self._worker is not self._ticker:
            self._worker.shutdown(wait=False)

    def serve(
        self, stop: threading.Event | None = None, max_seconds: float | None = None, on_start=None
    ) -> None:
        """Serve in this thread until ``stop`` is set or ``max_seconds`` pass (``icco live``);
        the tabs are then told the run ended, and why."""

        async def main():
            address = await self.start()
            if on_start is not None:
                on_start(address)
            end = None if max_seconds is None else time.monotonic() + max_seconds
            try:
                while not (stop is not None and stop.is_set()):
                    if end is not None and time.monotonic() >= end:
                        self.end_reason = f"live.seconds={max_seconds:g} ran out"
                        break
                    await asyncio.sleep(0.05)
            finally:
                await self.stop()

        asyncio.run(main())

    def start_in_thread(self, timeout: float = 10.0) -> tuple[str, int]:
        """Serve from a background thread (beside a bridge, in tests); returns the bound address."""
        started, failure = threading.Event(), []

        def target():
            async def main():
                try:
                    await self.start()
                except OSError as err:
                    failure.append(err)
                    return
                finally:
                    started.set()
                while not self._closed.is_set():
                    await asyncio.sleep(0.05)
                await self.stop()

            asyncio.run(main())

        self._thread = threading.Thread(target=target, daemon=True, name="icco-live-web")
        self._thread.start()
        if not started.wait(timeout):
            raise TimeoutError(f"the live page did not start within {timeout} s")
        if failure:
            raise failure[0]
        return self.address

    def close(self, timeout: float = 10.0, reason: str | None = None) -> None:
        """Stop a server started with :meth:`start_in_thread`; the tabs are told ``reason``."""
        if reason is not None:
            self.end_reason = reason
        self._closed.set()
        if self._thread is not None:
            self._thread.join(timeout)

    # ------------------------------------------------------------------ ticking and broadcasting
    async def _drive(self) -> None:
        aio = asyncio.get_running_loop()
        next_time = time.perf_counter()
        while True:
            if self.paused and not self._steps:
                await asyncio.sleep(0.02)
                next_time = time.perf_counter()
                continue
            self._steps = max(0, self._steps - 1)
            try:
                state = await aio.run_in_executor(self._ticker, self.loop.tick)
            except Exception as err:  # a bad tick must not end the page: log it and keep serving
                log.error("live: tick failed: %s", f"{type(err).__name__}: {err}".splitlines()[0])
                await asyncio.sleep(0.5)
                continue
            self.stats["latency_ms"].append(state.latency_ms)
            self._tick_times.append(time.perf_counter())
            self._broadcast(state.to_dict())
            next_time += 1.0 / (self.rate_hz * self.speed)
            pause = next_time - time.perf_counter()
            if pause < 0:  # late ticks are not made up for
                next_time, pause = time.perf_counter(), 0
            await asyncio.sleep(pause)

    def publish(self, state, fleet: dict | None = None) -> None:
        """Show ``state`` (a ``TickState`` or its dict) to every tab, with the bridge's ``fleet``
        (:meth:`~icco_torchrl.live.bridge.Bridge.fleet`) when given; callable from any thread."""
        payload = state.to_dict() if hasattr(state, "to_dict") else dict(state)
        if fleet is not None:
            payload["fleet"] = self._fleet = fleet
        self._tick_times.append(time.perf_counter())  # the bridge's commands are its ticks
        self._soon(self._broadcast, payload)

    def watch(self, bridge) -> None:
        """Show ``bridge``'s robots: the team and the fleet's state after each of its commands."""
        bridge.on_command = lambda _: self.publish(self.loop.snapshot(), fleet=bridge.fleet())

    def _soon(self, fn, *args) -> None:
        """Run ``fn(*args)`` on the server's event loop (from any thread), unless it has closed."""
        if self._aio is None or self._closed.is_set():
            return
        try:
            self._aio.call_soon_threadsafe(fn, *args)
        except RuntimeError:  # the event loop has just closed
            pass

    def _broadcast(self, payload: dict) -> None:
        self.stats["broadcasts"] += 1
        frame = self._tick_frame(payload)
        for client in self.clients:
            client.offer(frame)

    def _tick_frame(self, payload: dict) -> str:
        payload = {k: v for k, v in payload.items() if k != "planner"}  # sent once, on change
        return json.dumps(
            {
                "type": "tick",
                **payload,
                "paused": self.paused,
                "speed": self.speed,
                "clients": len(self.clients),
                "tick_rate": self.tick_rate(),
                "nominal_rate": self.rate_hz * (self.speed if self.drive else 1.0),
            }
        )

    def tick_rate(self) -> float | None:
        """Ticks per second over the last ``RATE_WINDOW_S`` (None while paused or before two)."""
        now, times = time.perf_counter(), self._tick_times
        while times and times[0] < now - RATE_WINDOW_S:
            times.popleft()
        if (self.drive and self.paused) or len(times) < 2 or times[-1] <= times[0]:
            return None
        return round((len(times) - 1) / (times[-1] - times[0]), 2)

    @staticmethod
    def _planner_frame(status) -> str:
        """The planner status as a message, each text cut to ``MAX_STATUS_CHARS`` (a planner
        may put a whole reply in its error)."""
        fields = {
            k: v[: MAX_STATUS_CHARS - 3] + "..." if isinstance(v, str) and len(v) > MAX_STATUS_CHARS
            else v
            for k, v in asdict(status).items()
        }  # fmt: skip
        return json.dumps({"type": "planner", **fields})

    def _status_changed(self, status) -> None:
        """The loop's planner status changed (any thread): every tab hears of it, once."""
        self._soon(self._broadcast_status, self._planner_frame(status))

    def _broadcast_status(self, frame: str) -> None:
        self._status_frame = frame
        for client in self.clients:
            client.offer_status(frame)

    def _hello(self) -> dict:
        raw = self.loop.raw
        return {
            "type": "hello",
            "mode": "live" if self.drive else "bridge",
            "field_size": raw.field_size,
            "home_radius": raw.home_radius,
            "vision_radius": raw.vision_radius,
            "n_agents": raw.n_agents,
            "team": self.loop.team,
            "dt": raw.dt,
            "agent_radius": raw.agent_radius,
            "resource_radius": raw.resource_radius,
            "invader_radius": raw.invader_radius,
            "rate_hz": self.rate_hz,
            "speed": self.speed,
            "paused": self.paused,
            "drive": self.drive,
            "speeds": list(SPEEDS),
            "policy": self.policy,
            "planner": self.planner,
            "max_instruction": MAX_INSTRUCTION,
            "max_message": MAX_MESSAGE,
            "reference": self.reference,
        }

    # ------------------------------------------------------------------ HTTP and WebSocket handlers
    @web.middleware
    async def _guard(self, request: web.Request, handler) -> web.StreamResponse:
        """Refuse (403, one line) a request that does not name this server in ``Host``, lacks
        the token, or upgrades to a WebSocket from another page's origin (module docstring)."""
        refusal = self._refusal(request)
        if refusal is not None:
            status, refusal = refusal if isinstance(refusal, tuple) else (403, refusal)
            self.stats["forbidden"] += 1
            self._log_refusal(f"{request.method} {request.path}: {refusal}")
            response = web.Response(status=status, text=refusal + "\n")
            response.force_close()  # a refused client gets no second request on this connection
            return response
        return await handler(request)

    def _log_refusal(self, what: str) -> None:
        """One bounded line (the path cut short) about a refusal, at most one a second."""
        due, n = self._refusals.due()
        if due:
            log.warning("live: refused %s%s", one_line(what, 240), held(n))

    def _refusal(self, request: web.Request) -> str | tuple[int, str] | None:
        """Why ``request`` is refused (with its status when not 403), or None."""
        host = request.headers.get("Host", "")
        name = _hostname(host)
        wildcard = self.host in ("0.0.0.0", "::", "")
        if not (
            name in self._names
            or (wildcard and (_is_ip(name) or name == socket.gethostname().lower()))
        ):
            return (
                f"refused: Host {host[:80]!r} is not this server's address (open "
                f"http://{self._shown_host()}:{self.address[1]}/)"
            )
        if self._tokens is not None:
            given = request.query.get("token", "")
            why = self._tokens.check(given, str(request.remote)) if given else "no token"
            if why == "wrong token" or why == "no token":
                return "refused: this page needs its token: open the address with ?token= printed"
            if why is not None:
                return 429, f"refused: {why}"
        origin = request.headers.get("Origin")
        if request.path == "/ws" and origin is not None:
            allowed = {f"http://{host.strip().lower()}", f"https://{host.strip().lower()}"}
            if origin.strip().lower() not in allowed:
                return f"refused: a page from {origin[:80]!r} may not drive this server"
        return None

    def _shown_host(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "::", "") else self.host
        return f"[{host}]" if ":" in host else host

    async def _page(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(PAGE, headers={"Cache-Control": "no-store"})

    async def _socket(self, request: web.Request) -> web.StreamResponse:
        if len(self.clients) >= self.max_clients:
            self.stats["full"] += 1
            refusal = (
                f"refused: {self.max_clients} tabs are open, the most this server serves: "
                "close one, or try again later"
            )
            self._log_refusal(f"a tab: {self.max_clients} are open")
            response = web.Response(status=503, text=refusal + "\n")
            response.force_close()
            return response
        ws = web.WebSocketResponse(heartbeat=10.0, max_msg_size=MAX_MESSAGE)
        await ws.prepare(request)
        client = _Client(ws)
        self.clients.add(client)
        self.stats["connections"] += 1
        client.writer = asyncio.create_task(self._write(client))
        try:
            client.reply(json.dumps(self._hello()))
            client.offer_status(self._status_frame)
            if not self.drive or self.paused:  # show the team at once, even before the next tick
                state = self.loop.snapshot().to_dict()
                client.offer(self._tick_frame({**state, "fleet": self._fleet}))
            async for msg in ws:
                if msg.type != WSMsgType.TEXT or client.closing:
                    continue
                if not client.admit():
                    self._refuse(client)
                    continue
                try:
                    error = await self._request(msg.data)
                except Exception as err:  # a bug must not close the tab: an error reply, one line
                    self.stats["failed"] += 1
                    self._failed("a request", err)
                    error = f"the request failed: {one_line(type(err).__name__, 60)}"
                if error:
                    self.stats["errors"] += 1
                client.reply(json.dumps({"type": "error", "message": error} if error else OK))
                # Yield once a message: a tab's buffered burst is read without waiting, so
                # without this a crowd's would hold the event loop, and the ticks, for a second.
                await asyncio.sleep(0)
        except (ConnectionError, RuntimeError, asyncio.CancelledError):
            pass  # a tab that went away: the loop goes on
        finally:
            self.clients.discard(client)
            if not client.closing:
                client.writer.cancel()
            self.stats["frames"] += client.sent
            self.stats["dropped"] += client.dropped
        return ws

    def _refuse(self, client: _Client) -> None:
        """Drop a request over ``client``'s rate limit: counted, and said once a second."""
        client.refused += 1
        self.stats["refused"] += 1
        now = time.monotonic()
        if now - client.warned >= 1.0:
            client.warned = now
            message = (
                f"too many requests: at most {RATE_LIMIT:g} a second (after {BURST}); "
                f"{client.refused} dropped so far"
            )
            client.reply(json.dumps({"type": "error", "message": message}))

    async def _write(self, client: _Client) -> None:
        try:
            while not client.ws.closed:
                await client.ready.wait()
                client.ready.clear()
                for frame in client.take():
                    await client.ws.send_str(frame)
                    client.sent += 1
                if client.closing and not client.replies:
                    break
        except (ConnectionError, RuntimeError):
            pass

    async def _close(self, client: _Client) -> None:
        """Send what ``client`` still has queued (the end frame), then close its connection."""
        try:
            await asyncio.wait_for(client.writer, 2.0)
        except (asyncio.TimeoutError, asyncio.CancelledError, ConnectionError, RuntimeError):
            pass
        await client.ws.close(code=1000, message=b"run ended")

    def _failed(self, what: str, err: Exception) -> None:
        due, n = self._failures.due()
        if due:
            log.error(
                "live: %s failed: %s%s", what, one_line(f"{type(err).__name__}: {err}"), held(n)
            )

    async def _request(self, text: str) -> str | None:
        """Apply one page request from a tab; an error message for it, or None. Team changes are
        at most ``CHANGE_RATE`` a second from all tabs together (after ``CHANGE_BURST``);
        they and instructions wait for the loop in a worker thread, never in the event loop."""
        msg = _parse(text)
        if isinstance(msg, str):
            return msg
        kind = msg.get("type")
        if kind == "instruct" or (self.drive and kind in LOOP_REQUESTS):
            if kind != "instruct" and not self._changes.admit():
                self.stats["busy"] += 1
                return (
                    f"busy: at most {CHANGE_RATE:g} team changes a second from all tabs together "
                    f"(after {CHANGE_BURST}); this one was dropped, try again"
                )
            if self._worker is not None:
                aio = asyncio.get_running_loop()
                return await aio.run_in_executor(self._worker, self._apply, msg)
        return self._apply(msg)

    def handle(self, text: str) -> str | None:
        """Apply one page request; returns an error message for the sender, or None."""
        msg = _parse(text)
        return msg if isinstance(msg, str) else self._apply(msg)

    def _apply(self, msg) -> str | None:
        """Apply one parsed request (any thread but the event loop's for the loop's requests);
        an error message for the sender, or None."""
        kind = msg.get("type")
        if kind == "instruct":
            text = msg.get("text")
            if not isinstance(text, str) or not text.strip():
                return "empty instruction: type one, e.g. 'Go right' (the team keeps its last plan)"
            try:
                self.loop.instruct(text)
            except ValueError as err:
                return str(err)
            return None
        if not isinstance(kind, str) or kind not in CONTROLS:
            shown = repr(kind) if len(repr(kind)) <= 40 else repr(kind)[:37] + "..."
            return f"unknown request type {shown}; expected instruct, {', '.join(CONTROLS)}"
        if not self.drive:
            if kind in ("add_robot", "remove_robot"):
                return (
                    "this page shows robots driven by the bridge: its team is the robots that "
                    "report (a new one joins, a silent one leaves after live.timeout_s)"
                )
            return (
                "this page shows robots driven by the bridge: pause, step, reset and speed are "
                "not available"
            )
        if kind == "reset":
            self._show("reset")
            return None
        error = self._control(kind, msg)
        if error is None:
            self._show("snapshot")  # every tab sees the change at once, even while paused
        return error

    def _control(self, kind: str, msg: dict) -> str | None:
        """Pause, resume, step, speed or a team change; an error message, or None."""
        if kind in ("pause", "resume"):
            self.paused = kind == "pause"
        elif kind == "step":
            if not self.paused:
                return "step works while paused"
            if self._steps >= MAX_STEPS:
                return f"{MAX_STEPS} steps are already waiting: this one was not added"
            self._steps += 1
        elif kind in ("add_robot", "remove_robot"):
            robot = msg.get("robot")
            if kind == "remove_robot" and robot is None:
                return (
                    "remove_robot needs the robot to remove: {'type': 'remove_robot', 'robot': i}"
                )
            try:  # between two ticks: the loop's lock
                if kind == "add_robot":
                    self.loop.add_robot(robot)
                else:
                    self.loop.remove_robot(robot)
            except ValueError as err:
                return str(err)
        elif kind == "speed":
            value = msg.get("value")
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                value = repr(value) if len(repr(value)) <= 40 else repr(value)[:37] + "..."
                return f"speed must be one of {list(SPEEDS)}, got {value}"
            if value not in SPEEDS:
                return f"speed must be one of {list(SPEEDS)}, got {value!r}"
            self.speed = float(value)
        return None

    def _show(self, job: str) -> None:
        """Reset the loop (``"reset"``) or take its snapshot, in tick order (never mid-tick), and
        show the state. Requests coalesce: one job at most waits in the tick thread, a reset
        winning over a snapshot, so a burst of them costs one reset, not a queue of them."""
        with self._show_lock:
            if self._show_job is not None:
                if job == "reset":
                    self._show_job = "reset"
                return
            self._show_job = job

        def run_and_show():
            with self._show_lock:  # taken in the tick thread: the newest request's job
                job, self._show_job = self._show_job, None
            state = self.loop.reset() if job == "reset" else self.loop.snapshot()
            self._soon(self._broadcast, state.to_dict())

        def schedule():  # on the event loop (a team change asks from the tick thread)
            try:
                self._aio.run_in_executor(self._ticker, run_and_show)
            except RuntimeError:  # the server is stopping: nothing more to show
                with self._show_lock:
                    self._show_job = None

        self._soon(schedule)
