"""The scripted frontier by role: the best role blend, searched on episodes no evaluation plays.

The blend reference policy has a radius per role (``reference_policies.ROLES``): ``defend``, the
robot the heuristic sends to intercept the invader; ``collect``, the robots it sends to a
resource; ``deliver``, the carriers it sends home. Within its role's radius a robot does the
heuristic's task, beyond it it follows its waypoints (``blend(defend=1.75)``: the interceptor
defends within 1.75 m, every other robot follows). The follower is ``blend(0)``, the heuristic
``blend(inf)``.

Protocol: four quadrants (4 x 145 steps), the default env (``compose_config([])``). Two stages,
every grid point a slice of one batched env (its own episodes; ``CHUNK_ENVS`` envs at a time):

1. search: every point of ``GRID`` on ``--search-trials`` episodes (env and walks seed
   ``SEARCH_SEED``);
2. confirm: per reward preset, the ``--top`` best points that collect (collect radius > 0) and
   the ``--top`` best that do not, on ``--confirm-trials`` fresh episodes (``CONFIRM_SEED``).

The best confirmed point at the default reward is "best scripted"
(``reference_policies.BEST_SCRIPTED``). Seeds: training plays env seed ``s``, its evaluations
``10_000 + s``, ``icco eval`` ``20_000 + s`` (``training/build.py``); these are 30_000 and 31_000.
Last, the named teams of the README's table by role and the best points are replayed, one env
each, on the episodes of ``icco eval`` at seed 0 (env seed 20_000, walks seed 0,
``--eval-trials`` trials, the four-quadrant experiment's): chosen elsewhere, scored there.

A blend's actions do not depend on the reward weights, so each rollout (instruction reward at
unit scale) is scored under every preset in ``conf/reward`` from its event counts.

    OMP_NUM_THREADS=1 python experiments/calibration/best_scripted.py   # ~9 min on one core
    python experiments/calibration/best_scripted.py --render            # README + figure from json
"""

from __future__ import annotations

import argparse
import functools
import itertools
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from icco_torchrl.envs import EVENTS, ResourceCollectionEnv
from icco_torchrl.envs.reference_policies import (
    BEST_SCRIPTED,
    ROLES,
    BlendPolicy,
    RoleRadii,
)
from icco_torchrl.evaluation.metrics import EPISODE, SHARE
from icco_torchrl.evaluation.protocols import quadrant_schedule, run_schedule
from icco_torchrl.paths import CONF_DIR
from icco_torchrl.training.build import EVAL_SEED_OFFSET, compose_config

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
import verdict  # noqa: E402  (experiments/verdict.py: the rule every page judges gaps by)

INF = math.inf
GRID = {
    "defend": (0.0, 1.0, 1.5, 1.75, 2.0, 2.5, 3.0, INF),
    "collect": (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, INF),
    "deliver": (0.0, 1.0, 2.0, 3.0, INF),
}
SEARCH_SEED, CONFIRM_SEED = 30_000, 31_000
CHUNK_ENVS = 2400  # envs per batched rollout (~1 GB of recorded trajectories)
# The table by role: named teams, replayed on the evaluation's episodes with the best points.
NAMED = {
    "follower": RoleRadii(0, 0, 0),
    "heuristic": RoleRadii(INF, INF, INF),
    "blend (r=1.75 m), every role": RoleRadii(1.75, 1.75, 1.75),
    "defend-first": RoleRadii(1.75, 0, 0),
    "defend-first, collecting within 1 m": RoleRadii(1.75, 1.0, 1.0),
    "collect-only (1.75 m)": RoleRadii(0, 1.75, 1.75),
}
# Per trial: the episode's event counts, unit-scale instruction reward and time in quadrant.
TRIAL_KEYS = (*EVENTS, "inst_reward", "task_reward", "in_quadrant")


@functools.cache
def default_env_params() -> dict:
    """The env parameters every command composes by default (the calibrated reward)."""
    return OmegaConf.to_container(compose_config([]).env.params, resolve=True)


def grid_points(grid: dict) -> list[RoleRadii]:
    """Every combination of the grid's radii, in ``ROLES`` order."""
    return [RoleRadii(*radii) for radii in itertools.product(*(grid[role] for role in ROLES))]


def reward_presets() -> dict[str, dict]:
    """Each ``conf/reward`` preset's weights: ``inst`` (the instruction reward's scale) and one per
    event (``invasion`` negative), from the composed config. Refuses a preset changing another
    reward parameter, which a rescoring of counts could not reproduce."""
    presets = {}
    default = default_env_params()
    for path in sorted((CONF_DIR / "reward").glob("*.yaml")):
        params = OmegaConf.to_container(
            compose_config([f"reward={path.stem}"]).env.params, resolve=True
        )
        other = [k for k in params if k != "inst_reward_scale" and params[k] != default.get(k)]
        other = [k for k in other if not k.endswith(("_reward", "_penalty"))]
        if other:
            raise ValueError(f"reward preset {path.stem!r} changes {other}: rescoring cannot")
        weights = dict(
            inst=params["inst_reward_scale"],
            pick=params["pick_reward"],
            collect=params["collect_reward"],
            defense=params["defense_reward"],
            invasion=-params["invasion_penalty"],
        )
        presets[path.stem] = {"weights": weights, "default": params == default}
    return presets


def team_reward(values: dict, weights: dict) -> np.ndarray:
    """Per-trial team reward under ``weights`` (``values``: unit-scale instruction reward)."""
    return weights["inst"] * values["inst_reward"] + sum(weights[e] * values[e] for e in EVENTS)


def rollout(
    points: list[RoleRadii],
    trials: int,
    *,
    seed: int,
    walks_seed: int,
    steps: int = 145,
    chunk_envs: int = CHUNK_ENVS,
) -> list[dict]:
    """Per point, ``{key: [trials]}`` of :data:`TRIAL_KEYS` over four-quadrant episodes (env seed
    ``seed``, quadrant walks ``walks_seed``) of the default env at unit instruction scale. Points
    share a batched env, ``trials`` envs each; with ``chunk_envs <= trials`` every point gets its
    own env, so all play the same episodes (those of ``icco eval`` with ``eval.trials=trials``
    at seed ``s`` for ``seed = 20_000 + s``, ``walks_seed = s``)."""
    params = dict(default_env_params())
    params.update(inst_reward_scale=1.0, max_steps=4 * steps, waypoint_mode="external")
    per_chunk = max(1, chunk_envs // trials)
    event_weights = {e: params[f"{e}_reward"] for e in ("pick", "collect", "defense")}
    event_weights["invasion"] = -params["invasion_penalty"]
    out = []
    for start in range(0, len(points), per_chunk):
        chunk = points[start : start + per_chunk]
        env = ResourceCollectionEnv(num_envs=len(chunk) * trials, seed=seed, **params)
        radii = torch.tensor(chunk, dtype=torch.float32).repeat_interleave(trials, 0)
        schedule = quadrant_schedule(steps, seed=walks_seed)
        run = run_schedule(env, BlendPolicy(env, radii), schedule, env.num_envs)
        rows = [r for r in run.rows if r["segment"] == EPISODE]
        for i in range(len(chunk)):
            mine = rows[i * trials : (i + 1) * trials]
            out.append({k: np.array([r[k] for r in mine], dtype=float) for k in TRIAL_KEYS})
            rescored = team_reward(out[-1], {"inst": 0.0, **event_weights})
            assert np.allclose(rescored, out[-1]["task_reward"], atol=1e-3), "rescoring is exact"
        print(f"  {start + len(chunk)}/{len(points)} points", flush=True)
    return out


def summary(radii: RoleRadii, values: dict, presets: dict) -> dict:
    """A point's means (``inst_reward`` at unit scale) and its team reward under each preset
    (mean, std over trials, standard error of the mean)."""
    n = len(values["inst_reward"])
    team = {}
    for name, preset in presets.items():
        r = team_reward(values, preset["weights"])
        team[name] = {"mean": r.mean(), "std": r.std(), "se": r.std(ddof=1) / math.sqrt(n)}
    means = {k: float(values[k].mean()) for k in TRIAL_KEYS}
    return {"radii": radii._asdict(), "trials": n, "metrics": means, "team": team}


def _collects(row: dict) -> bool:
    return row["radii"]["collect"] > 0


def search(
    grid: dict,
    *,
    presets: dict,
    search_trials: int,
    confirm_trials: int,
    top: int,
    steps: int = 145,
) -> dict:
    """The two stages (module docstring): every point of ``grid``, then per preset the ``top``
    best that collect and that do not, confirmed on fresh episodes. ``best[preset]``: the best
    confirmed point; ``collecting[preset]``: the best confirmed with and without collecting and
    the difference (``worth``, its standard error ``se``)."""
    points = grid_points(grid)
    values = rollout(points, search_trials, seed=SEARCH_SEED, walks_seed=SEARCH_SEED, steps=steps)
    found = [summary(p, v, presets) for p, v in zip(points, values)]
    chosen: list[RoleRadii] = []
    for name in presets:
        for collects in (False, True):
            group = [r for r in found if _collects(r) == collects]
            group.sort(key=lambda r: r["team"][name]["mean"], reverse=True)
            chosen += [RoleRadii(**r["radii"]) for r in group[:top]]
    chosen = list(dict.fromkeys(chosen))
    values = rollout(
        chosen, confirm_trials, seed=CONFIRM_SEED, walks_seed=CONFIRM_SEED, steps=steps
    )
    confirmed = [summary(p, v, presets) for p, v in zip(chosen, values)]
    best, collecting = {}, {}
    for name in presets:
        rank = sorted(confirmed, key=lambda r: r["team"][name]["mean"], reverse=True)
        best[name] = rank[0]["radii"]
        with_, without = (next(r for r in rank if _collects(r) == c) for c in (True, False))
        a, b = with_["team"][name], without["team"][name]
        collecting[name] = {
            "with": with_["radii"],
            "without": without["radii"],
            "worth": a["mean"] - b["mean"],
            "se": math.hypot(a["se"], b["se"]),
        }
    return {
        "grid": grid,
        "search": {"seed": SEARCH_SEED, "trials": search_trials, "points": found},
        "confirm": {"seed": CONFIRM_SEED, "trials": confirm_trials, "points": confirmed},
        "best": best,
        "collecting": collecting,
    }


def evaluation_teams(result: dict) -> dict[str, RoleRadii]:
    """The teams of the table by role: the named ones, best scripted, each other preset's best
    and the with/without-collecting pairs (by name; several names may share radii)."""
    default = next(name for name, p in result["presets"].items() if p["default"])
    teams = dict(NAMED)
    teams["best scripted"] = RoleRadii(**result["best"][default])
    for name in result["presets"]:
        if name != default:
            teams[f"best at reward={name}"] = RoleRadii(**result["best"][name])
        for key in ("with", "without"):
            teams[f"best {key} collecting at reward={name}"] = RoleRadii(
                **result["collecting"][name][key]
            )
    return teams


def replay(result: dict, trials: int, steps: int = 145) -> dict:
    """The teams of :func:`evaluation_teams`, each in its own env, on the episodes of ``icco
    eval`` at seed 0 (env seed ``EVAL_SEED_OFFSET``, walks seed 0)."""
    teams = evaluation_teams(result)
    distinct = list(dict.fromkeys(teams.values()))
    values = rollout(
        distinct, trials, seed=EVAL_SEED_OFFSET, walks_seed=0, steps=steps, chunk_envs=1
    )
    rows = {radii: summary(radii, v, result["presets"]) for radii, v in zip(distinct, values)}
    return {
        "seed": EVAL_SEED_OFFSET,
        "walks_seed": 0,
        "trials": trials,
        "teams": {name: rows[radii] for name, radii in teams.items()},
    }


# ---------------------------------------------------------------------------------- rendering
BEGIN, END = "<!-- best_scripted.py: begin -->", "<!-- best_scripted.py: end -->"


def _encode(value):
    """JSON without non-standard ``Infinity``: infinite radii as ``"inf"``; numpy as Python."""
    if isinstance(value, dict):
        return {k: _encode(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_encode(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return "inf" if math.isinf(value) else float(value)
    return value


def _decode(value):
    if isinstance(value, dict):
        return {k: _decode(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_decode(v) for v in value]
    return math.inf if value == "inf" else value


def blend_name(radii: dict) -> str:
    """The reference name of a role blend: ``blend(defend=1.75, collect=0, deliver=0)``."""
    return "blend(" + ", ".join(f"{role}={radii[role]:g}" for role in ROLES) + ")"


def _radii(radii: dict) -> str:
    return " / ".join(f"{radii[role]:g}" for role in ROLES)


def _team_table(evaluation: dict, preset: str, weights: dict, best: str) -> str:
    teams = evaluation["teams"]
    head = (
        "| team | defend / collect / deliver (m) | team reward | share of the best here "
        "| instruction | picks | deliveries | defenses | invasions |"
    )
    lines = [head, "|---|---|---|---|---|---|---|---|---|"]
    top = teams[best]["team"][preset]["mean"]
    for name, row in teams.items():
        if name.startswith("best with") or name.startswith("best without"):
            continue
        team, m = row["team"][preset], row["metrics"]
        bold = "**" if name == best else ""
        lines.append(
            f"| {bold}{name}{bold} | {_radii(row['radii'])} | {bold}{team['mean']:.1f} ± "
            f"{team['std']:.1f}{bold} | {100 * team['mean'] / top:.0f} % | "
            f"{weights['inst'] * m['inst_reward']:.1f} | {m['pick']:.1f} | {m['collect']:.1f} | "
            f"{m['defense']:.1f} | {m['invasion']:.1f} |"
        )
    return "\n".join(lines)


def _worth(result: dict, preset: str) -> str:
    """What collecting is worth under ``preset``, in words, from the confirm and replay stages."""
    c, weights = result["collecting"][preset], result["presets"][preset]["weights"]
    confirm = {blend_name(r["radii"]): r for r in result["confirm"]["points"]}
    w, wo = confirm[blend_name(c["with"])], confirm[blend_name(c["without"])]
    teams = result["evaluation"]["teams"]
    ew = teams[f"best with collecting at reward={preset}"]["metrics"]
    ewo = teams[f"best without collecting at reward={preset}"]["metrics"]
    parts = {
        "picks and deliveries": sum(weights[e] * (ew[e] - ewo[e]) for e in ("pick", "collect")),
        "defenses and invasions": sum(
            weights[e] * (ew[e] - ewo[e]) for e in ("defense", "invasion")
        ),
        "instruction": weights["inst"] * (ew["inst_reward"] - ewo["inst_reward"]),
    }
    gap = verdict.Gap(c["worth"], c["se"])
    said = {
        verdict.AHEAD: f"**collecting adds {gap.gap:.1f}**",
        verdict.BEHIND: f"**collecting costs {-gap.gap:.1f}**",
        verdict.WITHIN: "**collecting is worth nothing measurable**",
    }[gap.word]
    return (
        f"What collecting is worth at `reward={preset}`: the best confirmed team that collects, "
        f"`{blend_name(c['with'])}`, scores {w['team'][preset]['mean']:.1f}; the best that does "
        f"not, `{blend_name(c['without'])}`, {wo['team'][preset]['mean']:.1f} "
        f"({result['confirm']['trials']} confirm episodes each): {said} (with against without: "
        f"{gap.text()}). On the evaluation "
        "episodes the difference splits into "
        + ", ".join(f"{k} {v:+.1f}" for k, v in parts.items())
        + "."
    )


def plateau(points: list[dict], preset: str) -> list[dict]:
    """The confirmed points not behind the best one at ``preset`` (``verdict.py``'s rule on
    their standard errors), best first."""
    ranked = sorted(points, key=lambda r: -r["team"][preset]["mean"])
    best = ranked[0]["team"][preset]
    return [
        r
        for r in ranked
        if verdict.Gap(
            r["team"][preset]["mean"] - best["mean"],
            math.hypot(r["team"][preset]["se"], best["se"]),
        ).word
        != verdict.BEHIND
    ]


def render(result: dict) -> str:
    """The README section (between :data:`BEGIN` and :data:`END`), from the json alone."""
    presets, default = result["presets"], result["default_preset"]
    n_points = len(result["search"]["points"])
    best = result["best"][default]
    ev = result["evaluation"]
    bs = ev["teams"]["best scripted"]["team"][default]
    refs = {k: ev["teams"][k]["team"][default]["mean"] for k in ("follower", "heuristic")}
    blend = ev["teams"]["blend (r=1.75 m), every role"]["team"][default]["mean"]
    lines = [
        BEGIN,
        "## By role: the best scripted team (issue 36)",
        "",
        "`OMP_NUM_THREADS=1 python experiments/calibration/best_scripted.py` "
        f"({result['wall_s'] / 60:.0f} min, one process and one thread on a shared two-core "
        "machine; writes `results/best_scripted.json`, "
        "`results/best_scripted.png` and this section; `--render` rewrites both from the json).",
        "",
        "The blend gets a radius per role: **defend** (the robot the heuristic sends to intercept "
        "the invader), **collect** (robots it sends to a resource), **deliver** (carriers it sends "
        "home). Within its role's radius a robot does the heuristic's task, beyond it it follows; "
        "a reference named `blend(defend=1.75)` defends within 1.75 m and otherwise follows "
        "(`icco_torchrl/envs/reference_policies.py`). Four-quadrant protocol, 580 steps.",
        "",
        f"- Search: {n_points} points ("
        + " x ".join(
            f"{role} in {{{', '.join(f'{r:g}' for r in result['grid'][role])}}}" for role in ROLES
        )
        + f"), {result['search']['trials']} episodes each (env seed {result['search']['seed']}).",
        f"- Confirm: per reward preset the {result['top']} best that collect and the "
        f"{result['top']} best that do not, {result['confirm']['trials']} fresh episodes each "
        f"(env seed {result['confirm']['seed']}).",
        f"- Tables: the episodes of `icco eval` at seed 0 (env seed {ev['seed']}, walks seed "
        f"{ev['walks_seed']}, {ev['trials']} trials), which the search never played.",
        "",
        f"**Best scripted** (`reward={default}`, the default): `{blend_name(best)}`, "
        f"{bs['mean']:.1f} ± {bs['std']:.1f} on the evaluation episodes, against the blend "
        f"r = 1.75 m's {blend:.1f}, the follower's {refs['follower']:.1f} and the heuristic's "
        f"{refs['heuristic']:.1f}. It is `reference_policies.BEST_SCRIPTED`, the "
        '"best scripted" row of every evaluation table, `results.json` and learning curve; '
        f"reports give learned teams' reward as a '{SHARE}'.",
        "",
        "Confirmed points not behind the best, by the rule of `experiments/verdict.py` (within "
        "the spread of it: a plateau, not a peak): "
        + "; ".join(
            f"`{blend_name(r['radii'])}` {r['team'][default]['mean']:.1f} ± "
            f"{r['team'][default]['se']:.1f}"
            for r in plateau(result["confirm"]["points"], default)
        )
        + f" (mean ± standard error, {result['confirm']['trials']} confirm episodes).",
        "",
        "![best scripted](results/best_scripted.png)",
    ]
    for name, preset in presets.items():
        weights = preset["weights"]
        best_here = "best scripted" if name == default else f"best at reward={name}"
        lines += [
            "",
            f"### `reward={name}` (instruction scale {weights['inst']:g}; pick "
            f"{weights['pick']:g}, delivery {weights['collect']:g}, defense "
            f"{weights['defense']:g}, invasion {weights['invasion']:g})",
            "",
            _team_table(ev, name, weights, best_here),
            "",
            _worth(result, name),
        ]
    lines += [
        "",
        "**The paper's claim that ICCO collects**, read as \"collecting is part of the "
        'reward-optimal team" and judged on the confirm episodes by `experiments/verdict.py` '
        "(the best team that collects against the best that does not):",
    ]
    for name in presets:
        c = result["collecting"][name]
        gap = verdict.Gap(c["worth"], c["se"])
        if gap.word != verdict.AHEAD:
            lines.append(
                f"- `reward={name}`: {verdict.claim([gap.word])} ({gap.text()}); the best team "
                "that does not collect is "
                + ("better." if gap.word == verdict.BEHIND else "as good.")
            )
            continue
        team = "best scripted" if name == default else f"best at reward={name}"
        best_row, heuristic = ev["teams"][team], ev["teams"]["heuristic"]
        mean = best_row["team"][name]["mean"]
        lines.append(
            f"- `reward={name}`: {verdict.HOLDS} for collecting near the path only ("
            f"{gap.text()}). The best team collects within "
            f"{c['with']['collect']:g} m of a robot and delivers within {c['with']['deliver']:g} m "
            f"of home: {best_row['metrics']['pick']:.1f} picks per episode against the "
            f"heuristic's {heuristic['metrics']['pick']:.1f}, worth {c['worth']:.1f} "
            f"({100 * c['worth'] / mean:.0f} % of its reward). Collecting as the "
            f"heuristic does costs {mean - heuristic['team'][name]['mean']:.0f}."
        )
    lines.append(END)
    return "\n".join(lines) + "\n"


def write_readme(section: str, readme: Path) -> None:
    """Replace the section between the markers (or append it)."""
    text = readme.read_text()
    if BEGIN in text and END in text:
        text = text[: text.index(BEGIN)] + section + text[text.index(END) + len(END) + 1 :]
    else:
        text = text.rstrip("\n") + "\n\n" + section
    readme.write_text(text)


def plot(result: dict, out: Path) -> None:
    """Team reward of the search against the defend radius, a line per collect radius (best
    deliver radius), one panel per preset."""
    from matplotlib.figure import Figure

    presets = list(result["presets"])
    fig = Figure(figsize=(5.5 * len(presets), 4))
    axes = fig.subplots(1, len(presets), squeeze=False)[0]
    defend = result["grid"]["defend"]
    for ax, name in zip(axes, presets):
        for i, collect in enumerate(result["grid"]["collect"]):
            y = [
                max(
                    (
                        p["team"][name]["mean"]
                        for p in result["search"]["points"]
                        if p["radii"]["defend"] == d and p["radii"]["collect"] == collect
                    ),
                    default=math.nan,
                )
                for d in defend
            ]
            ax.plot(range(len(defend)), y, "o-", ms=3, color=f"C{i}", label=f"collect {collect:g}")
        ax.set_xticks(range(len(defend)), [f"{d:g}" for d in defend])
        ax.set_xlabel("defend radius (m)")
        ax.set_ylabel("team reward per 580-step episode")
        ax.set_title(f"reward={name}: search ({result['search']['trials']} episodes a point)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, title="collect radius (m), best deliver", title_fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--search-trials", type=int, default=128)
    parser.add_argument("--confirm-trials", type=int, default=800)
    parser.add_argument("--top", type=int, default=4)
    parser.add_argument("--eval-trials", type=int, default=100)
    parser.add_argument("--out", type=Path, default=HERE / "results")
    parser.add_argument("--readme", type=Path, default=HERE / "README.md")
    parser.add_argument("--render", action="store_true", help="only rewrite README and figure")
    args = parser.parse_args()
    path = args.out / "best_scripted.json"
    if not args.render:
        torch.set_num_threads(1)
        start = time.perf_counter()
        presets = reward_presets()
        result = search(
            GRID,
            presets=presets,
            search_trials=args.search_trials,
            confirm_trials=args.confirm_trials,
            top=args.top,
        )
        result.update(
            presets=presets,
            default_preset=next(n for n, p in presets.items() if p["default"]),
            top=args.top,
        )
        result["evaluation"] = replay(result, args.eval_trials)
        result["wall_s"] = time.perf_counter() - start
        args.out.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(_encode(result), indent=1))
    result = _decode(json.loads(path.read_text()))
    best = RoleRadii(**result["best"][result["default_preset"]])
    if best != BEST_SCRIPTED:
        print(f"note: update reference_policies.BEST_SCRIPTED to {best} (it is {BEST_SCRIPTED})")
    plot(result, args.out / "best_scripted.png")
    write_readme(render(result), args.readme)
    print(render(result))


if __name__ == "__main__":
    main()
