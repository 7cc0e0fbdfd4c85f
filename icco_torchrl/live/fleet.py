"""A simulated fleet that speaks the bridge's protocol: unicycle robots with noise and latency.

Run it beside :class:`~icco_torchrl.live.bridge.Bridge` on one machine to try the bridge
without robots: it streams the robots' poses (and fixed resources, and an invader walking to
home) to the bridge as a motion-capture system would, applies the velocity commands it gets
back after ``latency`` seconds, within the robots' limits, with Gaussian noise on the motion.
``silence(i)`` stops reporting robot ``i`` (a robot that drops off the network).
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
    ):
        self.bridge, self.rate_hz, self.latency, self.noise, self.limits = (
            bridge_address,
            rate_hz,
            latency,
            noise,
            limits,
        )
        self.rng = np.random.default_rng(seed)
        half = field_size / 2 - 0.5
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
        self.silenced.add(robot)

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
            for r in msg["robots"]:
                v = float(np.clip(r["v"], 0.0, self.limits.max_speed))
                w = float(np.clip(r["w"], -self.limits.max_turn, self.limits.max_turn))
                self.velocity[r["id"]] = (v, w)

    def step(self, dt: float) -> None:
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
        robots = [
            {"id": i, "pose": self.poses[i].tolist()}
            for i in range(len(self.poses))
            if i not in self.silenced
        ]
        return json.dumps(
            {
                "type": "state",
                "time": time.time(),
                "robots": robots,
                "resources": self.resources.tolist(),
                "invader": self.invader.tolist(),
            }
        ).encode()

    def run(self, stop: threading.Event, max_seconds: float = 10.0) -> None:
        period = 1.0 / self.rate_hz
        end = time.monotonic() + max_seconds
        while not stop.is_set() and time.monotonic() < end:
            self._receive()
            self._apply_due()
            self.step(period)
            self.sock.sendto(self.state_message(), self.bridge)
            time.sleep(period)

    def close(self) -> None:
        self.sock.close()
