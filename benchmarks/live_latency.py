"""Latency of driving a team live: live-loop ticks, offline planner calls, bridge round trips.

    python benchmarks/live_latency.py     # ~30 s; writes benchmarks/results/live_latency.json

The networks are ICCO's at the default sizes, untrained (a trained policy costs the same). One
torch thread. Tick = policy + env step + bookkeeping, run at 10 Hz; planner = the offline rule
planner through LLMPlanner (cache off); bridge round trip = a state datagram sent over loopback
until the command datagram comes back (the bridge ticks at 50 Hz, so up to 20 ms of it is the
wait for the next control tick).
"""

from __future__ import annotations

import json
import socket
import threading
import time
from pathlib import Path

import numpy as np
import torch

from icco_torchrl.instructions import LLMPlanner
from icco_torchrl.live import LiveLoop
from icco_torchrl.live.bridge import Bridge
from icco_torchrl.modules.policy import make_policy
from icco_torchrl.training.build import build_components, compose_config, make_env


def make_loop(planner=None) -> LiveLoop:
    cfg = compose_config(["method=icco"])
    parts = build_components(cfg)
    env = make_env(cfg, num_envs=1, waypoint_mode="external", max_steps=10**6)
    return LiveLoop(
        env,
        make_policy(parts["agent"], env.full_action_spec_unbatched, parts["coordinator"]),
        planner,
    )


def stats(ms) -> dict:
    ms = np.asarray(ms)
    return {
        "median_ms": float(np.median(ms)),
        "p99_ms": float(np.percentile(ms, 99)),
        "n": int(len(ms)),
    }


def main() -> None:
    torch.set_num_threads(1)
    loop = make_loop()
    loop.run(20, rate_hz=100)  # warm-up
    ticks = loop.run(200, rate_hz=10)
    planner = LLMPlanner()
    pos = np.array([[0.0, 0.0], [1.0, 1.0], [-1.0, 1.0]])
    plan_ms = []
    for text in ("Go right", "Move top", "Gather center", "Spread out") * 10:
        start = time.perf_counter()
        planner.plan(text, pos)
        plan_ms.append((time.perf_counter() - start) * 1e3)
    bridge = Bridge(make_loop(), rate_hz=50, timeout=1.0)
    stop = threading.Event()
    server = threading.Thread(target=bridge.serve, args=(stop, 60.0), daemon=True)
    server.start()
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.settimeout(2.0)
    rtt = []
    for _ in range(100):
        msg = {
            "type": "state",
            "robots": [
                {"id": i, "pose": [float(p[0]), float(p[1]), 0.0]} for i, p in enumerate(pos)
            ],
        }
        start = time.perf_counter()
        client.sendto(json.dumps(msg).encode(), bridge.address)
        client.recvfrom(65_507)
        rtt.append((time.perf_counter() - start) * 1e3)
    stop.set()
    server.join(timeout=5)
    bridge.close()
    result = {
        "tick_at_10hz": stats(ticks),
        "offline_planner": stats(plan_ms),
        "bridge_round_trip_50hz": stats(rtt[5:]),
        "bridge_state_to_command": stats(bridge.stats["latency_ms"][5:]),
        "threads": 1,
    }
    out = Path(__file__).parent / "results" / "live_latency.json"
    out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
