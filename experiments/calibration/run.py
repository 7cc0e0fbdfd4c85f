"""Calibrate the instruction-reward scale: team reward of the blend family against its radius.

The blend policy (``icco_torchrl.envs.reference_policies``) does the task when its task target
is within ``r`` metres and follows the waypoints otherwise: ``r = 0`` is the pure follower,
``r = inf`` the full-information task heuristic. Its behaviour does not depend on the reward
weights, so one rollout per radius at unit instruction scale gives the team reward at every
scale ``s`` exactly: ``team(r, s) = task(r) + s * inst(r)``.

A scale is *calibrated* when a policy that both follows and works (an interior radius) beats
both ends. We pick the scale that maximises that margin, ``min(best - follower, best -
heuristic)``, and report the radius that wins there.

    python experiments/calibration/run.py               # 512 episodes x 145 steps, ~1 min
    python experiments/calibration/run.py --episodes 64 --out runs/cal   # quick look
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

from icco_torchrl.envs import EVENTS, ResourceCollectionEnv
from icco_torchrl.envs.reference_policies import make_reference_policy
from icco_torchrl.evaluation import episode_metrics
from icco_torchrl.training.build import EVAL_SEED_OFFSET

RADII = (0.0, 0.25, 0.5, 0.65, 0.8, 1.0, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0, math.inf)
SCALES = (0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5, 0.6, 0.8, 1.0, 1.3)
QUAD_RADII = (0.65, 1.0, 1.5, 1.75, 2.0, 2.5)
QUAD_METRICS = (
    "reward",
    "task_reward",
    "inst_reward",
    "pick",
    "collect",
    "defense",
    "invasion",
    "in_quadrant",
    "waypoint_dist",
)


def blend_family(episodes: int, seed: int, spawn: str) -> list[dict]:
    """Task reward, unit-scale instruction reward and events per radius (same episodes each)."""
    rows = []
    for r in RADII:
        env = ResourceCollectionEnv(
            num_envs=episodes, seed=seed, spawn=spawn, inst_reward_scale=1.0
        )
        policy = make_reference_policy("blend", env, radius=r)
        with torch.no_grad():
            m = episode_metrics(env.rollout(env.max_steps, policy, break_when_any_done=False))
        task = m["reward"] - m["inst_reward"]
        rows.append(
            {
                "radius": r,
                "task_reward": task.mean().item(),
                "task_reward_std": task.std().item(),
                "inst_unit": m["inst_reward"].mean().item(),
                **{k: m[k].mean().item() for k in EVENTS},
            }
        )
        print(
            f"r={r:>4} task={rows[-1]['task_reward']:7.1f} inst/scale={rows[-1]['inst_unit']:7.1f} "
            + " ".join(f"{k}={rows[-1][k]:.1f}" for k in EVENTS),
            flush=True,
        )
    return rows


def choose_scale(rows: list[dict]) -> dict:
    """Per scale: each radius's team reward, the best radius and its margin over both ends."""
    table = []
    for s in SCALES:
        team = [row["task_reward"] + s * row["inst_unit"] for row in rows]
        best = max(range(len(rows)), key=team.__getitem__)
        table.append(
            {
                "scale": s,
                "team": team,
                "best_radius": rows[best]["radius"],
                "best": team[best],
                "follower": team[0],
                "heuristic": team[-1],
                "margin": min(team[best] - team[0], team[best] - team[-1]),
            }
        )
    return {"per_scale": table, "chosen": max(table, key=lambda t: t["margin"])}


def quadrant_means(
    make_policy, trials: int, *, env_seed: int, schedule_seed: int, **env_params
) -> dict:
    """Means over ``trials`` four-quadrant episodes (4 x 145 steps) of ``make_policy(env)``."""
    from icco_torchrl.evaluation.protocols import quadrant_schedule, run_schedule

    env = ResourceCollectionEnv(
        num_envs=trials,
        seed=env_seed,
        **{**env_params, "max_steps": 4 * 145, "waypoint_mode": "external"},
    )
    run = run_schedule(env, make_policy(env), quadrant_schedule(145, seed=schedule_seed), trials)
    rows = [x for x in run.rows if x["segment"] == "episode"]
    return {k: sum(x[k] for x in rows) / len(rows) for k in QUAD_METRICS}


def quadrant_references(scale: float, trials: int, seed: int, spawn: str) -> list[dict]:
    """The reference policies in the four-quadrant protocol (580 steps) at the chosen scale."""
    out = []
    for name, r in [("random", None), ("follower", None), ("heuristic", None)] + [
        ("blend", r) for r in QUAD_RADII
    ]:
        mean = quadrant_means(
            lambda env, name=name, r=r: make_reference_policy(name, env, radius=r),
            trials,
            env_seed=seed,
            schedule_seed=seed,
            spawn=spawn,
            inst_reward_scale=scale,
        )
        out.append({"policy": name if r is None else f"blend r={r}", **mean})
        print(
            f"{out[-1]['policy']:>14} " + " ".join(f"{k}={v:.2f}" for k, v in mean.items()),
            flush=True,
        )
    return out


def plot(rows: list[dict], calib: dict, out: Path) -> None:
    """Left: team reward against r at a few scales. Right: the blend's advantage over the better
    of its two ends (pure follower, pure heuristic) at every scale; positive = blending pays."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [min(row["radius"], 5.0) for row in rows]
    labels = [f"{v:g}" for v in x[:-1]] + ["inf"]
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5))
    cmap = plt.get_cmap("viridis")
    for i, t in enumerate(calib["per_scale"]):
        bold = t["scale"] == calib["chosen"]["scale"]
        style = dict(
            color="crimson" if bold else cmap(i / len(calib["per_scale"])),
            lw=2.5 if bold else 1,
            marker="o" if bold else ".",
            label=f"scale {t['scale']}" + (" (chosen)" if bold else ""),
        )
        ends = max(t["follower"], t["heuristic"])
        right.plot(x, [v - ends for v in t["team"]], **style)
        if t["scale"] in (0.1, 0.2, 0.3, 0.5, 1.3):
            left.plot(x, t["team"], **style)
    for ax in (left, right):
        ax.set_xticks(x)
        ax.set_xticklabels(labels, rotation=45)
        ax.set_xlabel("blend radius r (m): 0 = pure follower, inf = task heuristic")
        ax.grid(alpha=0.3)
    left.set_ylabel("team reward per 145-step episode")
    left.set_title("team reward of the blend family", fontsize=10)
    left.legend(fontsize=8)
    right.axhline(0, color="black", lw=0.8)
    right.set_ylabel("team reward - max(follower, heuristic)")
    right.set_title("does a policy that follows and works win?", fontsize=10)
    right.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=512)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--spawn", default="uniform")
    parser.add_argument("--quadrant-trials", type=int, default=40)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = blend_family(args.episodes, args.seed, args.spawn)
    calib = choose_scale(rows)
    print(
        f"four-quadrant protocol at scale {calib['chosen']['scale']} ({args.quadrant_trials} "
        "trials x 580 steps):"
    )
    quad = quadrant_references(
        calib["chosen"]["scale"], args.quadrant_trials, args.seed + EVAL_SEED_OFFSET, args.spawn
    )
    (out / "calibration.json").write_text(
        json.dumps(
            {
                "episodes": args.episodes,
                "steps": 145,
                "seed": args.seed,
                "spawn": args.spawn,
                "radii": rows,
                **calib,
                "quadrants": {"trials": args.quadrant_trials, "steps": 580, "policies": quad},
            },
            indent=1,
            default=lambda v: None,
        )
    )
    plot(rows, calib, out / "blend_team_reward.png")
    print("scale  best_r  best  follower  heuristic  margin")
    for t in calib["per_scale"]:
        print(
            f"{t['scale']:5}  {t['best_radius']:6}  {t['best']:6.1f}  {t['follower']:8.1f}  "
            f"{t['heuristic']:9.1f}  {t['margin']:6.1f}"
        )
    print("chosen:", {k: v for k, v in calib["chosen"].items() if k != "team"})


if __name__ == "__main__":
    main()
