"""Render ``benchmarks/README.md`` from ``benchmarks/README.template.md`` and ``results/*.json``.

    python benchmarks/report.py          # after any benchmark has rewritten its JSON

Every figure in the README is read from a results file here, so a number has one home: the JSON
that the benchmark wrote. A file whose rows this script does not know is rendered column by
column, so a benchmark may add fields without breaking the page.
"""

from __future__ import annotations

import json
from pathlib import Path
from string import Template

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"

# What each end-to-end training config is (``train_throughput.py``'s ``--configs``).
TRAIN_CONFIGS = {
    "qmix": "our QMIX (recurrent entity-attention agents, segment replay, `ICCOLoss`)",
    "icco": "our ICCO (coordinator + posterior on top of our QMIX)",
    "torchrl_qmix": "TorchRL's QMIX example as written (`qmix_vdn.py`: `RewardSum`, "
    "`MultiAgentMLP` 2×256 Tanh, `QMixer`, `QMixerLoss`, `SoftUpdate`, Adam, `Collector`)",
    "torchrl_qmix_w64": "the same example with 64 cells (our networks' width)",
}


def load(name: str):
    path = RESULTS / name
    return json.loads(path.read_text()) if path.is_file() else None


def fmt(value) -> str:
    if isinstance(value, bool) or value is None:
        return {True: "yes", False: "no", None: "–"}[value]
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        if abs(value) >= 1000:
            return f"{value:,.0f}"
        return f"{value:.2f}" if abs(value) < 10 else f"{value:.1f}"
    if isinstance(value, list):
        return ", ".join(fmt(v) for v in value)
    return str(value)


def table(rows: list[dict], columns: dict[str, str] | None = None) -> str:
    """A Markdown table of ``rows``: ``columns`` maps keys to headers (default: every scalar)."""
    if not rows:
        return "(no rows)"
    if columns is None or not all(k in rows[0] for k in columns):
        keys = [k for k, v in rows[0].items() if not isinstance(v, dict)]
        columns = {k: k for k in keys}
    lines = ["| " + " | ".join(columns.values()) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(fmt(r.get(k)) for k in columns) + " |" for r in rows]
    return "\n".join(lines)


def machine(data: dict) -> str:
    keys = ("torch", "python", "cpu_count", "cuda_device", "threads", "time")
    bits = [f"{k} {fmt(data[k])}" for k in keys if data.get(k) is not None]
    return "Measured with " + ", ".join(bits) + "." if bits else ""


def env_section(name: str) -> str:
    data = load(name)
    if data is None:
        return f"(not measured: no `results/{name}`)"
    rows = table(
        data.get("rows", []),
        {
            "api": "API",
            "device": "device",
            "num_envs": "envs",
            "env_steps_per_s": "env steps / s",
            "agent_steps_per_s": "agent steps / s",
            "speedup_vs_pettingzoo": "× the PettingZoo view",
        },
    )
    return f"{rows}\n\n{machine(data)} Source: [`results/{name}`](results/{name})."


def loss_section() -> str:
    data = load("loss_step.json")
    if data is None:
        return "(not measured: no `results/loss_step.json`)"
    rows = table(
        data.get("results", []),
        {
            "method": "method",
            "device": "device",
            "batch_segments": "segments",
            "segment_len": "steps per segment",
            "ms_per_update": "ms per update (median)",
            "runs_ms": "runs (ms)",
        },
    )
    src = "Source: [`results/loss_step.json`](results/loss_step.json)."
    return f"{rows}\n\n{machine(data)} {src}"


def throughput_section(name: str, first: str, baseline: str, settings=None) -> str:
    """A ``train_throughput.py`` suite: SPS per config beside ``baseline``, then the settings
    (``settings``: the ones to show; default every scalar one) and the source."""
    data = load(name)
    if data is None:
        return f"(not measured: no `results/{name}`)"
    rows = [
        {**r, "what": TRAIN_CONFIGS.get(r.get("config"), r.get("config"))}
        for r in data.get("results", [])
    ]
    columns = {
        "what": first,
        "sps": "median env steps / s",
        "ratio_vs_reference": f"× {baseline}",
        "sps_runs": "rounds",
        "train_share": "share of time in training",
        "peak_rss_mb": "peak RSS (MB)",
    }
    shown = {
        k: v
        for k, v in data.get("settings", {}).items()
        if not isinstance(v, (list, dict)) and (settings is None or k in settings)
    }
    text = table(rows, columns)
    if shown:
        text += "\n\nSettings: " + ", ".join(f"`{k}` {fmt(v)}" for k, v in shown.items()) + "."
    return f"{text}\n\nSource: [`results/{name}`](results/{name})."


def profile_section() -> str:
    data = load("train_profile.json")
    if data is None:
        return "(not measured: no `results/train_profile.json`)"
    rows = []
    for r in data.get("results", []):
        total = r["total_ms_per_frame"]
        shares = {k: f"{100 * v / total:.0f} %" for k, v in r["ms_per_frame"].items()}
        rows.append(
            {
                "recipe": r["recipe"],
                "ms per frame": total,
                **shares,
                "speed-up": r["speedup_vs_first"],
            }
        )
    src = "[`results/train_profile.json`](results/train_profile.json)"
    return f"{table(rows)}\n\nSource: {src}."


def skill_section() -> str:
    data = load("time_to_skill.json")
    if data is None or "target" not in data:
        return "(not measured: no `results/time_to_skill.json`)"
    rows = [
        {
            "recipe": r["recipe"],
            "seed": r["seed"],
            "CPU": r.get("cpu") or data.get("cpu"),
            "minutes to 90 %": "not reached"
            if r["minutes_to_90_percent"] is None
            else r["minutes_to_90_percent"],
            "frames to 90 %": r["frames_to_90_percent"],
            "final share": f"{100 * r['final_share']:.0f} %",
            "best share": f"{100 * max(m['share'] for m in r['marks']):.0f} %",
            "minutes, all": r["marks"][-1]["minutes"],
            "best scripted": r["best_scripted"],
            "language reward": r["language"]["reward"] if "language" in r else "–",
            "in place (4 instructions)": " / ".join(
                f"{100 * v:.0f}" for v in r["language"]["in_place"].values()
            )
            + " %"
            if "language" in r
            else "–",
        }
        for r in data.get("runs", [])
    ]
    follower = data.get("language_follower")
    if follower:
        places = " / ".join(f"{100 * v:.0f}" for v in follower["in_place"].values())
        rows.append(
            {
                "recipe": "scripted follower (language only)",
                "language reward": follower["reward"],
                "in place (4 instructions)": places + " %",
            }
        )
    where = (
        f"{data['threads']} thread per run, {data['side_by_side']} runs side by side (minutes "
        f"compare only between rows of one CPU); four quadrants, {data['trials']} trials per mark"
    )
    src = "[`results/time_to_skill.json`](results/time_to_skill.json)"
    return f"{where}.\n\n{table(rows)}\n\nSource: {src}; figure: `results/time_to_skill.png`."


def train_gpu_section() -> str:
    data = load("train_throughput_h200.json")
    if data is None:
        return "(not measured: no `results/train_throughput_h200.json`)"
    rows = [{"device": k, **v} for k, v in data.get("runs", {}).items()]
    text = table(
        rows,
        {
            "device": "device",
            "frames": "env steps",
            "env_steps_per_s": "env steps / s",
            "collect_s": "collection (s)",
            "train_s": "updates (s)",
        },
    )
    src = "[`results/train_throughput_h200.json`](results/train_throughput_h200.json)"
    return (
        f"{text}\n\n{data.get('what', '')} ({data.get('date', '')}; command: "
        f"`{data.get('command', '')}`). Source: {src}."
    )


def gpu_check_section() -> str:
    """``benchmarks/gpu_check.sh``'s figures: the update's paths, then whole runs."""
    data = load("gpu_train_h200.json")
    if data is None:
        return "(not measured: no `results/gpu_train_h200.json`)"
    names = {"icco_alone": "ICCO alone", "icco_pair": "ICCO, beside QMIX (FULL)"}
    names["qmix_full_pair"] = "QMIX (FULL), beside ICCO"
    run = data.get("icco_5m")
    rows = [{"run": "ICCO, the whole 5M run", **run}] if run else []  # first: every column
    rows += [{"run": names.get(k, k), **v} for k, v in data["runs"].items()]
    text = table(
        rows,
        {
            "run": "run",
            "frames": "env steps",
            "env_steps_per_s": "env steps / s (its own timing)",
            "collect": "collection (s)",
            "train": "updates (s)",
            "eval": "evaluation (s)",
            "wall_s": "wall, process start to end (s)",
        },
    )
    walls = data["wall_s"]
    text += (
        f"\n\nWall time of 1M frames: ICCO alone {walls['icco_alone']:.0f} s, the two runs at once "
        f"{walls['two_runs_at_once']:.0f} s."
    )
    if run:
        text += (
            f" The 5M run's final greedy evaluation (training's protocol): "
            f"{run['final_eval_reward']:.1f} ± {run['final_eval_reward_std']:.1f}."
        )
        if run.get("slowest_batch_train_s"):
            compile_s = run["slowest_batch_train_s"]
            rest = run["frames"] / (run["collect"] + run["train"] - compile_s + run["eval"])
            text += (
                f" Of its {run['train']:.1f} s of updates, {compile_s:.1f} s are the first batch's "
                f"(the cold compile); without it the run makes {rest:,.0f} env steps/s, and "
                "collection is the larger share."
            )
    src = "[`results/gpu_train_h200.json`](results/gpu_train_h200.json)"
    note = f" {data['note']}" if data.get("note") else ""
    return (
        f"{speed_section('train_speed_h200.json')}\n\n{text}\n\n{data['gpu']}, torch "
        f"{data['torch']}, {data['recipe']}, {data.get('date', '')}.{note} Source: {src}."
    )


def live_section() -> str:
    latency, clients = load("live_latency.json"), load("live_clients.json")
    parts = []
    if latency is not None:
        names = {
            "tick_at_10hz": "live-loop tick at 10 Hz (policy + step + bookkeeping)",
            "offline_planner": "offline planner call (the first one imports litellm)",
            "bridge_round_trip_50hz": "bridge round trip over loopback, 50 Hz control",
            "bridge_state_to_command": "bridge: state datagram in to command out",
        }
        rows = [{"what": names.get(k, k), **v} for k, v in latency.items() if isinstance(v, dict)]
        parts.append(
            table(rows, {"what": "what", "median_ms": "median (ms)", "p99_ms": "p99 (ms)"})
            + "\n\nSource: [`results/live_latency.json`](results/live_latency.json)."
        )
    if clients is not None:
        parts.append(
            f"Page clients of one loop at {fmt(clients.get('rate_hz'))} Hz, "
            f"{fmt(clients.get('seconds'))} s per count; the most clients served (loop >= 95 % "
            f"of its rate, slowest client >= 95 % of the ticks): "
            f"**{fmt(clients.get('max_served'))}**.\n\n"
            + table(
                clients.get("rows", []),
                {
                    "clients": "clients",
                    "loop_hz": "loop (Hz)",
                    "tick_median_ms": "tick median (ms)",
                    "tick_p99_ms": "tick p99 (ms)",
                    "client_hz_min": "slowest client (Hz)",
                    "client_hz_median": "median client (Hz)",
                    "served": "served",
                },
            )
            + "\n\nSource: [`results/live_clients.json`](results/live_clients.json)."
        )
    return "\n\n".join(parts) or "(not measured)"


def speed_section(name: str = "train_speed.json") -> str:
    """Today's eager update against the compiled one, side by side (benchmarks/train_speed.py)."""
    data = load(name)
    if data is None:
        return f"(not measured: no `results/{name}`)"
    rows = []
    for result in data["results"]:
        for path, v in result["paths"].items():
            gemm = result.get("gemm_gflop_s") or {}
            rows.append(
                {
                    "threads": result["threads"],
                    "path": path,
                    "env_steps_per_s": v["env_steps_per_s"],
                    "ms_per_update": v["ms_per_update"],
                    "ops_per_update": v["ops_per_update"],
                    "achieved": v["achieved_gflop_s"],
                    "gemm": max(gemm.values()) if gemm else None,
                    "first_update_s": v["first_update_s"],
                }
            )
    text = table(
        rows,
        {
            "threads": "threads",
            "path": "update",
            "env_steps_per_s": "env steps / s (end to end)",
            "ms_per_update": "ms / update",
            "ops_per_update": "ops / update",
            "achieved": "achieved GFLOP/s",
            "gemm": "GEMM GFLOP/s (same core, best shape)",
            "first_update_s": "warm-up to first update (s)",
        },
    )

    def ratio(r):
        text = (
            f"{r['threads']} thread(s): against eager, update {r['update_speedup']:.2f}x, end to "
            f"end {r['end_to_end_speedup']:.2f}x"
        )
        if r.get("end_to_end_speedup_vs_compiled"):  # the compiled path with bool ReLU masks
            text += (
                f"; against the compiled update with bool masks, update "
                f"{r['update_speedup_vs_compiled']:.2f}x, end to end "
                f"{r['end_to_end_speedup_vs_compiled']:.2f}x"
            )
        return text

    ratios = "; ".join(ratio(r) for r in data["results"])
    src = f"[`results/{name}`](results/{name})"
    isa = data.get("isa")
    isa = (
        f" ({isa['cpu_capability']}, AMX-BF16 {'yes' if isa['amx_bf16'] else 'no'})" if isa else ""
    )
    gflop = data["results"][0]["paths"]["eager"]["gflop_per_update"]
    return (
        f"{text}\n\nRatios of the fastest path: {ratios}. "
        f"{gflop:.2f} GFLOP per update; recipe: {data['recipe']}; {data.get('cpu', '')}"
        f"{isa}, torch {data.get('torch', '')}. Source: {src}."
    )


def kernels_section(name: str = "update_kernels_intel.json") -> str:
    """The compiled update kernel by kernel, with and without bool masks (update_kernels.py)."""
    data = load(name)
    if data is None:
        return f"(not measured: no `results/{name}`)"
    rows, largest = [], []
    for path, v in data["paths"].items():
        rows.append({"path": path, **{k: x for k, x in v.items() if not isinstance(x, list)}})
        largest += [
            f"`{path}`: "
            + "; ".join(
                f"{k['kernel'].split('cpp_fused_')[-1]} {k['ms']:.2f} ms"
                for k in v["largest_fused"][:4]
            )
        ]
    text = table(
        rows,
        {
            "path": "update",
            "ms_per_update": "ms / update",
            "achieved_gflop_s": "achieved GFLOP/s",
            "gemm_ms": "matrix products (ms)",
            "gemm_gflop_s": "their GFLOP/s",
            "fused_kernels": "fused kernels",
            "fused_ms": "their ms",
            "relu_mask_kernels_ms": "of which ReLU-mask kernels (ms)",
            "other_aten_ms": "other aten ops (ms)",
            "rest_ms": "rest (ms)",
        },
    )
    isa = data["isa"]
    return (
        f"{text}\n\nThe largest fused kernels per update: {'; '.join(largest)}. "
        f"{data['gflop_per_update']:.2f} GFLOP per update, {data['updates_profiled']} updates "
        f"profiled per path, {data['threads']} thread; {data['cpu']} ({isa['cpu_capability']}, "
        f"AMX-BF16 {'yes' if isa['amx_bf16'] else 'no'}), torch {data['torch']}. "
        f"Source: [`results/{name}`](results/{name})."
    )


def team_speed_section() -> str:
    """The fixed-size path at a baseline commit and at this one (benchmarks/team_speed.py)."""
    data = load("team_speed.json")
    if data is None:
        return "(not measured: no `results/team_speed.json`)"
    rows = [
        {
            "commit": data[tree],
            "update": path,
            **values,
            "rounds": " / ".join(
                f"{run['paths'][path]['ms_per_update']:.1f}" for run in data["runs"][tree]
            ),
        }
        for tree in ("baseline", "current")
        for path, values in data["median"][tree].items()
    ]
    text = table(
        rows,
        {
            "commit": "commit",
            "update": "update",
            "env_steps_per_s": "env steps / s (end to end)",
            "ms_per_update": "ms / update",
            "ops_per_update": "ops / update",
            "rounds": "ms / update, each round",
        },
    )
    ratios = "; ".join(
        f"{path}: env steps/s {r['env_steps_per_s']:.2f}x, ms/update {r['ms_per_update']:.2f}x"
        for path, r in data["current_over_baseline"].items()
    )
    src = "[`results/team_speed.json`](results/team_speed.json)"
    return (
        f"{text}\n\nThis commit over the baseline: {ratios}; {data['rounds']} rounds of "
        f"{data['batches']} collector batches per path, {data.get('cpu', '')}. Source: {src}."
    )


def render() -> str:
    return Template((HERE / "README.template.md").read_text()).substitute(
        env_cpu=env_section("env_throughput.json"),
        env_gpu=env_section("env_throughput_h200.json"),
        loss=loss_section(),
        train=throughput_section("train_throughput.json", "config", "TorchRL's example"),
        recipes=throughput_section(
            "train_throughput_recipes.json", "recipe", "`icco_4step`", ("frames", "repeats")
        ),
        profile=profile_section(),
        skill=skill_section(),
        speed=speed_section(),
        speed_intel=speed_section("train_speed_intel.json"),
        kernels=kernels_section(),
        team_speed=team_speed_section(),
        train_gpu=train_gpu_section(),
        gpu_check=gpu_check_section(),
        live=live_section(),
    )


def main() -> int:
    (HERE / "README.md").write_text(render())
    print(f"wrote {HERE / 'README.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
