"""Training-recipe ablation: which levers make ICCO and QMIX (FULL) learn the task on a CPU.

    python experiments/recipe/run.py                # every lever, resumable, 2 runs side by side
    python experiments/recipe/run.py --only rel_icco rel_qmix_full
    python experiments/recipe/run.py --report-only  # rewrite results.md / results.json

Each lever is one ``icco train`` run (seed 0, the calibrated reward, uniform spawns, random-walk
instructions) in ``--out/<name>``; the table reports its last greedy evaluation (16 episodes of
145 steps, the same initial configurations at every evaluation) beside the reference policies
of the same episodes (``references.json``), and its wall time. One seed per lever: a screen,
not a result; the kept recipe is then measured over 3 seeds by the reproduction.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from icco_torchrl.training.logger import clock_seconds

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from jobs import PRE_SEQUENCE_REPLAY, last_row, positive, train_runs  # noqa: E402  (experiments/jobs.py)

# The first budget (2026-11-22) with the first three levers of issue 7's probe (replay ratio 8
# updates per batch, a hard target copy every 50 updates, epsilon at its floor after 300k frames).
PROBE = [
    "train.updates_per_batch=8",
    "train.target_update_interval=50",
    "train.eps_decay_frames=300000",
]
WF_PATHS = [
    "method.waypoint_features=true",
    "env.params.waypoint_path_prob=0.5",
]  # the candidate levers of the waypoint-features entry (2026-11-30)
# Levers measured before waypoint features, paths and a consistency weight of 1e-4 became the
# defaults (README.md, entry "2026-11-30, new defaults"): they pin the defaults of their time
# (pre_waypoint_features below), so each still trains what it measured.
PRE_WAYPOINT_FEATURES = {  # name: (lever, setting, method, overrides)
    "flat_icco": (
        "global-state encoder",
        "flat (absolute tokens)",
        "icco",
        [*PROBE, "method.state_encoder=flat"],
    ),
    "flat_qmix_full": (
        "global-state encoder",
        "flat (one vector)",
        "qmix_full",
        [*PROBE, "method.state_encoder=flat"],
    ),
    "rel_icco": (
        "global-state encoder",
        "relative tokens",
        "icco",
        [*PROBE, "method.state_encoder=relative"],
    ),
    "rel_qmix_full": (
        "global-state encoder",
        "relative tokens",
        "qmix_full",
        [*PROBE, "method.state_encoder=relative"],
    ),
    "rel_lambda08_qmix_full": (
        "TD(lambda)",
        "lambda 0.8",
        "qmix_full",
        [*PROBE, "train.td_lambda=0.8"],
    ),
    "rel_logvar5_icco": (
        "initial z noise",
        "log-variance -5",
        "icco",
        [*PROBE, "method.z_init_logvar=-5"],
    ),
    "rel_logvar5_adam_icco": (
        "optimiser",
        "Adam 1e-3 (+ log-variance -5)",
        "icco",
        [*PROBE, "method.z_init_logvar=-5", "train.optimizer=adam", "train.lr=1e-3"],
    ),
    "rel_adam_qmix_full": (
        "optimiser",
        "Adam 1e-3",
        "qmix_full",
        [*PROBE, "train.optimizer=adam", "train.lr=1e-3"],
    ),
    # Longer training (2026-11-30), at the defaults of conf/experiment/default.yaml (the recipe
    # the rows above chose).
    "guide_blend_icco": (
        "exploration",
        "guided by the blend (r=1.75 m)",
        "icco",
        ["train.explore_guide=blend"],
    ),
    # Waypoint features (2026-11-30): the agents read the nearest waypoint and the path direction
    # r_inst scores.
    "waypoint_features_qmix_inst_only": (
        "waypoint features",
        "on, instruction reward only",
        "qmix",
        ["experiment=inst_only", "method.waypoint_features=true"],
    ),
    "no_waypoint_features_qmix_inst_only": (
        "waypoint features",
        "off, instruction reward only",
        "qmix",
        ["experiment=inst_only"],
    ),
    "waypoint_features_icco": (
        "waypoint features",
        "on",
        "icco",
        ["method.waypoint_features=true"],
    ),
    "waypoint_features_guided_icco": (
        "waypoint features",
        "on + guided by the blend",
        "icco",
        ["method.waypoint_features=true", "train.explore_guide=blend"],
    ),
    "waypoint_features_gamma09_icco": (
        "discount",
        "0.9 (+ waypoint features)",
        "icco",
        ["method.waypoint_features=true", "train.gamma=0.9"],
    ),
    "waypoint_features_gamma095_icco": (
        "discount",
        "0.95 (+ waypoint features)",
        "icco",
        ["method.waypoint_features=true", "train.gamma=0.95"],
    ),
    "waypoint_features_qmix_full": (
        "waypoint features",
        "on",
        "qmix_full",
        ["method.waypoint_features=true"],
    ),
    "waypoint_features_icco_wo_ce": (
        "waypoint features",
        "on",
        "icco_wo_ce",
        ["method.waypoint_features=true"],
    ),
    "paths_icco": ("training instructions", "paths p=0.5 (+ features)", "icco", [*WF_PATHS]),
    "paths_qmix_full": (
        "training instructions",
        "paths p=0.5 (+ features)",
        "qmix_full",
        [*WF_PATHS],
    ),
    "paths_icco_wo_ce": (
        "training instructions",
        "paths p=0.5 (+ features)",
        "icco_wo_ce",
        [*WF_PATHS],
    ),
    "paths_qmix": ("training instructions", "paths p=0.5 (+ features)", "qmix", [*WF_PATHS]),
    "paths_guided_ce1e4_icco": (
        "consistency weight",
        "1e-4, guided (+ features, paths)",
        "icco",
        [*WF_PATHS, "train.explore_guide=blend", "method.ce_coef=0.0001"],
    ),
    "paths_period1_icco": (
        "broadcast period",
        "1 (+ features, paths)",
        "icco",
        [
            *WF_PATHS,
            "method.period=1",
            "train.sequence_length=1",  # items of one period, as when this was measured
            "train.batch_segments=512",
            "train.buffer_segments=80000",
            "train.warmup_segments=2048",
        ],
    ),
}


def pre_waypoint_features(method: str, overrides: list[str]) -> list[str]:
    """``overrides`` on the defaults before waypoint features and paths (COPA's consistency
    weight for ICCO)."""
    return [
        "method.waypoint_features=false",
        "env.params.waypoint_path_prob=0",
        *(["method.ce_coef=0.001"] if method == "icco" else []),
        *overrides,
    ]


LEVERS = {
    name: (lever, setting, method, pre_waypoint_features(method, overrides))
    for name, (lever, setting, method, overrides) in PRE_WAYPOINT_FEATURES.items()
}
LEVERS.update(
    {  # New defaults (2026-11-30), at today's defaults; scored by the four-quadrant protocol at the
        # calibrated reward.
        "ce1e5_icco": ("consistency weight", "1e-5", "icco", ["method.ce_coef=0.00001"]),
        "entropy0_icco": ("entropy term", "off", "icco", ["method.entropy_coef=0"]),
        "guide_blend_qmix_full": (
            "exploration",
            "guided by the blend (r=1.75 m)",
            "qmix_full",
            ["train.explore_guide=blend"],
        ),
        # Delivery reward in the training env only (train.env_params; the first screens set
        # env.params.collect_reward, which trains identically but also shapes the evaluations
        # during training).
        **{
            f"collect{c:g}_{m}".replace(".", ""): (
                "delivery reward in training",
                f"{c:g}",
                m,
                [f"train.env_params.collect_reward={c:g}"],
            )
            for m in ("icco", "qmix_full")
            for c in (2.5, 3.5, 5.0)
        },
        "collect5_qmix": (
            "delivery reward in training",
            "5",
            "qmix",
            ["train.env_params.collect_reward=5"],
        ),
        # Training-env shaping (2026-12-01): the other two methods at 3.5; the paper's flat
        # QMIX (FULL); network and z width.
        **{
            f"collect35_{m}": (
                "delivery reward in training",
                "3.5",
                m,
                ["train.env_params.collect_reward=3.5"],
            )
            for m in ("qmix", "icco_wo_ce")
        },
        "flat_qmix_full_flat": (
            "global-state encoder",
            "flat (the paper's QMIX (FULL))",
            "qmix_full_flat",
            [],
        ),
        "hidden128_icco": ("network width", "128", "icco", ["method.hidden=128"]),
        "zdim128_icco": ("z size", "128 (COPA's)", "icco", ["method.z_dim=128"]),
    }
)
# Every lever here was measured before sequence replay became the default (2026-12-01): pin that
# recipe (4-step items, one-step targets, no shaping) so each still trains what it measured; a
# lever's own overrides come after and win.
LEVERS = {
    name: (lever, setting, method, [*PRE_SEQUENCE_REPLAY, *overrides])
    for name, (lever, setting, method, overrides) in LEVERS.items()
}
METRICS = ("reward", "task_reward", "inst_reward", "pick", "defense", "invasion")


def summarize(out: Path, frames: int) -> list[dict]:
    table = []
    for name, (lever, setting, method, overrides) in LEVERS.items():
        run = out / name
        ev, timing = last_row(run / "eval.csv"), last_row(run / "timing.csv")
        if ev is None:
            continue
        row = {
            "name": name,
            "lever": lever,
            "setting": setting,
            "method": method,
            "frames": int(ev["frames"]),
            **{k: float(ev[k]) for k in METRICS if k in ev},
        }
        if "task_reward" not in row:  # runs from before task_reward was logged
            row["task_reward"] = row["reward"] - row["inst_reward"]
        if timing:
            row["wall_min"] = clock_seconds(timing) / 60
            row["sps"] = float(timing["sps"])
        refs = run / "references.json"
        if refs.is_file():
            row["references"] = {
                k: {m: v[m] for m in METRICS if m in v}
                for k, v in json.loads(refs.read_text()).items()
            }
        row["command"] = " ".join(
            ["icco train", f"method={method}", *overrides, f"train.total_frames={frames}"]
        )
        table.append(row)
    return table


def markdown(table: list[dict]) -> str:
    lines = [
        "| lever | setting | method | frames | task reward | pick | defense | invasion "
        "| instruction reward | team reward | wall (min) |",
        "|" + "---|" * 11,
    ]
    for r in table:
        lines.append(
            f"| {r['lever']} | {r['setting']} | {r['method']} | {r['frames']:,} | "
            f"{r['task_reward']:.1f} | {r['pick']:.1f} | {r['defense']:.1f} | "
            f"{r['invasion']:.1f} | {r['inst_reward']:.1f} | {r['reward']:.1f} | "
            f"{r.get('wall_min', float('nan')):.1f} |"
        )
    refs = next((r["references"] for r in table if "references" in r), None)
    if refs:
        lines += [
            "",
            "Reference policies on the same evaluation episodes:",
            "",
            "| policy | task reward | pick | defense | invasion | instruction reward "
            "| team reward |",
            "|---|---|---|---|---|---|---|",
        ]
        for k, m in refs.items():
            lines.append(
                f"| {k} | {m['task_reward']:.1f} | {m['pick']:.1f} | {m['defense']:.1f} | "
                f"{m['invasion']:.1f} | {m['inst_reward']:.1f} | {m['reward']:.1f} |"
            )
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=Path("multirun/recipe"))
    parser.add_argument("--frames", type=int, default=800_000)
    parser.add_argument("--only", nargs="+", choices=list(LEVERS))
    parser.add_argument("--jobs", type=positive, default=2)
    parser.add_argument("--report-only", action="store_true")
    args = parser.parse_args(argv)
    if not args.report_only:
        chosen = args.only or list(LEVERS)
        train_runs(
            {
                args.out.resolve() / name: (
                    [
                        f"method={LEVERS[name][2]}",
                        *LEVERS[name][3],
                        f"train.total_frames={args.frames}",
                        "train.checkpoint_buffer=false",
                    ],
                    args.frames,
                )
                for name in chosen
            },
            args.jobs,
        )
    table = summarize(args.out, args.frames)
    (HERE / "results.json").write_text(json.dumps(table, indent=1))
    (HERE / "results.md").write_text(markdown(table) + "\n")
    print(markdown(table))


if __name__ == "__main__":
    main()
