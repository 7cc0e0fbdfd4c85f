"""Robot bridge: the live loop driven by external positions, commanding robots over JSON-over-UDP.

Protocol (UTF-8 JSON, one object per datagram; distances in metres, angles in radians, field
frame centred on home, +x right, +y up):

* in, ``{"type": "state", "time": t, "robots": [{"id": i, "pose": [x, y, theta]}, ...],
  "resources": [[x, y], ...], "invader": [[x, y]] }`` as a motion-capture system streams it.
  ``robots`` may list any subset (robots reported separately); ``resources`` and ``invader``
  are optional (kept from the last message; ``"invader": []`` means none on the field).
* in, ``{"type": "instruct", "text": "Go right"}``: a language instruction for the team.
* out, to the sender of the latest state: ``{"type": "command", "time": t, "robots": [{"id": i,
  "target": [x, y], "v": v, "w": w, "stopped": bool, "reason": null | "stale"}, ...]}`` at the
  control rate: the policy's next point for each robot and a unicycle velocity command toward
  it from the Dynamic Window Approach (``dwa.py``) within the robot's limits.

A robot whose pose is older than ``timeout`` seconds (or never seen) gets ``v = w = 0`` with
``"stopped": true, "reason": "stale"``, and the event is logged once; the others keep going.
A malformed datagram is logged, counted in ``stats["malformed"]`` and ignored, never a crash.
"""

from __future__ import annotations

import json
import logging
import socket
import threading
import time

import numpy as np

from icco_torchrl.live.dwa import DEFAULT_LIMITS, RobotLimits, dwa_command
from icco_torchrl.live.loop import LiveLoop

log = logging.getLogger("icco.bridge")
MAX_DATAGRAM = 65_507


class ProtocolError(ValueError):
    """A datagram that does not follow the protocol (module docstring)."""


def parse_message(data: bytes, n_robots: int) -> dict:
    """The validated message, or :class:`ProtocolError` with one line saying what is wrong."""
    try:
        msg = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ProtocolError(f"not UTF-8 JSON: {err}") from None
    if not isinstance(msg, dict) or msg.get("type") not in ("state", "instruct"):
        raise ProtocolError("a message must be a JSON object with type 'state' or 'instruct'")
    if msg["type"] == "instruct":
        if not isinstance(msg.get("text"), str) or not msg["text"].strip():
            raise ProtocolError("an instruct message needs a non-empty 'text'")
        return msg
    robots = msg.get("robots", [])
    if not isinstance(robots, list):
        raise ProtocolError("'robots' must be a list")
    for r in robots:
        if (
            not isinstance(r, dict)
            or not isinstance(r.get("id"), int)
            or not 0 <= r["id"] < n_robots
        ):
            raise ProtocolError(f"each robot needs an integer 'id' in [0, {n_robots})")
        pose = r.get("pose")
        if not (isinstance(pose, list) and len(pose) == 3 and all(_finite(v) for v in pose)):
            raise ProtocolError(f"robot {r['id']}: 'pose' must be [x, y, theta] (finite numbers)")
    for key in ("resources", "invader"):
        if key in msg and not (
            isinstance(msg[key], list)
            and all(
                isinstance(p, list) and len(p) == 2 and all(_finite(v) for v in p) for p in msg[key]
            )
        ):
            raise ProtocolError(f"'{key}' must be a list of [x, y] points")
    if "time" in msg and not _finite(msg["time"]):
        raise ProtocolError("'time' must be a number (seconds)")
    return msg


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)


class Bridge:
    """Serve one team over UDP (see the module docstring); :meth:`serve` runs until ``stop`` is
    set."""

    def __init__(
        self,
        loop: LiveLoop,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        rate_hz: float = 10.0,
        timeout: float = 0.5,
        limits: RobotLimits = DEFAULT_LIMITS,
    ):
        if not rate_hz > 0 or not timeout > 0:
            raise ValueError(f"rate_hz and timeout must be > 0, got {rate_hz!r} and {timeout!r}")
        self.loop, self.rate_hz, self.timeout, self.limits = (
            loop,
            float(rate_hz),
            float(timeout),
            limits,
        )
        self.n = loop.raw.n_agents
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((host, port))
        except OSError as err:
            raise OSError(f"cannot listen on udp {host}:{port}: {err.strerror or err}") from None
        self.address = self.sock.getsockname()
        self.poses = np.zeros((self.n, 3))
        self.seen = np.full(self.n, -np.inf)  # monotonic time of each robot's latest pose
        self.velocity = np.zeros((self.n, 2))  # measured, m/s (for the policy)
        self.command = np.zeros((self.n, 2))  # last (v, w) sent
        self.resources = self.invader = None
        self.reply_to = None
        self.stale_logged = np.zeros(self.n, bool)
        self.stats = {
            "messages": 0,
            "malformed": 0,
            "commands": 0,
            "stale_stops": 0,
            "latency_ms": [],
        }
        self._received_at = None
        self._last: dict[int, dict] = {}  # each robot's entry in the last command message
        self.on_command = None  # called with each command message (e.g. the live page)

    def handle(self, data: bytes, sender) -> None:
        """One datagram: update the measured state, or pass an instruction to the live loop."""
        try:
            msg = parse_message(data, self.n)
        except ProtocolError as err:
            self.stats["malformed"] += 1
            log.warning("bridge: ignored a malformed datagram from %s: %s", sender, err)
            return
        self.stats["messages"] += 1
        if msg["type"] == "instruct":
            self.loop.instruct(msg["text"])
            return
        now = time.monotonic()
        for r in msg.get("robots", []):
            i, pose = r["id"], np.asarray(r["pose"], float)
            if np.isfinite(self.seen[i]) and now > self.seen[i]:
                self.velocity[i] = (pose[:2] - self.poses[i, :2]) / (now - self.seen[i])
            self.poses[i], self.seen[i] = pose, now
            self.stale_logged[i] = False
        if "resources" in msg:
            self.resources = np.asarray(msg["resources"], float).reshape(-1, 2)
        if "invader" in msg:
            self.invader = np.asarray(msg["invader"], float).reshape(-1, 2)
        self.reply_to, self._received_at = sender, time.perf_counter()

    def control(self) -> dict | None:
        """One control tick: the policy's targets and DWA commands; stale robots stopped."""
        if self.reply_to is None:
            return None
        now = time.monotonic()
        fresh = now - self.seen <= self.timeout
        resources = (
            self.resources
            if self.resources is not None and len(self.resources) == self.loop.raw.n_resources
            else None
        )
        _, targets = self.loop.act_on(
            self.poses[:, :2], velocities=self.velocity, resources=resources, invader=self.invader
        )
        robots = []
        for i in range(self.n):
            if not fresh[i]:
                if not self.stale_logged[i]:
                    log.warning(
                        "bridge: robot %d sent no pose for %.2f s: stopping it",
                        i,
                        now - self.seen[i],
                    )
                    self.stale_logged[i] = True
                    self.stats["stale_stops"] += 1
                self.command[i] = 0.0
                robots.append(
                    {
                        "id": i,
                        "target": targets[i].tolist(),
                        "v": 0.0,
                        "w": 0.0,
                        "stopped": True,
                        "reason": "stale",
                    }
                )
                continue
            others = np.delete(self.poses[:, :2], i, axis=0)
            v, w = dwa_command(
                self.poses[i],
                self.command[i],
                targets[i],
                self.limits,
                1.0 / self.rate_hz,
                others=others,
            )
            self.command[i] = (v, w)
            robots.append(
                {
                    "id": i,
                    "target": targets[i].tolist(),
                    "v": v,
                    "w": w,
                    "stopped": False,
                    "reason": None,
                }
            )
        message = {"type": "command", "time": time.time(), "robots": robots}
        self._last = {r["id"]: r for r in robots}
        self.sock.sendto(json.dumps(message).encode(), self.reply_to)
        self.stats["commands"] += 1
        if self._received_at is not None:
            self.stats["latency_ms"].append((time.perf_counter() - self._received_at) * 1e3)
            self._received_at = None
        if self.on_command is not None:
            self.on_command(message)
        return message

    def fleet(self) -> dict:
        """The fleet as the bridge sees it, for the live page: each robot's last pose, how old it
        is, its last command and whether it is stopped (and why); the message counts."""
        now = time.monotonic()
        robots = []
        for i in range(self.n):
            seen = bool(np.isfinite(self.seen[i]))
            last = self._last.get(i, {"stopped": True, "reason": "no command yet"})
            robots.append(
                {
                    "id": i,
                    "pose": np.round(self.poses[i], 3).tolist() if seen else None,
                    "age_s": round(float(now - self.seen[i]), 3) if seen else None,
                    "v": float(self.command[i, 0]),
                    "w": float(self.command[i, 1]),
                    "stopped": bool(last["stopped"]),
                    "reason": last["reason"],
                }
            )
        s = self.stats
        latency = s["latency_ms"][-50:]
        return {
            "robots": robots,
            "address": f"udp {self.address[0]}:{self.address[1]}",
            "rate_hz": self.rate_hz,
            "timeout_s": self.timeout,
            "messages": s["messages"],
            "commands": s["commands"],
            "malformed": s["malformed"],
            "stale_stops": s["stale_stops"],
            "latency_ms": float(np.median(latency)) if latency else None,
        }

    def serve(self, stop: threading.Event, max_seconds: float | None = None) -> None:
        """Receive datagrams and send commands at ``rate_hz`` until ``stop`` is set (or
        ``max_seconds`` pass)."""
        period = 1.0 / self.rate_hz
        end = None if max_seconds is None else time.monotonic() + max_seconds
        next_tick = time.monotonic() + period
        while not stop.is_set() and (end is None or time.monotonic() < end):
            self.sock.settimeout(max(1e-3, next_tick - time.monotonic()))
            try:
                data, sender = self.sock.recvfrom(MAX_DATAGRAM)
                self.handle(data, sender)
            except TimeoutError:
                pass
            if time.monotonic() >= next_tick:
                next_tick += period
                try:
                    self.control()
                except Exception as err:  # a bad tick must not end the bridge: log and go on
                    log.error(
                        "bridge: control tick failed: %s",
                        f"{type(err).__name__}: {err}".splitlines()[0],
                    )

    def close(self) -> None:
        self.sock.close()
