"""Env throughput: the batched TorchRL env against the PettingZoo view stepped in Python.

Measures env-steps/s (one step of one env) and agent-steps/s (times the robots) through
the public API: ``env.step_and_maybe_reset`` with random actions from ``torch.randint``
(``action_spec.rand()`` would dominate small batches). Each configuration is warmed up,
then timed over ``--runs`` runs of N steps, N chosen so a run lasts ~``--run-seconds``;
the median run is reported. The PettingZoo view (one env, numpy actions, a Python loop)
is the baseline of the speedup column, as a user of that API would step it.

    python benchmarks/env_throughput.py --sizes 1 64 1024 --threads 1
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import numpy as np
import torch

from icco_torchrl.envs import N_ACTIONS, ResourceCollectionEnv, parallel_env

DEFAULT_SIZES = (1, 64, 1024, 4096, 16384)
DEFAULT_OUT = os.path.join(os.path.dirname(__file__), "results", "env_throughput.json")


def _median_rate(run, runs: int, run_seconds: float, sync=lambda: None) -> float:
    """Median steps/s of ``runs`` timed calls of ``run(n)``, n calibrated to ``run_seconds``."""
    n = 2
    while True:  # warm-up doubles as calibration
        sync()
        t0 = time.perf_counter()
        run(n)
        sync()
        elapsed = time.perf_counter() - t0
        if elapsed >= run_seconds / 4:
            break
        n *= 2
    n = max(1, int(n * run_seconds / elapsed))
    rates = []
    for _ in range(runs):
        sync()
        t0 = time.perf_counter()
        run(n)
        sync()
        rates.append(n / (time.perf_counter() - t0))
    return statistics.median(rates)


def bench_batched(num_envs: int, device: str, runs: int, run_seconds: float) -> float:
    """Env-steps/s of ``ResourceCollectionEnv`` with ``num_envs`` envs on ``device``."""
    env = ResourceCollectionEnv(num_envs=num_envs, device=device, seed=0)
    td = env.reset()
    shape = (num_envs, env.n_agents)

    def run(n: int) -> None:
        nonlocal td
        for _ in range(n):
            td.set(("agents", "action"), torch.randint(0, N_ACTIONS, shape, device=device))
            _, td = env.step_and_maybe_reset(td)

    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    return num_envs * _median_rate(run, runs, run_seconds, sync)


def bench_pettingzoo(runs: int, run_seconds: float) -> float:
    """Steps/s of the PettingZoo view (one env) in a plain Python loop, resetting when done."""
    env = parallel_env(seed=0)
    env.reset()
    rng = np.random.default_rng(0)

    def run(n: int) -> None:
        for _ in range(n):
            if not env.agents:
                env.reset()
            env.step({a: int(rng.integers(N_ACTIONS)) for a in env.agents})

    return _median_rate(run, runs, run_seconds)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--sizes", type=int, nargs="+", default=list(DEFAULT_SIZES), help="num_envs values"
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument(
        "--runs", type=int, default=5, help="timed runs per configuration (median reported)"
    )
    parser.add_argument(
        "--run-seconds", type=float, default=0.5, help="target duration of one timed run"
    )
    parser.add_argument(
        "--device",
        nargs="+",
        default=None,
        help="devices to time (default: cpu, plus cuda when available)",
    )
    parser.add_argument("--out", default=DEFAULT_OUT, help="JSON results path")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    devices = args.device or (["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    on_cuda = any(d.startswith("cuda") for d in devices)

    pz_rate = bench_pettingzoo(args.runs, args.run_seconds)
    n_agents = ResourceCollectionEnv().n_agents
    rows = [
        dict(
            api="pettingzoo",
            num_envs=1,
            device="cpu",
            env_steps_per_s=pz_rate,
            agent_steps_per_s=pz_rate * n_agents,
            speedup_vs_pettingzoo=1.0,
        )
    ]
    for device in devices:
        for size in args.sizes:
            rate = bench_batched(size, device, args.runs, args.run_seconds)
            rows.append(
                dict(
                    api="torchrl",
                    num_envs=size,
                    device=device,
                    env_steps_per_s=rate,
                    agent_steps_per_s=rate * n_agents,
                    speedup_vs_pettingzoo=rate / pz_rate,
                )
            )

    print(
        f"{'api':<11}{'num_envs':>9} "
        f"{'device':<7}{'env-steps/s':>14}{'agent-steps/s':>15}{'speedup':>10}"
    )
    for r in rows:
        print(
            f"{r['api']:<11}{r['num_envs']:>9} {r['device']:<7}{r['env_steps_per_s']:>14,.0f}"
            f"{r['agent_steps_per_s']:>15,.0f}{r['speedup_vs_pettingzoo']:>9.1f}x"
        )

    result = dict(
        benchmark="env_throughput",
        threads=args.threads,
        runs=args.runs,
        run_seconds=args.run_seconds,
        torch=torch.__version__,
        python=platform.python_version(),
        machine=platform.machine(),
        processor=platform.processor() or None,
        cpu_count=os.cpu_count(),
        cuda_device=torch.cuda.get_device_name() if on_cuda else None,
        time=time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        rows=rows,
    )
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=2)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
