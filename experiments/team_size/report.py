"""Render the team-size README and its figures from ``results.json`` (see ``run.py``).

    python experiments/team_size/report.py [RESULTS_JSON] [--readme PATH]

Without a results file (the experiment not run yet) the README says so, with the command, and
every target reads "not measured". The targets are computed from the numbers, never written in
advance, each judged by the rule and in the words of ``experiments/verdict.py`` (a share of a
reference is a bar: ``a >= s x b`` judged on ``a - s x b`` against 2 standard errors; n: the
trials of each results entry, pooled across seeds): holds, does not hold, not resolved at this
budget or not measured.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
from pathlib import Path
from string import Template

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
import verdict  # noqa: E402  (experiments/verdict.py: the rule every page judges gaps by)

COPA_RATE = 0.13  # COPA: "remains high even when the coach communicates as little as 13 %"
ZERO_SHOT = (5, 6)  # the team sizes no training env held
PER_ROBOT_SHARE = 0.8  # of the blend's team reward per robot, at 5 and 6 robots
RATE_BOUND, KEPT_SHARE = 0.25, 0.9  # at <= 25 % of the every-T broadcasts, >= 90 % of its reward


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def _num(x, digits: int = 1) -> str:
    return f"{x:.{digits}f}" if _finite(x) else "–"


def _pct(x) -> str:
    return f"{100 * x:.0f} %" if _finite(x) else "–"


def _by_method(results: dict) -> dict[str, dict[int, dict]]:
    """``{method label: {team size: entry}}`` in results order."""
    out: dict[str, dict[int, dict]] = {}
    for entry in results.get("sizes", []):
        out.setdefault(entry["method"], {})[entry["team_size"]] = entry
    return out


def _blend(results: dict) -> dict[int, dict]:
    return next((v for k, v in _by_method(results).items() if k.startswith("blend")), {})


def _mean(point: dict, metric: str = "reward_per_robot") -> verdict.Mean:
    """A results entry's ``metric`` over its trials (seeds pooled)."""
    return verdict.Mean(point[metric], point[f"{metric}_std"], int(point.get("trials") or 0))


def zero_shot_target(results: dict | None) -> str:
    """Target 1: a policy trained on 2-4 robots keeps >= 80 % of the blend's team reward per
    robot at 5 and 6 robots (the bar ``a >= 0.8 x blend``, judged by ``verdict.compare``). Holds
    when one trained policy holds it at both sizes."""
    head = (
        f"- **Zero-shot teams: >= {_pct(PER_ROBOT_SHARE)} of the scripted blend's team reward per "
        f"robot at {' and '.join(map(str, ZERO_SHOT))} robots, trained on 2-4**: "
    )
    if not results:
        return head + f"{verdict.MISSING} (the experiment has not been run)."
    blend = _blend(results)
    trained = {
        label: points
        for label, points in _by_method(results).items()
        if any(p.get("trained_on") == [2, 3, 4] for p in points.values())
    }
    parts, verdicts = [], {}
    for label, points in trained.items():
        checks = []
        for k in ZERO_SHOT:
            p, b = points.get(k), blend.get(k)
            if p is None or b is None or not _finite(p["reward_per_robot"]):
                checks.append((f"{k} robots not evaluated", verdict.MISSING))
            elif not b["reward_per_robot"] > 0:
                checks.append((f"{k} robots: the blend's reward is not positive", verdict.MISSING))
            else:
                share = p["reward_per_robot"] / b["reward_per_robot"]
                gap = verdict.compare(_mean(p), _mean(b), PER_ROBOT_SHARE)
                checks.append(
                    (
                        f"{k} robots {p['reward_per_robot']:.2f} vs {b['reward_per_robot']:.2f} "
                        f"per robot ({_pct(share)}), against the bar: {gap.text(2)}",
                        gap.word,
                    )
                )
        verdicts[label] = verdict.claim(word for _, word in checks)
        parts.append(f"{label}, {verdicts[label]}: " + "; ".join(text for text, _ in checks))
    overall = verdict.any_of(verdicts.values())
    passed = [label for label, v in verdicts.items() if v == verdict.HOLDS]
    if passed:
        overall += f" (by {', '.join(passed)})"
    return head + overall + (f". {'. '.join(parts)}." if parts else " (no policy trained on 2-4).")


def training_sizes(results: dict) -> str:
    """Each method trained on 3 robots against the same method trained on 2-4, reward per robot
    at every evaluated team size, judged by ``verdict.compare``: the finding in one sentence per
    method, from the numbers."""
    by = _by_method(results)
    lines = []
    for label, fixed in by.items():
        if not label.endswith(" (3)") or f"{label[: -len(' (3)')]} (2-4)" not in by:
            continue
        name = label[: -len(" (3)")]
        mixed = by[f"{name} (2-4)"]
        sizes = [k for k in results["team_sizes"] if k in fixed and k in mixed]
        gaps = {k: verdict.compare(_mean(fixed[k]), _mean(mixed[k])) for k in sizes}
        words = {g.word for g in gaps.values()}
        if not sizes:
            continue
        if words == {verdict.AHEAD}:
            finding = f"ahead at every team size, {sizes[0]} to {sizes[-1]} robots"
        elif words == {verdict.BEHIND}:
            finding = f"behind at every team size, {sizes[0]} to {sizes[-1]} robots"
        else:
            finding = "; ".join(
                f"{word} at {', '.join(str(k) for k in sizes if gaps[k].word == word)} robots"
                for word in (verdict.AHEAD, verdict.WITHIN, verdict.BEHIND, verdict.MISSING)
                if word in words
            )
        lines.append(
            f"- **{name} trained on 3 robots against {name} trained on 2-4** (reward per robot): "
            f"{label} is {finding}. "
            + "; ".join(
                f"{k}: {fixed[k]['reward_per_robot']:.2f} vs {mixed[k]['reward_per_robot']:.2f}, "
                f"{gaps[k].text(2)}"
                for k in sizes
            )
            + "."
        )
    return "\n".join(lines) or "No method was trained both ways."


def relative_rate(point: dict, period: int) -> float:
    """The share of the every-T broadcasts sent: ``broadcast_rate x T``."""
    rate = point.get("broadcast_rate")
    return rate * period if _finite(rate) else math.nan


def beta_target(results: dict | None) -> str:
    """Target 2: at <= 25 % of the every-T broadcasts ICCO keeps >= 90 % of its every-T (beta =
    0) team reward; the best beta at that rate is checked."""
    head = (
        f"- **Adaptive broadcast: at a broadcast rate <= {_pct(RATE_BOUND)} ICCO keeps >= "
        f"{_pct(KEPT_SHARE)} of its every-T team reward**: "
    )
    if not results:
        return head + f"{verdict.MISSING} (the experiment has not been run)."
    period = int(results.get("period", 1))
    points = results.get("beta_sweep", {}).get("points", [])
    base = next((p for p in points if p["beta"] == 0), None)
    if base is None or not _finite(base["reward"]):
        return head + f"{verdict.MISSING} (no beta = 0 point in the sweep)."
    if not base["reward"] > 0:
        return head + (
            f"{verdict.MISSING} (the every-T reward {base['reward']:.1f} is not positive)."
        )
    low = [p for p in points if relative_rate(p, period) <= RATE_BOUND]
    if not low:
        lowest = min(points, key=lambda p: relative_rate(p, period))
        return head + (
            f"{verdict.MISSING} (no beta sent <= {_pct(RATE_BOUND)} of the every-T broadcasts; the "
            f"fewest: {_pct(relative_rate(lowest, period))} at beta = {lowest['beta']:g}: add "
            "larger --betas)."
        )
    best = max(low, key=lambda p: p["reward"])
    share = best["reward"] / base["reward"]
    gap = verdict.compare(_mean(best, "reward"), _mean(base, "reward"), KEPT_SHARE)
    return head + (
        f"{verdict.claim([gap.word])}: beta = {best['beta']:g} sends "
        f"{_pct(relative_rate(best, period))} of the every-T broadcasts (broadcast rate "
        f"{best['broadcast_rate']:.3f} of robot-steps, every T: {base['broadcast_rate']:.3f}) and "
        f"keeps {best['reward']:.1f} of {base['reward']:.1f} ({_pct(share)}; against the bar: "
        f"{gap.text()})."
    )


def targets(results: dict | None) -> str:
    return "\n".join([zero_shot_target(results), beta_target(results)])


def sizes_table(results: dict) -> str:
    """Reward per robot (mean ± std over trials) per method and team size, then team reward."""
    teams = results["team_sizes"]
    by = _by_method(results)
    lines = []
    for metric, title in (("reward_per_robot", "reward per robot"), ("reward", "team reward")):
        lines += [
            f"| {title} | " + " | ".join(f"{k} robot{'s' * (k != 1)}" for k in teams) + " |",
            "|" + "---|" * (len(teams) + 1),
        ]
        for label, points in by.items():
            cells = [
                f"{_num(p[metric], 2 if metric == 'reward_per_robot' else 1)} ± "
                f"{_num(p[metric + '_std'], 2 if metric == 'reward_per_robot' else 1)}"
                if (p := points.get(k))
                else "–"
                for k in teams
            ]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines).rstrip()


def beta_table(results: dict) -> str:
    period = int(results.get("period", 1))
    sweep = results["beta_sweep"]
    base = next((p for p in sweep["points"] if p["beta"] == 0), None)
    lines = [
        f"{sweep.get('policy', 'ICCO (2-4)')} at {sweep['team_size']} robots, T = {period}.",
        "",
        "| beta | team reward | reward per robot | broadcast rate (robot-steps) | "
        "share of every-T broadcasts | share of every-T reward | in quadrant |",
        "|---|---|---|---|---|---|---|",
    ]
    for p in sweep["points"]:
        kept = p["reward"] / base["reward"] if base and base["reward"] > 0 else math.nan
        lines.append(
            f"| {p['beta']:g} | {_num(p['reward'])} ± {_num(p['reward_std'])} | "
            f"{_num(p['reward_per_robot'], 2)} | {_num(p['broadcast_rate'], 3)} | "
            f"{_pct(relative_rate(p, period))} | {_pct(kept)} | {_num(p.get('in_quadrant'), 2)} |"
        )
    return "\n".join(lines)


def plot_sizes(results: dict, path: Path) -> Path:
    """Reward per robot against team size: trained policies solid, references dashed; the
    training sizes of the 2-4 group shaded."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.0, 3.8))
    ax = fig.subplots()
    ax.axvspan(1.75, 4.25, color="0.92", zorder=0, label="trained on (2-4)")
    for label, points in _by_method(results).items():
        ks = sorted(points)
        reference = points[ks[0]].get("kind") == "reference"
        ax.errorbar(
            ks,
            [points[k]["reward_per_robot"] for k in ks],
            yerr=[points[k]["reward_per_robot_std"] for k in ks],
            marker="o" if not reference else "s",
            linestyle="--" if reference else "-",
            capsize=3,
            label=label,
        )
    ax.set_xlabel("team size (robots)")
    ax.set_ylabel("team reward per robot")
    ax.set_xticks(results["team_sizes"])
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path


def plot_beta(results: dict, path: Path) -> Path:
    """Team reward against the share of every-T broadcasts sent, one point per beta; COPA's 13 %
    and the target's 25 % and 90 % marked."""
    from matplotlib.figure import Figure

    period = int(results.get("period", 1))
    points = results["beta_sweep"]["points"]
    fig = Figure(figsize=(6.0, 3.8))
    ax = fig.subplots()
    x = [100 * relative_rate(p, period) for p in points]
    ax.errorbar(
        x,
        [p["reward"] for p in points],
        yerr=[p["reward_std"] for p in points],
        marker="o",
        capsize=3,
        label="ICCO (2-4)",
    )
    for xi, p in zip(x, points):
        ax.annotate(
            f"β={p['beta']:g}",
            (xi, p["reward"]),
            textcoords="offset points",
            xytext=(4, 4),
            fontsize=7,
        )
    ax.axvline(100 * COPA_RATE, color="tab:red", linestyle="--", label="COPA's 13 %")
    ax.axvline(100 * RATE_BOUND, color="0.5", linestyle=":", label="target: <= 25 %")
    base = next((p for p in points if p["beta"] == 0), None)
    if base is not None and _finite(base["reward"]) and base["reward"] > 0:
        ax.axhline(
            KEPT_SHARE * base["reward"], color="0.5", linestyle="-.", label="90 % of every-T reward"
        )
    ax.set_xlabel("share of the every-T broadcasts sent (%)")
    ax.set_ylabel("team reward")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path


def _frames(frames) -> str:
    return f"{frames:,}" if isinstance(frames, int) else "?"


def budget_section(results: dict) -> str:
    m = results.get("machine", {})
    wall = results.get("wall_s", {})
    commands = "\n".join(results.get("commands", []))
    return (
        f"Training budget: `{' '.join(results.get('budget', []))}`, {results.get('frames', 0):,} "
        f"env steps per run (checkpoints at {_frames(results.get('checkpoint_frames'))}), seeds "
        f"{results.get('seeds')}. Evaluation: {results.get('trials')} trials per checkpoint, "
        f"{results.get('steps')} steps per quadrant ({results.get('episode_steps')} per "
        f"episode). Wall time: {wall.get('train', 0) / 60:.1f} min training (this invocation), "
        f"{wall.get('eval', 0) / 60:.1f} min evaluation.\n"
        f"Machine: {m.get('cpu', '?')} ({m.get('cores', '?')} cores), GPU: "
        f"{m.get('gpu') or 'none'}, torch {m.get('torch', '?')}, Python {m.get('python', '?')}, "
        f"{m.get('platform', '?')}.\n\n"
        f"<details><summary>The commands</summary>\n\n```\n{commands}\n```\n\n</details>"
    )


def screen_section(screen: dict | None) -> str:
    """``run.py --beta-screen``'s sweep on checkpoints trained elsewhere, with the broadcast
    target read on it (a screen: not the experiment's own policy)."""
    if not screen:
        return "Not run (`run.py --beta-screen CHECKPOINT...`)."
    target = beta_target(screen).replace("- **Adaptive broadcast", "- **Screen", 1)
    return (
        f"{target}\n\n{beta_table(screen)}\n\nCheckpoints: "
        + ", ".join(f"`{Path(p).parent.name}`" for p in screen["checkpoints"])
        + f"; `{' '.join(screen['eval_overrides'])}`. "
        + f"Command: `{screen['commands'][0]}` (one per beta)."
    )


def trained_section(trained: dict | None, results: dict | None) -> str:
    """``run.py --train-beta B``'s sweep: ICCO (2-4) trained with the threshold, its broadcast
    target read against its own every-T reward and against the beta = 0 policy's."""
    if not trained:
        return "Not run (`run.py --train-beta B`)."
    beta = trained["train_beta"]
    target = beta_target(trained).replace(
        "- **Adaptive broadcast", f"- **Trained at beta = {beta:g}", 1
    )
    period = int(trained.get("period", 1))
    points = trained["beta_sweep"]["points"]
    low = [p for p in points if relative_rate(p, period) <= RATE_BOUND]
    best = max(low, key=lambda p: p["reward"]) if low else None
    base = next(
        (p for p in (results or {}).get("beta_sweep", {}).get("points", []) if p["beta"] == 0),
        None,
    )
    against = first_only = ""
    if best and base and _finite(base["reward"]) and base["reward"] > 0:
        share = best["reward"] / base["reward"]
        gap = verdict.compare(_mean(best, "reward"), _mean(base, "reward"), KEPT_SHARE)
        against = (
            f"\n- **Against the beta = 0 policy's every-T reward** ({base['reward']:.1f}, "
            f"{base['method']}): {verdict.claim([gap.word])}, "
            f"{best['reward']:.1f} at beta = {best['beta']:g} ({_pct(share)}; against the bar: "
            f"{gap.text()})."
        )
    steps = trained.get("episode_steps")
    rate = best["broadcast_rate"] if best else math.nan
    if steps and _finite(rate) and rate <= 1.5 / steps:
        # One z per robot per episode is the first one, at t = 0: nothing after it moved by more
        # than beta, so the agents acted on their first z alone.
        first_only = (
            f"\n- **Read with care:** at beta = {best['beta']:g} a robot receives "
            f"{rate * steps:.1f} z per {steps}-step episode (one z is {1 / steps:.4f} of "
            "robot-steps): little more than the first. This policy's z moves by less than beta "
            "within an episode, so its agents act on their first z alone; the target is read here "
            "on a coordinator that has stopped speaking, not on one that speaks only when it has "
            "something new."
        )
    return (
        f"{target}{against}{first_only}\n\n{beta_table(trained)}\n\n"
        f"Trained: `{trained['train_command']}`, "
        f"seeds {trained['seeds']}, checkpoints at {_frames(trained.get('frames'))} env steps "
        f"({trained.get('train_wall_s', 0) / 60:.1f} min training in this invocation). "
        f"Evaluation: `{' '.join(trained['eval_overrides'])}`, "
        f"`{trained['commands'][0]}` (one per beta)."
    )


def rule(results: dict | None) -> str:
    """How the page's verdicts are read, with its n."""
    n = "n = trials pooled across seeds (each results entry's `trials`)"
    if results and results.get("trials") and results.get("seeds"):
        trials, seeds = results["trials"], len(results["seeds"])
        n += (
            f": {trials} per checkpoint x {seeds} seeds = {trials * seeds} per trained policy, "
            f"{trials} per scripted reference"
        )
    return f"**Verdicts.** {verdict.RULE} {n}."


def render(
    results: dict | None,
    figures: dict[str, str] | None = None,
    screen: dict | None = None,
    trained: dict | None = None,
) -> str:
    """The README for ``results`` (None: not run yet); ``figures`` maps ``sizes`` and ``beta`` to
    the figures' paths relative to the README; ``screen`` is ``beta_screen.json``, ``trained``
    ``beta_trained.json``."""
    figures = figures or {}
    if results is None:
        pending = "Not run yet: run the command above."
        banner = (
            "> **Not run yet at its budget.** The pipeline has been run end to end at a smoke "
            "budget only (`run.py --smoke`, into `multirun/team_size_smoke`); its numbers mean "
            "nothing and are not shown here. Run `python experiments/team_size/run.py` (default "
            "`--budget experiment=repro_cpu`, 12 training runs, two at a time) to fill this page."
        )
        return Template((HERE / "README.template.md").read_text()).substitute(
            banner=banner,
            rule=rule(None),
            budget_args="",
            targets=targets(None),
            training=pending,
            budget=pending,
            sizes=pending,
            beta=pending,
            screen=screen_section(screen),
            trained=trained_section(trained, None),
        )
    banner = (
        "> **Smoke budget: these numbers only show that the pipeline runs end to end; the policies "
        "have learned nothing. Re-run without `--smoke` for results.**"
        if results.get("smoke")
        else ""
    )
    budget_args = (
        "--smoke"
        if results.get("smoke")
        else " ".join(shlex.quote(a) for a in ["--budget", *results.get("budget", [])])
    )
    sizes = sizes_table(results)
    if "sizes" in figures:
        sizes += f"\n\n![reward per robot against team size]({figures['sizes']})"
    beta = beta_table(results)
    if "beta" in figures:
        beta += f"\n\n![team reward against broadcast rate]({figures['beta']})"
    return Template((HERE / "README.template.md").read_text()).substitute(
        banner=banner,
        rule=rule(results),
        budget_args=budget_args,
        targets=targets(results),
        training=training_sizes(results),
        budget=budget_section(results),
        sizes=sizes,
        beta=beta,
        screen=screen_section(screen),
        trained=trained_section(trained, results),
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("results", type=Path, nargs="?", default=HERE / "results.json")
    parser.add_argument("--readme", type=Path, default=HERE / "README.md")
    args = parser.parse_args(argv)
    screen_path = args.results.with_name("beta_screen.json")
    screen = json.loads(screen_path.read_text()) if screen_path.is_file() else None
    trained_path = args.results.with_name("beta_trained.json")
    trained = json.loads(trained_path.read_text()) if trained_path.is_file() else None
    if not args.results.is_file():
        args.readme.write_text(render(None, screen=screen, trained=trained))
        print(f"{args.results} not found: wrote {args.readme} as not run yet")
        return 0
    results = json.loads(args.results.read_text())
    folder = args.readme.parent / "figures"
    made = {
        "sizes": plot_sizes(results, folder / "reward_per_robot.png"),
        "beta": plot_beta(results, folder / "beta_sweep.png"),
    }
    rel = {k: str(p.relative_to(args.readme.parent)) for k, p in made.items()}
    args.readme.write_text(render(results, rel, screen, trained))
    print(f"wrote {args.readme} and {', '.join(rel.values())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
