"""How many browser tabs one live loop serves at 10 Hz (``icco live``'s page over its WebSocket).

    python benchmarks/live_clients.py          # ~2 min; writes benchmarks/results/live_clients.json
    python benchmarks/live_clients.py --counts 1 10 50 --seconds 3

The server (``LiveServer`` driving ICCO's networks at the default sizes, one torch thread) runs in
this process; N WebSocket clients run in a second process (one asyncio loop, as N tabs would be
N renderers), each counting the tick frames it receives. For each N: the loop's achieved tick
rate, tick latency (median, p99) and every client's received frame rate. N tabs are *served* when
the loop keeps >= 95 % of its rate and the slowest client receives >= 95 % of the ticks. A real
tab also draws each frame; that cost is the browser's, not the loop's.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import time
from pathlib import Path

import numpy as np
import torch

from icco_torchrl.live.web import LiveServer

RATE = 10.0


def clients(url: str, n: int, seconds: float, out) -> None:
    import aiohttp

    async def one(session, counts, i):
        async with session.ws_connect(url, max_msg_size=0) as ws:
            end = time.monotonic() + seconds
            async for msg in ws:
                if json.loads(msg.data)["type"] == "tick":
                    counts[i] += 1
                if time.monotonic() > end:
                    break

    async def main():
        counts = [0] * n
        async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(limit=0)) as session:
            await asyncio.gather(*(one(session, counts, i) for i in range(n)))
        out.put([c / seconds for c in counts])

    asyncio.run(main())


def measure(url: str, server: LiveServer, n: int, seconds: float) -> dict:
    out = mp.get_context("spawn").Queue()
    proc = mp.get_context("spawn").Process(target=clients, args=(url, n, seconds, out))
    lat_before, broadcasts_before = len(server.stats["latency_ms"]), server.stats["broadcasts"]
    start = time.monotonic()
    proc.start()
    rates = out.get(timeout=seconds + 120)
    proc.join()
    elapsed = time.monotonic() - start
    lat = np.asarray(server.stats["latency_ms"][lat_before:])
    loop_rate = (server.stats["broadcasts"] - broadcasts_before) / elapsed
    slowest = float(min(rates))
    return {
        "clients": n,
        "loop_hz": round(loop_rate, 2),
        "tick_median_ms": round(float(np.median(lat)), 2),
        "tick_p99_ms": round(float(np.percentile(lat, 99)), 2),
        "client_hz_min": round(slowest, 2),
        "client_hz_median": round(float(np.median(rates)), 2),
        "served": bool(loop_rate >= 0.95 * RATE and slowest >= 0.95 * RATE),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[1, 10, 100, 400, 800, 1600])
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    from benchmarks.live_latency import make_loop

    # Past the default cap on tabs (web.MAX_CLIENTS): this measures the loop, not the cap.
    server = LiveServer(make_loop(), rate_hz=RATE, max_clients=4096)
    host, port = server.start_in_thread()
    url = f"http://{host}:{port}/ws"
    rows = []
    try:
        for n in args.counts:
            rows.append(measure(url, server, n, args.seconds))
            print(json.dumps(rows[-1]), flush=True)
    finally:
        server.close()
    served = [r["clients"] for r in rows if r["served"]]
    result = {
        "rate_hz": RATE,
        "seconds": args.seconds,
        "rows": rows,
        "max_served": max(served) if served else 0,
    }
    path = Path(__file__).with_name("results") / "live_clients.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(
        f"one live loop at {RATE:g} Hz served up to {result['max_served']} WebSocket clients; "
        f"wrote {path}"
    )


if __name__ == "__main__":
    main()
