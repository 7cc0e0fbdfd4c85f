"""Task reward against time in the instructed quadrant: can any scripted policy meet both bars?

Issue 10 asks trained teams for a task reward of at least half the full-information heuristic's
*and* at least 70 % of robot-steps inside the instructed quadrant (four-quadrant protocol, 580
steps, calibrated reward). This traces what two families of scripted policies reach on that plane:

- the blend (``reference_policies.BlendPolicy``): the task when its target is within ``r`` of the
  robot, the waypoints otherwise;
- the *anchored* blend (defined here, an experiment, not a reference policy): the task when its
  target is within ``r`` of the centre of the robot's own waypoints, so a robot works where it is
  told to be; carriers always deliver; optionally also within ``robot_r`` of the robot.

Trained teams (``../four_quadrants/results.json``) are drawn on the same plane.

    python experiments/calibration/frontier.py   # ~1 min on one core; results/frontier.{json,png}
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

from icco_torchrl import methods
from icco_torchrl.envs.reference_policies import (
    BlendPolicy,
    lookahead,
    make_reference_policy,
    steer,
)
from icco_torchrl.training.build import EVAL_SEED_OFFSET, compose_config

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from run import quadrant_means  # noqa: E402  (experiments/calibration/run.py, the sibling script)

BLEND_RADII = (0.65, 1.0, 1.5, 1.75, 2.0, 2.5, 3.0)
ANCHORED = [(r, 0.0) for r in (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)] + [(r, 0.65) for r in (1.0, 1.5, 2.0)]


class AnchoredBlend(BlendPolicy):
    """The task when the task target is within ``radius`` of the centre of the robot's waypoints
    (or within ``robot_radius`` of the robot, or the robot carries); the waypoints otherwise."""

    def __init__(self, env, radius: float, robot_radius: float = 0.0):
        super().__init__(env, radius)
        self.anchor_radius, self.robot_radius = radius, robot_radius

    def act(self) -> torch.Tensor:
        e = self.env
        new_pos, r_inst = lookahead(e)
        target, dist = self.targets()
        near_instruction = (target - e.waypoints.mean(-2)).norm(dim=-1) <= self.anchor_radius
        work = near_instruction | e.carry | (dist <= self.robot_radius)
        return torch.where(work, steer(new_pos, target), r_inst.argmax(-1))


def plot(rows: list[dict], trained: dict, bars: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5))
    for family, style in (("blend", "o-"), ("anchored", "s-"), ("anchored + robot 0.65 m", "^-")):
        pts = [r for r in rows if r["family"] == family]
        ax.plot(
            [p["in_quadrant"] for p in pts],
            [p["task_reward"] for p in pts],
            style,
            label=family,
            alpha=0.8,
        )
        for p in pts:
            ax.annotate(
                f"{p['radius']:g}",
                (p["in_quadrant"], p["task_reward"]),
                fontsize=7,
                textcoords="offset points",
                xytext=(3, 3),
            )
    for p in (r for r in rows if r["family"] in ("follower", "heuristic")):
        ax.plot(p["in_quadrant"], p["task_reward"], "k*", ms=10)
        ax.annotate(
            p["family"],
            (p["in_quadrant"], p["task_reward"]),
            fontsize=8,
            textcoords="offset points",
            xytext=(4, -10),
        )
    for name, m in trained.items():
        ax.plot(m["in_quadrant"]["mean"], m["task_reward"]["mean"], "D", color="crimson", ms=6)
        ax.annotate(
            name,
            (m["in_quadrant"]["mean"], m["task_reward"]["mean"]),
            fontsize=7,
            color="crimson",
            textcoords="offset points",
            xytext=(4, 2),
        )
    ax.axhline(bars["task"], color="grey", ls="--", lw=1)
    ax.axvline(bars["in_quadrant"], color="grey", ls="--", lw=1)
    ax.fill_between(
        [bars["in_quadrant"], 1.0], bars["task"], 450, color="green", alpha=0.08, label="both bars"
    )
    ax.set_xlim(0.15, 0.85)
    ax.set_ylim(-120, 420)
    ax.set_xlabel("fraction of robot-steps in the instructed quadrant")
    ax.set_ylabel("task reward per 580-step episode (team)")
    ax.set_title(
        "four-quadrant protocol, calibrated reward: scripted families (label: r in m)\n"
        "and trained teams (3 seeds, red)",
        fontsize=9,
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=40)
    parser.add_argument("--out", type=Path, default=HERE / "results")
    args = parser.parse_args()
    torch.set_num_threads(1)
    params = OmegaConf.to_container(
        compose_config([]).env.params, resolve=True
    )  # the calibrated eval env
    rows = []

    def add(
        family: str, radius, make
    ):  # the episodes of `icco eval` at seed 0 (env seed 20000, walks seed 0)
        means = quadrant_means(
            make, args.trials, env_seed=EVAL_SEED_OFFSET, schedule_seed=0, **params
        )
        rows.append({"family": family, "radius": radius, **means})
        print(
            " ".join(
                f"{k}={v:.2f}" if isinstance(v, float) else f"{k}={v}" for k, v in rows[-1].items()
            ),
            flush=True,
        )

    add("follower", None, lambda env: make_reference_policy("follower", env))
    add("heuristic", None, lambda env: make_reference_policy("heuristic", env))
    for r in BLEND_RADII:
        add("blend", r, lambda env, r=r: make_reference_policy("blend", env, radius=r))
    for r, robot in ANCHORED:
        add(
            "anchored" + (f" + robot {robot:g} m" if robot else ""),
            r,
            lambda env, r=r, robot=robot: AnchoredBlend(env, r, robot),
        )
    heuristic = next(r for r in rows if r["family"] == "heuristic")
    bars = {"task": heuristic["task_reward"] / 2, "in_quadrant": 0.70}
    both = [
        r
        for r in rows
        if r["task_reward"] >= bars["task"] and r["in_quadrant"] >= bars["in_quadrant"]
    ]
    print(
        f"bars: task >= {bars['task']:.1f} and in quadrant >= 0.70; met by {len(both)} of "
        f"{len(rows)} policies"
    )
    trained_path = HERE.parent / "four_quadrants" / "results.json"
    trained = {
        k: v
        for k, v in json.loads(trained_path.read_text())["methods"].items()
        if k in methods.names()
    }  # the methods, not the reference rows
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "frontier.json").write_text(
        json.dumps(
            {
                "trials": args.trials,
                "steps": 580,
                "bars": bars,
                "policies": rows,
                "both_bars": both,
            },
            indent=1,
        )
    )
    plot(rows, trained, bars, args.out / "frontier.png")


if __name__ == "__main__":
    main()
