"""Where the compiled update's time goes, kernel by kernel: the update with bool masks
(``compiled_mask``, the speed-ups' baseline) against today's (``compiled``), on this CPU.

    .venv/bin/python benchmarks/update_kernels.py                 # one thread, 5 updates
    .venv/bin/python benchmarks/update_kernels.py --out update_kernels_intel.json

Both paths are built as ``train_speed.py`` builds them (its ``Stepper``, the default recipe),
compiled with ``torch._inductor.config.cpp.enable_kernel_profile=True`` so each of Inductor's fused
C++ kernels shows in ``torch.profiler`` under its own name. Per path and update: the wall time
(median of blocks of updates in turn, outside the profiler), the matrix products' time and
GFLOP/s, the fused kernels' time and the largest of them, the other aten ops, and what is left
(the graphs' Python wrappers, guards, sampling the replay). FLOPs are counted once on the eager
path. Writes ``benchmarks/results/<out>`` (default ``update_kernels.json``).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import statistics
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

RESULTS = Path(__file__).resolve().parent / "results"
GEMMS = ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm", "aten::linear")


def train_speed():
    """``train_speed.py`` (a sibling script, not a package)."""
    spec = importlib.util.spec_from_file_location(
        "train_speed", Path(__file__).resolve().parent / "train_speed.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def kernels(stepper, n: int) -> dict[str, tuple[float, float]]:
    """{event: (self ms per update, calls per update)} over ``n`` profiled updates."""
    update, buffer = stepper.run.update, stepper.run.buffer
    samples = [buffer.sample() for _ in range(n)]
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for sample in samples:
            update(sample)
    return {
        e.key: (e.self_cpu_time_total / 1e3 / n, e.count / n)
        for e in prof.key_averages()
        if not e.key.startswith("##") and e.self_cpu_time_total > 0
    }


def summarise(events: dict, ms_update: float, flops: float, top: int) -> dict:
    gemm = sum(ms for key, (ms, _) in events.items() if key in GEMMS)
    fused = {k: v for k, v in events.items() if "cpp_fused" in k}  # graph_<i>_cpp_fused_...
    fused_ms = sum(ms for ms, _ in fused.values())
    aten = sum(ms for k, (ms, _) in events.items() if k.startswith("aten::") and k not in GEMMS)
    largest = sorted(fused.items(), key=lambda kv: -kv[1][0])[:top]
    return {
        "ms_per_update": ms_update,
        "achieved_gflop_s": flops / 1e9 / (ms_update / 1e3),
        "gemm_ms": gemm,
        "gemm_calls": sum(c for k, (_, c) in events.items() if k in GEMMS),
        "gemm_gflop_s": flops / 1e9 / (gemm / 1e3) if gemm else None,
        "fused_kernels": len(fused),
        "fused_ms": fused_ms,
        "other_aten_ms": aten,
        "rest_ms": max(ms_update - gemm - fused_ms - aten, 0.0),
        "largest_fused": [{"kernel": k, "ms": ms, "calls": calls} for k, (ms, calls) in largest],
        "largest_events": [
            {"event": k, "ms": ms, "calls": calls}
            for k, (ms, calls) in sorted(events.items(), key=lambda kv: -kv[1][0])[:top]
        ],
        "relu_mask_kernels_ms": sum(
            ms for k, (ms, _) in fused.items() if "threshold_backward" in k
        ),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--updates", type=int, default=5, help="profiled updates per path")
    parser.add_argument("--top", type=int, default=8, help="largest fused kernels listed")
    parser.add_argument("--method", default="icco")
    parser.add_argument("--run-dir", default="runs/bench_update_kernels")
    parser.add_argument("--out", default="update_kernels.json", help="file in benchmarks/results/")
    args = parser.parse_args(argv)
    if args.threads < 1 or args.updates < 1 or args.top < 0:
        parser.error("--threads and --updates must be at least 1, --top at least 0")
    speed = train_speed()
    torch.set_num_threads(args.threads)
    torch._inductor.config.cpp.enable_kernel_profile = True
    common = ["device=cpu", "experiment=default"]
    run_dir = Path(args.run_dir)
    eager = speed.Stepper([*common, *speed.PATHS["eager"]], args.method, run_dir / "eager")
    flops = eager.flops()
    eager.close()
    paths = (speed.BASELINE, "compiled")
    steppers = {}
    for name in paths:
        with speed.path_context(name):
            steppers[name] = speed.Stepper(
                [*common, *speed.PATHS[name]], args.method, run_dir / name
            )
    ms = {name: [] for name in paths}
    for _ in range(5):  # in turn, so machine load falls on both
        for name in paths:
            with speed.path_context(name):
                ms[name].append(steppers[name].updates(8))
    rows = {}
    for name in paths:
        with speed.path_context(name):
            events = kernels(steppers[name], args.updates)
        rows[name] = summarise(events, statistics.median(ms[name]), flops, args.top)
        steppers[name].close()
        r = rows[name]
        print(
            f"{name}: {r['ms_per_update']:.1f} ms/update ({r['achieved_gflop_s']:.1f} GFLOP/s); "
            f"GEMMs {r['gemm_ms']:.1f} ms ({r['gemm_gflop_s']:.0f} GFLOP/s), "
            f"{r['fused_kernels']} fused kernels {r['fused_ms']:.1f} ms "
            f"(ReLU-mask kernels {r['relu_mask_kernels_ms']:.2f} ms), "
            f"other aten {r['other_aten_ms']:.1f} ms, rest {r['rest_ms']:.1f} ms",
            flush=True,
        )
    payload = {
        "method": args.method,
        "threads": args.threads,
        "updates_profiled": args.updates,
        "gflop_per_update": flops / 1e9,
        "cpu": speed.cpu_name(),
        "isa": speed.isa(),
        "torch": torch.__version__,
        "paths": rows,
        "update_speedup_vs_compiled_mask": rows[paths[0]]["ms_per_update"]
        / rows["compiled"]["ms_per_update"],
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / args.out).write_text(json.dumps(payload, indent=1) + "\n")


if __name__ == "__main__":
    main()
