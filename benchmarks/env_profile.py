"""Time and profile ``ResourceCollectionEnv`` through its public API, single-threaded.

The loop is the one a collector runs::

    td = env.reset()
    loop: td["agents", "action"] = torch.randint(0, 5, (B, N)); _, td = env.step_and_maybe_reset(td)

Usage::

    python benchmarks/env_profile.py                          # ms/step and env-steps/s
    python benchmarks/env_profile.py --baseline old_env.py    # old vs current, interleaved
    python benchmarks/env_profile.py --profile --sizes 4096   # torch.profiler top ops

The machine may be shared and noisy, so variants are timed in alternating rounds in one
process; each line gives the median round (wall clock and this thread's CPU time) and the
fastest round's CPU time, the closest to an idle machine.
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import time

import torch


def _load_env_class(path: str | None):
    if path is None:
        from icco_torchrl.envs.resource_collection import ResourceCollectionEnv

        return ResourceCollectionEnv
    spec = importlib.util.spec_from_file_location("_baseline_env", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["_baseline_env"] = module
    spec.loader.exec_module(module)
    return module.ResourceCollectionEnv


class _Runner:
    """One env plus its rollout state, so rounds of different variants can alternate."""

    def __init__(self, env_cls, num_envs: int, **kwargs):
        self.env = env_cls(num_envs=num_envs, seed=0, **kwargs)
        self.shape = (num_envs, self.env.n_agents)
        self.gen = torch.Generator().manual_seed(0)
        self.td = self.env.reset()

    def run(self, steps: int) -> tuple[float, float]:
        """Seconds per step: wall clock and this thread's CPU time (less hurt by a busy machine)."""
        env, td, shape, gen = self.env, self.td, self.shape, self.gen
        start, start_cpu = time.perf_counter(), time.thread_time()
        for _ in range(steps):
            td["agents", "action"] = torch.randint(0, 5, shape, generator=gen)
            _, td = env.step_and_maybe_reset(td)
        elapsed, elapsed_cpu = time.perf_counter() - start, time.thread_time() - start_cpu
        self.td = td
        return elapsed / steps, elapsed_cpu / steps


def bench(variants: dict, sizes, steps: int, rounds: int) -> None:
    for num_envs in sizes:
        start = time.perf_counter()
        runners = {name: _Runner(cls, num_envs, **kw) for name, (cls, kw) in variants.items()}
        setup = time.perf_counter() - start
        for runner in runners.values():
            runner.run(max(3, steps // 10))  # warm-up (and compilation where enabled)
        times = {name: [] for name in runners}
        for _ in range(rounds):
            for name, runner in runners.items():
                times[name].append(runner.run(steps))
        line = [f"num_envs={num_envs:6d}"]
        for name, ts in times.items():
            ms = statistics.median(t for t, _ in ts) * 1e3
            cpu = statistics.median(c for _, c in ts) * 1e3
            best = min(c for _, c in ts) * 1e3
            line.append(
                f"{name}: {ms:7.3f} ms/step (cpu {cpu:7.3f}, best {best:7.3f}) "
                f"{num_envs / ms * 1e3 / 1e6:6.3f} M env-steps/s (best "
                f"{num_envs / best * 1e3 / 1e6:5.3f})"
            )
        print(" | ".join(line) + f"  (setup {setup:.1f}s)", flush=True)


def profile(env_cls, num_envs: int, steps: int, rows: int) -> None:
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    runner = _Runner(env_cls, num_envs)
    runner.run(steps)
    with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
        runner.run(steps)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096, 16384])
    parser.add_argument("--steps", type=int, default=20, help="steps per timed round")
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument(
        "--baseline", default=None, help="path of another resource_collection.py to compare"
    )
    parser.add_argument(
        "--profile", action="store_true", help="print torch.profiler's top ops instead"
    )
    parser.add_argument("--rows", type=int, default=30)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    current = _load_env_class(None)
    if args.profile:
        for n in args.sizes:
            print(f"== num_envs={n}")
            profile(current, n, args.steps, args.rows)
        return
    variants = {}
    if args.baseline:
        variants["baseline"] = (_load_env_class(args.baseline), {})
    variants["current"] = (current, {})
    bench(variants, args.sizes, args.steps, args.rounds)


if __name__ == "__main__":
    main()
