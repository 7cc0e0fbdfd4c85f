"""Instruction-schedule protocols: one episode per trial, the instruction changing between segments.

A schedule is a list of ``(segment name, InstructionSource, steps)``. :func:`run_schedule`
plays one greedy episode of ``sum(steps)`` steps in each of ``trials`` parallel envs (the env
batch is the trial batch), writes each source's waypoints before the policy acts, records the
trajectories for figures and computes per-trial, per-segment metrics. The paper's protocols
are schedules: the four-quadrant test (Sec. V-B) is quadrant 1 -> 2 -> 3 -> 4 for 145 steps
each, a language run is one instruction per segment.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from icco_torchrl.envs.waypoints import (
    InstructionSource,
    QuadrantSource,
    RandomWalkSource,
    base_env,
)
from icco_torchrl.evaluation.metrics import step_values, trial_rows
from icco_torchrl.evaluation.placement import region

Schedule = Sequence[tuple[str, InstructionSource, int]]
# Raw-env state recorded before the first step and after every step: [T + 1, B, ...].
STATE_KEYS = ("pos", "carry", "defended", "res_pos", "inv_pos", "inv_active")


@dataclass
class ScheduleRun:
    """What one schedule did: segment layout, trajectories, per-step values and metrics rows.

    ``trajectory[key]`` is ``[T + 1, B, ...]`` for :data:`STATE_KEYS` (index 0 = after reset)
    and ``[T, B, N, K, 2]`` for ``"waypoints"`` (those in force at each step); ``per_step[key]``
    is ``[T, B]``; ``rows`` come from :func:`~icco_torchrl.evaluation.metrics.trial_rows`;
    ``sources`` holds the per-segment counters of sources that keep them (LLM plans, fallbacks).
    """

    names: list[str]
    bounds: list[tuple[int, int]]
    quadrants: list[int | None]
    trajectory: dict[str, np.ndarray]
    per_step: dict[str, np.ndarray]
    rows: list[dict]
    geometry: dict[str, float]
    sources: list[dict] = field(default_factory=list)


def check_schedule(schedule: Schedule, trials: int) -> int:
    """Fail fast on bad input; returns the episode length ``sum(steps)``."""
    if isinstance(trials, bool) or not isinstance(trials, int) or trials < 1:
        raise ValueError(f"trials must be a positive integer, got {trials!r}")
    if not schedule:
        raise ValueError("the schedule is empty: give at least one (name, source, steps) segment")
    for name, source, steps in schedule:
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ValueError(
                f"segment {name!r} has steps={steps!r}; every segment needs a positive integer"
            )
        if not isinstance(source, InstructionSource):
            raise ValueError(f"segment {name!r}: {source!r} is not an InstructionSource")
    return sum(steps for _, _, steps in schedule)


def run_schedule(
    env,
    policy: Callable,
    schedule: Schedule,
    trials: int,
    *,
    on_step: Callable | None = None,
    **labels,
) -> ScheduleRun:
    """Play ``schedule`` once in each of ``trials`` envs, greedily, and measure it.

    ``env`` (a ``ResourceCollectionEnv`` or a ``TransformedEnv`` over one) must have
    ``num_envs == trials``, ``max_steps >= sum(steps)`` and ``waypoint_mode="external"``
    (:func:`schedule_env` builds one from a checkpoint). ``policy`` maps the root TensorDict to
    one with ``("agents", "action")``. ``on_step(env)`` is called after the reset and after
    every step (e.g. to render frames). ``labels`` go into every metrics row.
    """
    total = check_schedule(schedule, trials)
    raw = base_env(env)
    _check_env(raw, trials, total)
    names = [name for name, _, _ in schedule]
    ends = np.cumsum([steps for _, _, steps in schedule]).tolist()
    bounds = list(zip([0, *ends[:-1]], ends))
    states, waypoints, values = _play(env, raw, policy, schedule, on_step)
    trajectory = {key: torch.stack(v).cpu().numpy() for key, v in states.items()}
    trajectory["waypoints"] = torch.stack(waypoints).cpu().numpy()
    per_step = {key: torch.stack([v[key] for v in values]).cpu().numpy() for key in values[0]}
    counters = [
        dict(segment=name, **source.stats)
        for name, source, _ in schedule
        if hasattr(source, "stats")
    ]
    quadrants = [source.quadrant for _, source, _ in schedule]
    return ScheduleRun(
        names,
        bounds,
        quadrants,
        trajectory,
        per_step,
        trial_rows(per_step, names, bounds, **labels),
        _geometry(raw),
        counters,
    )


def _check_env(raw, trials: int, total: int) -> None:
    """Fail fast on an env that cannot play ``trials`` trials of a ``total``-step schedule."""
    if raw.num_envs != trials:
        raise ValueError(
            f"the env runs {raw.num_envs} envs but trials={trials}: build it with num_envs=trials"
        )
    if raw.max_steps < total:
        raise ValueError(
            f"the env stops after {raw.max_steps} steps but the schedule needs {total}: "
            f"build it with max_steps={total}"
        )
    if raw.waypoint_mode != "external":
        raise ValueError(
            "the env regenerates its own waypoints: build it with waypoint_mode='external'"
        )


def _play(
    env, raw, policy: Callable, schedule: Schedule, on_step: Callable | None
) -> tuple[dict[str, list], list, list]:
    """One greedy episode of ``schedule``: the states recorded (:data:`STATE_KEYS`), and per
    step the waypoints in force and the step's metric values."""
    states = {key: [] for key in STATE_KEYS}
    waypoints, values = [], []  # per step: the waypoints in force, the step's metric values

    def record_state():
        for key in STATE_KEYS:
            states[key].append(getattr(raw, key).clone())
        if on_step is not None:
            on_step(raw)

    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        record_state()
        for _, source, steps in schedule:
            source.reset(env, td)
            judge = region(source.instruction, raw.half) if source.instruction else None
            for step in range(steps):
                new = source(env, td, step)
                if new is not None:
                    raw.write_waypoints(td, new)
                waypoints.append(raw.waypoints.clone())
                present = raw.present  # the team the action was chosen for
                td = env.step(policy(td))
                sent = td.get(("agents", "z_sent"), None)  # a coordinator's broadcast this step
                record_state()
                values.append(
                    step_values(
                        raw,
                        td.get("next"),
                        waypoints[-1],
                        source.quadrant,
                        sent,
                        present,
                        slots=source.slots,
                        judge=judge,
                    )  # fmt: skip
                )
                td = step_mdp(td)
    return states, waypoints, values


def _geometry(raw) -> dict[str, float]:
    """The field's half width and the radii of home, resources, robots and invaders."""
    return dict(
        half=raw.half,
        home_radius=raw.home_radius,
        resource_radius=raw.resource_radius,
        agent_radius=raw.agent_radius,
        invader_radius=raw.invader_radius,
    )


def quadrant_schedule(steps: int = 145, seed: int = 0, **source_kwargs) -> list:
    """Paper Sec. V-B: quadrant 1 -> 2 -> 3 -> 4, ``steps`` each (580 steps per episode)."""
    return [
        (f"quadrant {q}", QuadrantSource(q, seed=seed + q, **source_kwargs), steps)
        for q in (1, 2, 3, 4)
    ]


def random_walk_schedule(steps: int = 145, seed: int = 0, **source_kwargs) -> list:
    """The training distribution for one episode: the sanity check of a trained policy."""
    return [("random walk", RandomWalkSource(seed=seed, **source_kwargs), steps)]


PROTOCOLS: dict[str, Callable[..., list]] = {
    "random_walk": random_walk_schedule,
    "quadrants": quadrant_schedule,
}


def schedule_env(
    checkpoint: str | Path,
    total_steps: int,
    trials: int,
    *,
    device: str = "cpu",
    seed: int | None = None,
    broadcast_threshold: float | None = None,
    **env_overrides,
) -> dict:
    """:func:`~icco_torchrl.training.restore.restore` with an env fit for a schedule:
    ``num_envs=trials``, ``max_steps=total_steps``, external waypoints. ``env_overrides`` may
    change other env parameters (``n_agents``: another team size, for acting networks that read
    any team); layout changes are refused there (``CheckpointError``). ``broadcast_threshold``
    replaces the coordinator's beta (None: the checkpoint's)."""
    from icco_torchrl.training.restore import restore  # heavy (networks, Hydra config)

    if isinstance(trials, bool) or not isinstance(trials, int) or trials < 1:
        raise ValueError(f"trials must be a positive integer, got {trials!r}")
    return restore(
        checkpoint,
        num_envs=trials,
        device=device,
        seed=seed,
        broadcast_threshold=broadcast_threshold,
        **{**env_overrides, "max_steps": total_steps, "waypoint_mode": "external"},
    )
