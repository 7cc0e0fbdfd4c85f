"""ICCO's training speed, today's eager update against the compiled one, side by side in one run.

For each thread count, both paths are built at the same recipe (the defaults: 32 envs x 16
steps a batch, 8 updates of 32 x 16 transitions, a replay ratio of 8) and stepped a collector
batch at a time in turn (eager, compiled, eager, ...), so load on the machine falls on both
alike. Measured per path: env steps per second end to end (collect, cut, store, learn), ms per
update (blocks of updates in turn), ops per update (torch.profiler), FLOPs per update
(``torch.utils.flop_counter``) and the achieved GFLOP/s, beside this core's GEMM rate at the
update's shapes. Writes ``benchmarks/results/train_speed.json``.

    .venv/bin/python benchmarks/train_speed.py                  # 1 and 2 threads, ICCO
    .venv/bin/python benchmarks/train_speed.py --threads 1 --batches 20
    .venv/bin/python benchmarks/train_speed.py --threads 1 --paths eager compiled process
    python benchmarks/train_speed.py --device cuda --experiment gpu --paths eager compiled \
        graphs --threads 8 --out train_speed_gpu.json            # benchmarks/gpu_check.sh
"""

from __future__ import annotations

import argparse
import contextlib
import json
import platform
import statistics
import time
from pathlib import Path
from unittest import mock

import torch
from torch.profiler import ProfilerActivity, profile
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_map
from torch.utils.flop_counter import flop_registry

from icco_torchrl.modules import activations
from icco_torchrl.trainer import TrainingRun
from icco_torchrl.training.build import build
from icco_torchrl.training.collector_process import make_collector
from icco_torchrl.training.config import compose_config

RESULTS = Path(__file__).resolve().parent / "results"
PATHS = {
    "eager": ["train.compile=false", "train.cudagraphs=false"],
    # The compiled update as it was before modules/activations.py: ReLUs saving a bool mask for
    # their backward (see MaskReLU), kept here as the baseline of the speed-ups.
    "compiled_mask": ["train.compile=true", "train.cudagraphs=false"],
    "compiled": ["train.compile=true", "train.cudagraphs=false"],
    "graphs": ["train.compile=true", "train.cudagraphs=true"],  # CUDA only
    # The compiled update, the env and the acting policy in a collector process beside it
    # (train.collector=process): it collects its next batch while the other paths take their turn,
    # as it would during the learner's own updates. Two cores, the CPU only.
    "process": ["train.compile=true", "train.cudagraphs=false", "train.collector=process"],
}
BASELINE = "compiled_mask"


class MaskReLU:
    """Stands in for ``activations.SignReLU`` on the ``compiled_mask`` path: ``torch.relu``,
    whose compiled backward stores the bool mask ``x <= 0``."""

    apply = staticmethod(torch.relu)


def path_context(name: str):
    """The context every call of a path runs in (Dynamo guards on the patched global, so each
    path keeps its own graph)."""
    if name == "compiled_mask":
        return mock.patch.object(activations, "SignReLU", MaskReLU)
    return contextlib.nullcontext()


# The update's matrix products: [S*(L+1)*N, hidden] rows against the hidden and gate widths.
GEMM_SHAPES = ((1632, 64, 64), (1632, 64, 192), (4096, 256, 256))


class FlopCount(TorchDispatchMode):
    """FLOPs of every op with a formula in torch's ``flop_registry`` (matrix products,
    convolutions), counted at dispatch (``FlopCounterMode``'s module tracker trips on
    TensorDictModules)."""

    total = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        formula = flop_registry.get(func._overloadpacket)
        if formula is not None:
            shape = lambda x: x.shape if isinstance(x, torch.Tensor) else x  # noqa: E731
            self.total += formula(
                *tree_map(shape, args), **tree_map(shape, kwargs), out_val=tree_map(shape, out)
            )
        return out


class Stepper:
    """One path's training run, stepped a collector batch at a time through the trainer's own
    ``learn()`` (the loop's body without its logging)."""

    def __init__(self, overrides: list[str], method: str, run_dir: Path):
        torch.manual_seed(0)
        cfg = compose_config([f"method={method}", *overrides])
        self.cfg = cfg
        self.training = TrainingRun(build(cfg, for_training=True), cfg, run_dir)
        self.run = self.training.run
        self.frames = cfg.env.num_envs * cfg.train.steps_per_batch
        # The trainer's collector (train.collector), endless.
        self.collector = make_collector(self.run, cfg, -1, frames=0, epsilon=None)
        self.batches = iter(self.collector)
        t = cfg.train
        start = time.perf_counter()
        while len(self.run.buffer) < max(t.warmup_segments, t.batch_segments):
            self.step()
        self.step()  # the first update (a compile, on the compiled path)
        self.first_update_s = time.perf_counter() - start

    def step(self) -> float:
        """One batch end to end; its seconds."""
        start = time.perf_counter()
        batch = next(self.batches)
        items = self.run.cutter(batch.select(*self.run.loss.in_keys, strict=False))
        if items.shape[0]:
            self.run.buffer.extend(items)
        self.training.learn()
        return time.perf_counter() - start

    def updates(self, n: int) -> float:
        """ms per update over ``n`` updates on replayed batches."""
        update, buffer = self.run.update, self.run.buffer
        start = time.perf_counter()
        for _ in range(n):
            metrics = update(buffer.sample())
        metrics["loss_td"].item()  # waits for the device
        return 1e3 * (time.perf_counter() - start) / n

    def ops(self) -> int:
        """Ops one update dispatches (torch.profiler's events, its own markers left out)."""
        sample = self.run.buffer.sample()
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            self.run.update(sample)
        return sum(e.count for e in prof.key_averages() if not e.key.startswith("##"))

    def flops(self) -> float:
        """FLOPs of one update, counted on the eager path (the compiled one does the same)."""
        with FlopCount() as counter:
            self.run.update(self.run.buffer.sample())
        return counter.total

    def close(self) -> None:
        self.collector.shutdown()


def gemm_rate(threads: int) -> dict[str, float]:
    """GFLOP/s of plain matrix products on this core at ``threads``."""
    torch.set_num_threads(threads)
    out = {}
    for m, k, n in GEMM_SHAPES:
        a, b = torch.randn(m, k), torch.randn(k, n)
        for _ in range(5):
            a @ b
        reps = max(5, int(1e9 / (2 * m * k * n)))
        start = time.perf_counter()
        for _ in range(reps):
            a @ b
        out[f"{m}x{k}x{n}"] = 2 * m * k * n * reps / (time.perf_counter() - start) / 1e9
    return out


def measure(threads: int, batches: int, method: str, run_dir: Path, paths, common) -> dict:
    torch.set_num_threads(threads)
    steppers = {}
    for name in paths:
        with path_context(name):
            steppers[name] = Stepper([*common, *PATHS[name]], method, run_dir / name)
    seconds = {name: [] for name in steppers}
    for _ in range(batches):  # in turn, so every path sees the same load
        for name, stepper in steppers.items():
            with path_context(name):
                seconds[name].append(stepper.step())
    ms = {name: [] for name in steppers}
    for _ in range(5):
        for name, stepper in steppers.items():
            with path_context(name):
                ms[name].append(stepper.updates(8))
    rows, flops = {}, steppers["eager"].flops()
    for name, stepper in steppers.items():
        with path_context(name):
            ops = stepper.ops()
        ms_update = statistics.median(ms[name])
        rows[name] = {
            "env_steps_per_s": stepper.frames / statistics.median(seconds[name]),
            "ms_per_update": ms_update,
            "ops_per_update": ops,
            "gflop_per_update": flops / 1e9,
            "achieved_gflop_s": flops / 1e9 / (ms_update / 1e3),
            "first_update_s": stepper.first_update_s,
        }
        stepper.close()
    base, fast = rows["eager"], rows[paths[-1]]
    before = rows.get(BASELINE)
    return {
        "threads": threads,
        "paths": rows,
        "fastest": paths[-1],
        "update_speedup": base["ms_per_update"] / fast["ms_per_update"],
        "end_to_end_speedup": fast["env_steps_per_s"] / base["env_steps_per_s"],
        "update_speedup_vs_compiled": (
            before["ms_per_update"] / fast["ms_per_update"] if before else None
        ),
        "end_to_end_speedup_vs_compiled": (
            fast["env_steps_per_s"] / before["env_steps_per_s"] if before else None
        ),
        "gemm_gflop_s": gemm_rate(threads) if "cpu" in common[0] else None,
    }


def cpu_name() -> str:
    for line in (
        Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").exists() else []
    ):
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def isa() -> dict:
    """The vector ISA torch's kernels use here, and the matrix units bf16 would need."""
    caps = torch.cpu.get_capabilities() if hasattr(torch.cpu, "get_capabilities") else {}
    return {
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        **{k: bool(caps.get(k)) for k in ("avx512_bf16", "amx_bf16", "amx_tile")},
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--batches", type=int, default=30, help="collector batches per path")
    parser.add_argument("--method", default="icco")
    parser.add_argument("--run-dir", default="runs/bench_train_speed")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--experiment", default="default", help="the recipe (conf/experiment/)")
    parser.add_argument(
        "--paths", nargs="+", default=["eager", BASELINE, "compiled"], choices=list(PATHS)
    )
    parser.add_argument("--out", default="train_speed.json", help="file in benchmarks/results/")
    args = parser.parse_args(argv)
    common = [f"device={args.device}", f"experiment={args.experiment}"]
    results = []
    for threads in args.threads:
        row = measure(threads, args.batches, args.method, Path(args.run_dir), args.paths, common)
        results.append(row)
        p, fast = row["paths"], row["fastest"]
        print(
            f"{threads} thread(s): update {p['eager']['ms_per_update']:.1f} -> "
            f"{p[fast]['ms_per_update']:.1f} ms ({row['update_speedup']:.2f}x), end to end "
            f"{p['eager']['env_steps_per_s']:.0f} -> {p[fast]['env_steps_per_s']:.0f} "
            f"env steps/s ({row['end_to_end_speedup']:.2f}x); ops/update "
            f"{p['eager']['ops_per_update']} -> {p[fast]['ops_per_update']} ({fast})",
            flush=True,
        )
    cfg = compose_config([f"method={args.method}", *common])
    t = cfg.train
    ratio = t.updates_per_batch * t.batch_segments * t.sequence_length
    ratio /= cfg.env.num_envs * t.steps_per_batch
    payload = {
        "method": args.method,
        "experiment": args.experiment,
        "device": args.device,
        "recipe": (
            f"{cfg.env.num_envs} envs x {t.steps_per_batch} steps a batch, {t.updates_per_batch} "
            f"updates of {t.batch_segments} x {t.sequence_length}, replay ratio "
            f"{ratio:g}"
        ),
        "cpu": cpu_name(),
        "isa": isa(),
        "torch": torch.__version__,
        "results": results,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / args.out).write_text(json.dumps(payload, indent=1) + "\n")


if __name__ == "__main__":
    main()
