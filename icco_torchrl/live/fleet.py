"""A simulated fleet that speaks the bridge's protocol: unicycle robots with noise and latency.

Run it beside :class:`~icco_torchrl.live.bridge.Bridge` on one machine to try the bridge
without robots: it streams the robots' poses (and fixed resources, and an invader walking to
home) to the bridge as a motion-capture system would, applies the velocity commands it gets
back after ``latency`` seconds, within the robots' limits, with Gaussian noise on the motion.
``silence(i)`` stops reporting robot ``i`` (a robot that drops off the network), ``resume(i)``
brings it back, and ``join(i)`` adds a robot with a new id (a robot switched on mid-run). Robots
carry any integer ids (``ids``; default ``0..n_robots-1``); commands for other ids are ignored.
With ``token`` (the bridge's ``live.token``) every state carries it.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from collections import deque

import numpy as np

from icco_torchrl.live.dwa import DEFAULT_LIMITS, RobotLimits


class SimulatedFleet:
    """Robots ``ids`` (default ``0..n_robots-1``) streaming poses to ``bridge_address`` at
    ``rate_hz`` and driven by its commands (see the module docstring)."""

    def __init__(
        self,
        bridge_address,
        *,
        n_robots: int = 3,
        n_resources: int = 6,
        rate_hz: float = 20.0,
        latency: float = 0.05,
        noise: float = 0.005,
        limits: RobotLimits = DEFAULT_LIMITS,
        field_size: float = 6.5,
        seed: int = 0,
        ids=None,
        token: str | None = None,
    ):
        self.bridge, self.rate_hz, self.latency, self.noise, self.limits = (
            bridge_address,
            rate_hz,
            latency,
            noise,
            limits,
        )
        self.rng = np.random.default_rng(seed)
        self.token = token  # carried by every state (the bridge's live.token)
        self.half = half = field_size / 2 - 0.5
        self.ids = list(range(n_robots)) if ids is None else [int(i) for i in ids]
        if len(set(self.ids)) != len(self.ids):
            raise ValueError(f"robot ids must differ, got {self.ids}")
        n_robots = len(self.ids)
        self._lock = threading.Lock()  # join() may add a robot while run() steps them
        self.poses = np.column_stack(
            [
                self.rng.uniform(-half, half, (n_robots, 2)),
                self.rng.uniform(-np.pi, np.pi, n_robots),
            ]
        )
        self.velocity = np.zeros((n_robots, 2))
        self.resources = self.rng.uniform(-half, half, (n_resources, 2))
        self.invader = np.array([[half, half]])
        self.silenced: set[int] = set()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.queue: deque = deque()  # (apply_at, message)
        self.commands: list[dict] = []

    def silence(self, robot: int) -> None:
        """Robot ``robot`` (an id) stops reporting its pose."""
        self.silenced.add(robot)

    def resume(self, robot: int) -> None:
        """Robot ``robot`` reports again (it comes back after a silence)."""
        self.silenced.discard(robot)

    def join(self, robot: int, pose=None) -> None:
        """A robot with the new id ``robot`` is switched on (at ``pose`` [x, y, theta], else a
        random one) and reports from the next state on."""
        if robot in self.ids:
            raise ValueError(f"robot {robot} is already in the fleet (ids {self.ids})")
        if pose is None:
            xy = self.rng.uniform(-self.half, self.half, 2)
            pose = [*xy, self.rng.uniform(-np.pi, np.pi)]
        with self._lock:
            self.ids.append(int(robot))
            self.poses = np.vstack([self.poses, np.asarray(pose, float).reshape(1, 3)])
            self.velocity = np.vstack([self.velocity, np.zeros((1, 2))])

    def row(self, robot: int) -> int:
        """The row of robot ``robot`` (an id) in ``poses`` and ``velocity``."""
        return self.ids.index(robot)

    def send_raw(self, data: bytes) -> None:
        self.sock.sendto(data, self.bridge)

    def _receive(self) -> None:
        while True:
            try:
                data, _ = self.sock.recvfrom(65_507)
            except BlockingIOError:
                return
            msg = json.loads(data)
            self.commands.append(msg)
            self.queue.append((time.monotonic() + self.latency, msg))

    def _apply_due(self) -> None:
        now = time.monotonic()
        while self.queue and self.queue[0][0] <= now:
            _, msg = self.queue.popleft()
            rows = {rid: k for k, rid in enumerate(self.ids)}
            for r in msg["robots"]:
                if r["id"] not in rows:
                    continue  # not one of these robots
                v = float(np.clip(r["v"], 0.0, self.limits.max_speed))
                w = float(np.clip(r["w"], -self.limits.max_turn, self.limits.max_turn))
                self.velocity[rows[r["id"]]] = (v, w)

    def step(self, dt: float) -> None:
        with self._lock:
            self._step(dt)

    def _step(self, dt: float) -> None:
        v, w = self.velocity[:, 0], self.velocity[:, 1]
        self.poses[:, 2] += w * dt + self.rng.normal(0, self.noise, len(v))
        self.poses[:, 0] += v * np.cos(self.poses[:, 2]) * dt + self.rng.normal(
            0, self.noise, len(v)
        )
        self.poses[:, 1] += v * np.sin(self.poses[:, 2]) * dt + self.rng.normal(
            0, self.noise, len(v)
        )
        home = -self.invader / max(np.linalg.norm(self.invader), 1e-6)
        self.invader = (
            self.invader + 0.2 * dt * home
            if np.linalg.norm(self.invader) > 0.4
            else np.array([[3.0, 3.0]])
        )

    def state_message(self) -> bytes:
        with self._lock:
            robots = [
                {"id": rid, "pose": self.poses[k].tolist()}
                for k, rid in enumerate(self.ids)
                if rid not in self.silenced
            ]
        msg = {
            "type": "state",
            "time": time.time(),
            "robots": robots,
            "resources": self.resources.tolist(),
            "invader": self.invader.tolist(),
        }
        if self.token is not None:
            msg["token"] = self.token
        return json.dumps(msg).encode()

    def run(self, stop: threading.Event, max_seconds: float = 10.0) -> None:
        period = 1.0 / self.rate_hz
        end = time.monotonic() + max_seconds
        while not stop.is_set() and time.monotonic() < end:
            self._receive()
            with self._lock:
                self._apply_due()
            self.step(period)
            self.sock.sendto(self.state_message(), self.bridge)
            time.sleep(period)

    def close(self) -> None:
        self.sock.close()
