"""``icco bridge checkpoint=PATH``: a trained team commanding robots over UDP (``live.*`` settings).

    icco bridge checkpoint=runs/icco/.../checkpoint.pt                  # wait for a motion-capture stream
    icco bridge checkpoint=... live.fleet=true live.seconds=30          # with the simulated fleet beside it

Prints where it listens, then a summary when stopped (Ctrl-C, SIGTERM or ``live.seconds``).
"""
from __future__ import annotations

import logging
import signal
import sys
import threading
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from icco_torchrl.live.bridge import Bridge
from icco_torchrl.live.dwa import RobotLimits
from icco_torchrl.live.fleet import SimulatedFleet
from icco_torchrl.live.loop import LiveLoop

LOOPBACK = ("127.0.0.1", "localhost", "::1")
# The small policy that ships with a source checkout (assets/README.md says how it was made).
DEMO_POLICY = Path(__file__).resolve().parents[2] / "assets" / "demo_icco.pt"


def run_bridge(cfg: DictConfig) -> float:
    from icco_torchrl.instructions import LLMPlanner

    live = cfg.live
    checkpoint = cfg.checkpoint
    if not checkpoint:
        if not DEMO_POLICY.is_file():
            raise ValueError(f"no checkpoint= given and no demo policy at {DEMO_POLICY}: give checkpoint=PATH")
        checkpoint = DEMO_POLICY
        print(f"icco bridge: no checkpoint= given: using the demo policy {DEMO_POLICY} (see assets/README.md)")
    if live.host not in LOOPBACK:
        print(f"warning: live.host={live.host} accepts datagrams from other machines; anyone who can reach "
              f"it can steer the robots", file=sys.stderr)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    limits = RobotLimits(max_speed=live.max_speed, max_turn=live.max_turn, max_accel=live.max_accel,
                         max_turn_accel=live.max_turn_accel, radius=live.robot_radius)
    loop = LiveLoop.from_checkpoint(checkpoint, planner=LLMPlanner.from_config(cfg.llm), device=cfg.device)
    bridge = Bridge(loop, host=live.host, port=live.port, rate_hz=live.rate_hz, timeout=live.timeout_s, limits=limits)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    threads = []
    if live.fleet:
        fleet = SimulatedFleet(bridge.address, n_robots=loop.raw.n_agents, n_resources=loop.raw.n_resources,
                               limits=limits, field_size=loop.raw.field_size, seed=cfg.seed)
        threads.append(threading.Thread(target=fleet.run, args=(stop, live.seconds or 1e9), daemon=True))
    print(f"icco bridge: listening on udp {bridge.address[0]}:{bridge.address[1]} at {live.rate_hz:g} Hz "
          f"({'with the simulated fleet' if live.fleet else 'waiting for state messages'}); Ctrl-C stops", flush=True)
    for t in threads:
        t.start()
    try:
        bridge.serve(stop, max_seconds=live.seconds)
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=5)
        bridge.close()
    s = bridge.stats
    latency = np.median(s["latency_ms"]) if s["latency_ms"] else float("nan")
    print(f"icco bridge: {s['messages']} messages, {s['commands']} commands, {s['malformed']} malformed, "
          f"{s['stale_stops']} stale-robot stops; median state-to-command latency {latency:.1f} ms", flush=True)
    return float(s["commands"])
