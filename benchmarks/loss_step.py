"""Milliseconds per ICCOLoss update: forward + backward + RMSprop step on 512 segments of T=4 steps.

Segments come from a real rollout of the env with the ICCO policy; each method is timed side
by side in one process with an explicit thread count. Writes ``benchmarks/results/loss_step.json``.

    python benchmarks/loss_step.py --threads 1 --batch 512
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from icco_torchrl import methods
from icco_torchrl.objectives import total_loss
from icco_torchrl.training.build import build, compose_config


def time_updates(method: str, batch: int, steps: int, runs: int, device: str) -> dict:
    run = build(compose_config([f"method={method}", "seed=0", f"device={device}"]), num_envs=64)
    env, policy, loss = run.env, run.policy, run.loss
    with torch.no_grad():
        data = env.rollout(40, policy, break_when_any_done=False)
    segs = run.cutter(data)
    idx = torch.randint(0, segs.shape[0], (batch,))
    sample = segs[idx].contiguous()
    optim = torch.optim.RMSprop(loss.parameters(), lr=3e-4, alpha=0.99, eps=1e-5, foreach=True)

    def update():
        out = loss(sample)
        optim.zero_grad(set_to_none=True)
        total_loss(out).backward()
        torch.nn.utils.clip_grad_norm_(loss.parameters(), 10.0)
        optim.step()

    for _ in range(3):
        update()
    times = []
    for _ in range(runs):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        for _ in range(steps):
            update()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        times.append(1000 * (time.perf_counter() - t0) / steps)
    return {
        "method": method,
        "device": device,
        "batch_segments": batch,
        "segment_len": int(sample.shape[1]),
        "ms_per_update": statistics.median(times),
        "runs_ms": times,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batch", type=int, default=512)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--methods", nargs="+", default=list(methods.names()))
    parser.add_argument("--out", default="benchmarks/results/loss_step.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    rows = [time_updates(m, args.batch, args.steps, args.runs, args.device) for m in args.methods]
    print(f"{'method':<12} {'device':<6} {'batch':>6} {'ms/update':>10}")
    for r in rows:
        print(
            f"{r['method']:<12} {r['device']:<6} {r['batch_segments']:>6} "
            f"{r['ms_per_update']:>10.1f}"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps({"threads": args.threads, "torch": torch.__version__, "results": rows}, indent=2)
    )


if __name__ == "__main__":
    main()
