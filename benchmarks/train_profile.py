"""Where a training batch's time goes, for ICCO's recipes: collection (env and policy), cutting
items, replay writes and samples, loss forward and backward, the optimiser step (clip, Adam,
target copy) and the per-batch metrics read-back, as milliseconds per collected frame.

    python benchmarks/train_profile.py --batches 40

Each recipe (``train_throughput.py``'s ``RECIPES``) is built with a filled buffer, then the
recipes run one collector batch each in turn (round-robin, one torch thread), so the machine's
noise falls on all of them alike. Writes ``benchmarks/results/train_profile.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch
from torchrl.collectors import Collector

from icco_torchrl.objectives import total_loss
from icco_torchrl.training.build import build
from icco_torchrl.training.config import compose_config

RESULTS = Path(__file__).resolve().parent / "results"
PHASES = ("collect", "cut", "extend", "sample", "forward", "backward", "optimiser", "metrics")


def recipes() -> dict[str, list[str]]:
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "train_throughput", Path(__file__).resolve().parent / "train_throughput.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.RECIPES


class Profiled:
    """One recipe's run: its collector and buffer, stepped a batch at a time."""

    def __init__(self, overrides: list[str]):
        torch.manual_seed(0)
        cfg = compose_config(["method=icco", *overrides, "train.checkpoint_buffer=false"])
        self.cfg, self.run = cfg, build(cfg, for_training=True)
        frames = cfg.env.num_envs * cfg.train.steps_per_batch
        self.collector = Collector(
            self.run.env,
            self.run.policy,
            frames_per_batch=frames,
            total_frames=-1,
            auto_register_policy_transforms=False,
            track_traj_ids=False,
        )
        self.batches = iter(self.collector)
        self.frames = frames
        while len(self.run.buffer) < 4 * cfg.train.batch_segments:  # fill before measuring
            self.step({})

    def step(self, times: dict) -> None:
        run, t = self.run, self.cfg.train
        clock = time.perf_counter
        tick = clock()
        batch = next(self.batches)
        marks = [("collect", clock())]
        items = run.cutter(batch.select(*run.loss.in_keys, strict=False))
        marks.append(("cut", clock()))
        if items.shape[0]:
            run.buffer.extend(items)
        marks.append(("extend", clock()))
        if len(run.buffer) >= t.batch_segments:
            for _ in range(t.updates_per_batch):
                sample = run.buffer.sample()
                marks.append(("sample", clock()))
                losses = run.loss(sample)
                marks.append(("forward", clock()))
                run.optim.zero_grad(set_to_none=True)
                total_loss(losses).backward()
                marks.append(("backward", clock()))
                torch.nn.utils.clip_grad_norm_(run.loss.parameters(), t.grad_clip)
                run.optim.step()
                run.updater.step()
                marks.append(("optimiser", clock()))
            {k: v.item() for k, v in losses.items()}
            marks.append(("metrics", clock()))
        for name, stamp in marks:
            times.setdefault(name, 0.0)
            times[name] += stamp - tick
            tick = stamp


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", type=int, default=40, help="collector batches per recipe")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    runs = {name: Profiled(overrides) for name, overrides in recipes().items()}
    per_batch = {name: [] for name in runs}
    for _ in range(args.batches):
        for name, run in runs.items():
            times = {}
            run.step(times)
            per_batch[name].append(times)
    rows = []
    for name, batches in per_batch.items():
        frames = runs[name].frames
        ms = {p: 1e3 * statistics.median(b.get(p, 0.0) for b in batches) / frames for p in PHASES}
        rows.append({"recipe": name, "ms_per_frame": ms, "total_ms_per_frame": sum(ms.values())})
        shares = ", ".join(f"{p} {v / sum(ms.values()):.0%}" for p, v in ms.items())
        print(f"{name:<24} {sum(ms.values()):.3f} ms/frame  ({shares})")
    base = rows[0]["total_ms_per_frame"]
    for row in rows:
        row["speedup_vs_first"] = base / row["total_ms_per_frame"]
    RESULTS.mkdir(parents=True, exist_ok=True)
    payload = {"threads": args.threads, "batches": args.batches, "results": rows}
    (RESULTS / "train_profile.json").write_text(json.dumps(payload, indent=1) + "\n")
    for run in runs.values():
        run.collector.shutdown()


if __name__ == "__main__":
    main()
