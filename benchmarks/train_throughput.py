"""End-to-end training SPS (env steps per second, learning included) and peak RSS.

Two suites, each run side by side (round-robin, one subprocess per run, median reported):

``--suite recipes`` (ICCO's training recipes at the reproduction's replay ratio: 8 replayed
transitions per collected one, 512 transitions per update or the same total per batch):

- ``icco_4step``: the recipe before sequence replay (4-step items, 128 per update, 8 updates per
  collector batch of 32 envs x 16 steps, one-step targets);
- ``icco_seq16``: 16-step items, 32 per update, 8 updates, lambda 0.6;
- ``icco_seq16_wide``: 16-step items, 128 per update, 2 updates (fewer, larger updates);
- ``icco_seq16_xwide``: 16-step items, 256 per update, 1 update (pymarl2's shape: one large
  update per rollout);
- ``icco_seq16_wide_envs64``: ``icco_seq16_wide`` with 64 envs per collector batch, 4 updates.

``--suite reference`` (same frame budget, collector batch, updates per batch and transitions per
update):

- ``icco`` and ``qmix``: this project's pipeline (``icco train``'s loop, recurrent agents);
- ``torchrl_qmix``: TorchRL's reference QMIX recipe, ``sota-implementations/multiagent/qmix_vdn.py``
  as written (env wrapped with ``RewardSum``; feed-forward ``MultiAgentMLP``, depth 2, 256 cells,
  Tanh, shared parameters + ``QMixer`` (embed 32) + ``QMixerLoss`` (TD(0)) + ``SoftUpdate``
  (tau 0.005) + Adam + ``Collector``) on our env, with our budget;
- ``torchrl_qmix_w64``: the same recipe with 64 cells, the width of our networks.

Writes ``benchmarks/results/train_throughput_recipes.json`` or ``train_throughput.json``.

    python benchmarks/train_throughput.py --suite recipes --frames 60000 --repeats 3
    python benchmarks/train_throughput.py --frames 30000 --threads 1 --repeats 5
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

SUPERVISOR_ARGS = ("config", "configs", "out", "repeats", "suite")
# As measured: no shaping (the default since), so every recipe costs the same per env step.
SEQ16 = [
    "train.sequence_length=16",
    "train.buffer_segments=5000",
    "train.td_lambda=0.6",
    "train.shaping.potentials=[]",
]
RECIPES = {  # name: overrides (each sets its own batch shape; the replay ratio is 8 for all)
    "icco_4step": [
        "train.sequence_length=4",
        "train.batch_segments=128",
        "train.updates_per_batch=8",
        "train.buffer_segments=20000",
        "train.td_lambda=0",
        "train.shaping.potentials=[]",
    ],
    "icco_seq16": [*SEQ16, "train.batch_segments=32", "train.updates_per_batch=8"],
    "icco_seq16_wide": [*SEQ16, "train.batch_segments=128", "train.updates_per_batch=2"],
    "icco_seq16_xwide": [*SEQ16, "train.batch_segments=256", "train.updates_per_batch=1"],
    "icco_seq16_wide_envs64": [
        *SEQ16,
        "env.num_envs=64",
        "train.batch_segments=128",
        "train.updates_per_batch=4",
    ],
}
SUITES = {
    "recipes": list(RECIPES),
    "reference": ["qmix", "torchrl_qmix", "torchrl_qmix_w64", "icco"],
}


def run_ours(method: str, args) -> dict:
    from icco_torchrl.trainer import train
    from icco_torchrl.training.build import compose_config

    if method in RECIPES:  # a recipe sets its own batch shape
        shape = ["method=icco", f"env.num_envs={args.num_envs}", *RECIPES[method]]
    else:
        shape = [
            f"method={method}",
            f"env.num_envs={args.num_envs}",
            f"train.updates_per_batch={args.updates}",
            f"train.batch_segments={args.batch_segments}",
            "train.sequence_length=4",
        ]
    cfg = compose_config(
        [
            *shape,
            f"device={args.device}",
            f"train.total_frames={args.frames}",
            f"train.steps_per_batch={args.steps_per_batch}",
            "train.warmup_segments=0",
            "train.eval_interval=0",
            "train.checkpoint_interval=0",
            f"train.threads={args.threads}",
            "logger.progress=false",
            "train.eval_envs=2",
            "train.checkpoint_buffer=false",
        ]
    )
    with tempfile.TemporaryDirectory() as run_dir:
        train(cfg, run_dir)
        header, *rows = (Path(run_dir) / "timing.csv").read_text().strip().splitlines()
        last = dict(zip(header.split(","), rows[-1].split(",")))
    wall = int(last["frames"]) / float(last["sps"])
    return {
        "sps": float(last["sps"]),
        "frames": int(last["frames"]),
        "train_share": float(last["time_train"]) / wall,
    }


def run_reference(args, num_cells: int) -> dict:
    """TorchRL's multi-agent QMIX example (model, loss, target update, optimiser) on our env and
    budget."""
    from tensordict.nn import TensorDictModule
    from torchrl.collectors import Collector
    from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer
    from torchrl.envs import RewardSum, TransformedEnv
    from torchrl.modules import EGreedyModule, MultiAgentMLP, QMixer, QValueModule, SafeSequential
    from torchrl.objectives import QMixerLoss, SoftUpdate, ValueEstimators

    from icco_torchrl.envs import ResourceCollectionEnv

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    device = torch.device(args.device)
    # As in the example: the env wrapped with RewardSum (episode reward per robot, for logging).
    env = TransformedEnv(
        ResourceCollectionEnv(num_envs=args.num_envs, device=device, seed=0),
        RewardSum(in_keys=[("agents", "reward")], out_keys=[("agents", "episode_reward")]),
    )
    L = env.base_env.layout
    net = TensorDictModule(
        MultiAgentMLP(
            L.obs_dim,
            5,
            L.n_agents,
            centralized=False,
            share_params=True,
            depth=2,
            num_cells=num_cells,
            activation_class=torch.nn.Tanh,
            device=device,
        ),
        in_keys=[("agents", "observation")],
        out_keys=[("agents", "action_value")],
    )
    qnet = SafeSequential(
        net,
        QValueModule(
            action_value_key=("agents", "action_value"),
            out_keys=[
                ("agents", "action"),
                ("agents", "action_value"),
                ("agents", "chosen_action_value"),
            ],
            spec=env.full_action_spec_unbatched,
            action_space=None,
        ),
    )
    explore = EGreedyModule(
        spec=env.full_action_spec_unbatched,
        eps_init=1.0,
        eps_end=0.05,
        annealing_num_steps=args.frames,
        action_key=("agents", "action"),
    )
    policy = SafeSequential(qnet, explore)
    mixer = TensorDictModule(
        QMixer(state_shape=(L.state_dim,), mixing_embed_dim=32, n_agents=L.n_agents, device=device),
        in_keys=[("agents", "chosen_action_value"), "state"],
        out_keys=["chosen_action_value"],
    )
    loss = QMixerLoss(qnet, mixer, delay_value=True, action_space="categorical")
    loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99)
    updater = SoftUpdate(loss, eps=1 - 0.005)
    optim = torch.optim.Adam(loss.parameters(), lr=5e-5)
    frames_per_batch = args.num_envs * args.steps_per_batch
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(args.frames, device=device),
        sampler=RandomSampler(),
        batch_size=args.batch_segments * 4,
    )
    collector = Collector(
        env,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=args.frames,
        device=device,
        storing_device=device,
        auto_register_policy_transforms=False,
    )
    start, frames, train_time = time.perf_counter(), 0, 0.0
    for batch in collector:
        tick = time.perf_counter()
        frames += batch.numel()
        buffer.extend(batch.reshape(-1))
        for _ in range(args.updates):
            out = loss(buffer.sample())
            optim.zero_grad()
            out["loss"].backward()
            torch.nn.utils.clip_grad_norm_(loss.parameters(), 40.0)
            optim.step()
            updater.step()
        explore.step(batch.numel())
        train_time += time.perf_counter() - tick
    collector.shutdown()
    wall = time.perf_counter() - start
    return {"sps": frames / wall, "frames": frames, "train_share": train_time / wall}


def child(args) -> None:
    torch.set_num_threads(args.threads)
    if args.config.startswith("torchrl_qmix"):
        result = run_reference(args, num_cells=64 if args.config.endswith("_w64") else 256)
    else:
        result = run_ours(args.config, args)
    result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print("RESULT " + json.dumps(result))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60_000)
    parser.add_argument("--num-envs", type=int, default=32)
    parser.add_argument("--steps-per-batch", type=int, default=16)
    parser.add_argument(
        "--updates", type=int, default=2, help="gradient updates per collector batch"
    )
    parser.add_argument(
        "--batch-segments", type=int, default=128, help="segments of 4 steps per update"
    )
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--suite", choices=list(SUITES), default="reference")
    parser.add_argument("--configs", nargs="+", help="default: the suite's configs")
    parser.add_argument(
        "--repeats", type=int, default=3, help="round-robin runs per config (median reported)"
    )
    parser.add_argument("--out", help="default: benchmarks/results/train_throughput[_recipes].json")
    parser.add_argument("--config", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.config:
        return child(args)
    args.configs = args.configs or SUITES[args.suite]
    suffix = "_recipes" if args.suite == "recipes" else ""
    args.out = args.out or f"benchmarks/results/train_throughput{suffix}.json"
    runs = {config: [] for config in args.configs}
    for repeat in range(args.repeats):
        for config in args.configs:
            cmd = [sys.executable, __file__, "--config", config] + [
                f"--{k.replace('_', '-')}={v}"
                for k, v in vars(args).items()
                if k not in SUPERVISOR_ARGS
            ]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            line = next((x for x in proc.stdout.splitlines() if x.startswith("RESULT ")), None)
            if line is None:
                raise RuntimeError(f"{config} failed:\n{proc.stderr[-3000:]}")
            runs[config].append(json.loads(line[7:]))
            print(
                f"[{repeat + 1}/{args.repeats}] {config}: {runs[config][-1]['sps']:.0f} SPS",
                flush=True,
            )
    rows = [
        {
            "config": config,
            "sps": statistics.median(r["sps"] for r in results),
            "sps_runs": [round(r["sps"]) for r in results],
            "frames": results[0]["frames"],
            "train_share": statistics.median(r["train_share"] for r in results),
            "peak_rss_mb": max(r["peak_rss_mb"] for r in results),
        }
        for config, results in runs.items()
    ]
    baseline = "icco_4step" if args.suite == "recipes" else "torchrl_qmix"
    ref = next((r["sps"] for r in rows if r["config"] == baseline), None)
    print(f"{'config':<24} {'median SPS':>10} {'vs ' + baseline:>18} {'training share':>15}  runs")
    for r in rows:
        r["baseline"] = baseline
        r["ratio_vs_reference"] = r["sps"] / ref if ref else None
        ratio = f"{r['ratio_vs_reference']:.2f}x" if ref else "-"
        print(
            f"{r['config']:<24} {r['sps']:>10.0f} {ratio:>18} {r['train_share']:>15.0%}  "
            f"{r['sps_runs']} (peak RSS {r['peak_rss_mb']:.0f} MB)"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps(
            {
                "device": args.device,
                "threads": args.threads,
                "settings": {k: v for k, v in vars(args).items() if k not in ("config", "out")},
                "results": rows,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
