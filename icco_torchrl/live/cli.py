"""``icco live`` (a trained team on a web page) and ``icco bridge`` (commanding robots over UDP).

    icco live                                       # the demo policy at http://127.0.0.1:8000/
    icco live checkpoint=runs/icco/.../checkpoint.pt live.web_port=8080
    icco bridge checkpoint=runs/icco/.../checkpoint.pt  # wait for a motion-capture stream
    icco bridge live.fleet=true live.web=true        # a simulated fleet, watched in the page

Both print where they listen, then a summary when stopped (Ctrl-C, SIGTERM or ``live.seconds``).
Settings: ``live.*`` (:class:`~icco_torchrl.training.config.LiveConfig`: defaults, ranges and
what each one means).
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
from pathlib import Path
from urllib.parse import quote

import numpy as np
from omegaconf import DictConfig

from icco_torchrl.live.bridge import Bridge
from icco_torchrl.live.dwa import RobotLimits
from icco_torchrl.live.fleet import SimulatedFleet
from icco_torchrl.live.guard import redact_run_folder
from icco_torchrl.live.loop import LiveLoop, scripted_yardstick
from icco_torchrl.live.web import LiveServer

LOOPBACK = ("127.0.0.1", "localhost", "::1")
# The small policy that ships with a source checkout (assets/README.md says how it was made).
DEMO_POLICY = Path(__file__).resolve().parents[2] / "assets" / "demo_icco.pt"


def _checkpoint(cfg: DictConfig, command: str) -> Path:
    """``checkpoint=``, or the shipped demo policy (said on stdout)."""
    if cfg.checkpoint:
        return Path(cfg.checkpoint)
    if not DEMO_POLICY.is_file():
        raise ValueError(
            f"no checkpoint= given and no demo policy at {DEMO_POLICY}: give checkpoint=PATH"
        )
    print(
        f"icco {command}: no checkpoint= given: using the demo policy {DEMO_POLICY} "
        "(see assets/README.md)"
    )
    return DEMO_POLICY


def _warn_if_exposed(host: str, token: str | None = None, command: str = "live") -> None:
    """Say on stderr who can steer the team when ``host`` is reachable from other machines."""
    if host in LOOPBACK:
        return
    channels = (
        "the page (live.web=true) and every state and instruct datagram of the UDP port"
        if command == "bridge"
        else "the page"
    )
    if token:
        guard = (
            f"live.token guards {channels}: only who has the token can steer the team (it "
            "travels unencrypted: anyone who reads this network can read it)"
        )
    else:
        guard = (
            f"anyone who can reach it can steer the team through {channels} (set "
            "live.token=SECRET to require a token of them)"
        )
    print(f"warning: live.host={host} is reachable from other machines; {guard}", file=sys.stderr)


def _keep_token_private(token: str | None) -> None:
    """With a token, the run folder Hydra wrote (``.hydra/``, ``cli.log``): the token's place
    redacted in its files, which only their owner may read (``guard.redact_run_folder``). They
    never held the token itself (``guard.keep_token_out`` ran before Hydra wrote them)."""
    if token is None:
        return
    try:
        from hydra.core.hydra_config import HydraConfig

        if not HydraConfig.initialized():
            return
        folder = HydraConfig.get().runtime.output_dir
    except Exception:  # not run by Hydra (a test calling run_live): no folder was written
        return
    redact_run_folder(folder, token)


def _page_url(address, token: str | None) -> str:
    """The page's address as printed: with ``?token=`` when the server wants one."""
    host = f"[{address[0]}]" if ":" in str(address[0]) else address[0]
    return f"http://{host}:{address[1]}/" + (f"?token={quote(token)}" if token else "")


def _stop_on_signals() -> threading.Event:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def _warm_planner() -> None:
    """Import the planner's backend (litellm: seconds) in the background once the page is up, so
    that a person's first instruction does not wait for it."""
    from icco_torchrl.instructions.llm import _litellm

    threading.Thread(target=_litellm, daemon=True, name="icco-planner-import").start()


def _planner_label(cfg: DictConfig) -> str:
    return (
        str(cfg.llm.get("model") or cfg.llm.get("backend") or "offline") if cfg.llm else "offline"
    )


def _prepare(cfg: DictConfig, command: str) -> Path:
    """The checkpoint to run, once the token is kept private, exposure warned of, logging set."""
    live = cfg.live
    _keep_token_private(live.get("token"))
    checkpoint = _checkpoint(cfg, command)
    _warn_if_exposed(live.host, live.get("token"), command)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    return checkpoint


def _live_server(cfg: DictConfig, loop: LiveLoop, checkpoint: Path, drive: bool) -> LiveServer:
    """The page's server for ``loop`` (``drive``: it ticks the loop, else it only shows it)."""
    live = cfg.live
    reference = scripted_yardstick(checkpoint, live.reference_episodes, seed=cfg.seed)
    return LiveServer(
        loop,
        host=live.host,
        port=live.web_port,
        rate_hz=live.rate_hz,
        drive=drive,
        policy=checkpoint.name,
        planner=_planner_label(cfg),
        token=live.get("token"),
        reference=reference,
    )


def run_live(cfg: DictConfig) -> float:
    """``icco live``: serve the page and drive the team until stopped; returns the ticks run."""
    from icco_torchrl.instructions import LLMPlanner

    live = cfg.live
    checkpoint = _prepare(cfg, "live")
    loop = LiveLoop.from_checkpoint(
        checkpoint,
        planner=LLMPlanner.from_config(cfg.llm),
        device=cfg.device,
        seed=cfg.seed,
        max_robots=live.get("max_robots"),
    )
    server = _live_server(cfg, loop, checkpoint, drive=True)
    stop = _stop_on_signals()

    def started(address):
        print(
            f"icco live: open {_page_url(address, live.get('token'))} ({checkpoint.name} at "
            f"{live.rate_hz:g} Hz, any number of tabs); Ctrl-C stops",
            flush=True,
        )
        _warm_planner()

    server.serve(stop, max_seconds=live.seconds, on_start=started)
    lat = server.stats["latency_ms"]
    print(
        f"icco live: {loop.ticks} ticks, {server.stats['connections']} page connections, "
        f"team robots {', '.join(map(str, loop.team))} of at most {loop.raw.n_agents}, "
        f"median tick {np.median(lat) if lat else float('nan'):.1f} ms; totals of episode "
        f"{loop.episode} so far {_totals(loop)}",
        flush=True,
    )
    return float(loop.ticks)


def _totals(loop: LiveLoop) -> str:
    return ", ".join(
        f"{k} {v:.1f}" if k.endswith("reward") else f"{k} {v:.0f}" for k, v in loop.totals.items()
    )


def _robot_limits(live: DictConfig) -> RobotLimits:
    """The robots' limits of motion from ``live.*``."""
    return RobotLimits(
        max_speed=live.max_speed,
        max_turn=live.max_turn,
        max_accel=live.max_accel,
        max_turn_accel=live.max_turn_accel,
        radius=live.robot_radius,
    )


def _watch_page(cfg: DictConfig, loop: LiveLoop, bridge: Bridge, checkpoint: Path) -> LiveServer:
    """The page showing the bridge's team, started in a thread (the bridge closed if it fails)."""
    page = _live_server(cfg, loop, checkpoint, drive=False)
    try:
        address = page.start_in_thread()
    except OSError:
        bridge.close()
        raise
    page.watch(bridge)
    print(f"icco bridge: watch it at {_page_url(address, cfg.live.get('token'))}", flush=True)
    _warm_planner()
    return page


def _fleet_thread(
    cfg: DictConfig, loop: LiveLoop, bridge: Bridge, limits: RobotLimits, stop: threading.Event
) -> threading.Thread:
    """A thread (not started) running a simulated fleet of the team's robots against ``bridge``."""
    fleet = SimulatedFleet(
        bridge.address,
        n_robots=len(loop.team),  # the checkpoint's team; live.max_robots leaves room
        n_resources=loop.raw.n_resources,
        limits=limits,
        field_size=loop.raw.field_size,
        seed=cfg.seed,
        token=cfg.live.get("token"),
    )
    return threading.Thread(target=fleet.run, args=(stop, cfg.live.seconds or 1e9), daemon=True)


def _serve_bridge(
    bridge: Bridge,
    page: LiveServer | None,
    threads: list[threading.Thread],
    stop: threading.Event,
    seconds: float | None,
) -> None:
    """Serve until stopped or ``seconds`` run out, then stop the threads, bridge and page."""
    for t in threads:
        t.start()
    try:
        bridge.serve(stop, max_seconds=seconds)
    finally:
        stopped = stop.is_set()
        stop.set()
        for t in threads:
            t.join(timeout=5)
        bridge.close()
        if page is not None:
            ran_out = not stopped and seconds is not None
            page.close(reason=f"live.seconds={seconds:g} ran out" if ran_out else None)


def _print_bridge_summary(bridge: Bridge, live: DictConfig) -> None:
    """Print what the bridge did: messages, commands, rate, latency and the team at the end."""
    s = bridge.stats
    latency = np.median(s["latency_ms"]) if s["latency_ms"] else float("nan")
    rate = bridge.mean_rate()
    print(
        f"icco bridge: {s['messages']} messages, {s['commands']} commands, {s['malformed']} "
        f"malformed (refused), {s['stale_stops']} stale-robot stops; "
        f"{'-' if rate is None else f'{rate:.1f}'} Hz actual of {live.rate_hz:g} nominal; "
        f"median state-to-command latency {latency:.1f} ms",
        flush=True,
    )
    team = ", ".join(map(str, bridge.team())) or "none"
    print(
        f"icco bridge: team at the end: robots {team} (at most {bridge.n}); {s['joined']} joined, "
        f"{s['dropped']} left after live.timeout_s={live.timeout_s:g} s, {s['refused_robots']} "
        "refused (team full)",
        flush=True,
    )


def run_bridge(cfg: DictConfig) -> float:
    """``icco bridge``: command robots over UDP until stopped; returns the commands sent."""
    from icco_torchrl.instructions import LLMPlanner

    live = cfg.live
    checkpoint = _prepare(cfg, "bridge")
    limits = _robot_limits(live)
    loop = LiveLoop.from_checkpoint(
        checkpoint,
        planner=LLMPlanner.from_config(cfg.llm),
        device=cfg.device,
        max_robots=live.get("max_robots"),
    )
    bridge = Bridge(
        loop,
        host=live.host,
        port=live.port,
        rate_hz=live.rate_hz,
        timeout=live.timeout_s,
        limits=limits,
        token=live.get("token"),
    )
    page = _watch_page(cfg, loop, bridge, checkpoint) if live.web else None
    stop = _stop_on_signals()
    threads = [_fleet_thread(cfg, loop, bridge, limits, stop)] if live.fleet else []
    source = "with the simulated fleet" if live.fleet else "waiting for state messages"
    print(
        f"icco bridge: listening on udp {bridge.address[0]}:{bridge.address[1]} at "
        f"{live.rate_hz:g} Hz ({source}); Ctrl-C stops",
        flush=True,
    )
    _serve_bridge(bridge, page, threads, stop, live.seconds)
    _print_bridge_summary(bridge, live)
    return float(bridge.stats["commands"])
