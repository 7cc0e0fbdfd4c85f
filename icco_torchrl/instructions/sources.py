"""Language instructions as a waypoint source: :class:`LLMSource` plans an instruction into
routes and serves them (:mod:`icco_torchrl.instructions.serving`).

The other sources (random walk, quadrant reference, fixed waypoints) and their base class live
in :mod:`icco_torchrl.envs.waypoints` and are exported from :mod:`icco_torchrl.envs`.
"""

from __future__ import annotations

import copy
import re

import numpy as np
import torch

from icco_torchrl.envs.routes import DEFAULT_STEP, check_step
from icco_torchrl.envs.waypoints import PLAN_INTERFACES, InstructionSource, base_env, refresh_mask
from icco_torchrl.instructions.llm import PROMPTS, LLMPlanner, last_json_object
from icco_torchrl.instructions.serving import PlanServer


class LLMSource(InstructionSource):
    """A language instruction, planned into routes by :class:`LLMPlanner` and served to the team.

    The planner is asked once per env when the instruction is given (``reset``), with the
    robots' positions then: one request per instruction and episode, as in the paper ("each time
    a language instruction was given, the prompt was re-fed to the LLM"). Its waypoints are each
    robot's route, the last one its slot (:attr:`slots`); at every waypoint refresh, on the env's
    clock, :class:`~icco_torchrl.instructions.serving.PlanServer` turns them into K waypoints from
    where each robot is now (``plan="served"``, ``step`` metres apart). ``plan="fixed"`` writes
    the planner's waypoints once and keeps them (a comparison only).

    ``prompt`` picks the paper's plain prompt or the task-aligned one of QMIX-TAP ("tap"), which
    also shows the resources and the active invaders. Bad replies are the planner's business
    (retry, then fall back); ``stats`` counts ``plans`` (requests), ``failures`` (rejected
    attempts), ``fallbacks`` and ``cache_hits``, and ``errors`` keeps the fallback reasons; a
    fallback keeps each robot's previous waypoints as its route. ``reading`` is the planner's
    reading of the instruction (its first reply's movement strategy). With ``strict=True`` a
    fallback raises ``ValueError`` naming the instruction instead: for a deterministic planner,
    a refusal means the instruction is not understood, not noise.
    """

    def __init__(
        self,
        planner: LLMPlanner,
        instruction: str,
        prompt: str | None = None,
        strict: bool = False,
        plan: str = "served",
        step: float = DEFAULT_STEP,
    ):
        if not isinstance(instruction, str) or not instruction.strip():
            raise ValueError(f"instruction must be a non-empty string, got {instruction!r}")
        if prompt is not None and prompt not in PROMPTS:
            raise ValueError(f"prompt must be one of {PROMPTS}, got {prompt!r}")
        if plan not in PLAN_INTERFACES:
            raise ValueError(f"plan must be one of {PLAN_INTERFACES}, got {plan!r}")
        if prompt is not None and prompt != planner.prompt:
            planner = copy.copy(planner)  # shares the cache and counters; only the prompt differs
            planner.prompt = prompt
        self.planner, self.instruction, self.strict = planner, instruction.strip(), strict
        self.interface, self.step = plan, check_step(step)
        self.stats = {"plans": 0, "failures": 0, "fallbacks": 0, "cache_hits": 0}
        self.errors: list[str] = []
        self.reading: str | None = None
        self.server: PlanServer | None = None

    @property
    def prompt(self) -> str:
        return self.planner.prompt

    @property
    def slots(self) -> torch.Tensor | None:
        """``[B, N, 2]``: each robot's slot under the plan in force (None before a plan)."""
        return None if self.server is None else self.server.slots

    def reset(self, env, td):
        raw = base_env(env)
        self.server = PlanServer(raw.n_waypoints, self.step)
        self.server.set_plan(raw.pos, self.plan(env))

    def __call__(self, env, td, step):
        raw = base_env(env)
        if self.interface == "fixed":
            return self.server.routes[..., 1:, :] if step == 0 else None
        due = refresh_mask(raw, step, raw.waypoint_interval)
        if not bool(due.any()):
            return None
        return torch.where(due[:, None, None, None], self.server.serve(raw.pos), raw.waypoints)

    def plan(self, env) -> torch.Tensor:
        """Ask the planner once per env; ``[B, N, K, 2]`` waypoints on the env's device."""
        env = base_env(env)
        if self.planner.n_waypoints != env.n_waypoints:
            raise ValueError(
                f"the planner gives {self.planner.n_waypoints} waypoints per robot, the env uses "
                f"{env.n_waypoints} (set llm.n_waypoints)"
            )
        pos, previous = env.pos.cpu().numpy(), env.waypoints.cpu().numpy()
        res, inv, active = (
            env.res_pos.cpu().numpy(),
            env.inv_pos.cpu().numpy(),
            env.inv_active.cpu().numpy(),
        )
        plans = []
        for b in range(env.num_envs):  # one request per env: each has its own configuration
            # Resources and the invader on the field reach the model only through the "tap" prompt.
            result = self.planner.plan(
                self.instruction,
                pos[b],
                previous=previous[b],
                resources=res[b],
                invader=inv[b][active[b]],
            )
            self._count(result)
            if self.reading is None and result.ok:
                self.reading = planner_reading(getattr(result, "raw", None))
            plans.append(result.waypoints)
        return torch.as_tensor(np.stack(plans), device=env.device)

    def _count(self, result) -> None:
        self.stats["plans"] += 1
        self.stats["cache_hits"] += int(result.cached)
        self.stats["failures"] += result.attempts if not result.ok else max(result.attempts - 1, 0)
        if not result.ok:
            self.stats["fallbacks"] += 1
            self.errors.append(result.error or "unknown error")
            if self.strict:
                raise ValueError(
                    f"instruction {self.instruction!r} could not be planned by "
                    f"{self.planner.model}: {result.error}"
                )


def split_instructions(text: str) -> list[str]:
    """``"Go right; Move top"`` -> ``["Go right", "Move top"]``; empty parts are an error."""
    parts = [part.strip() for part in text.split(";")]
    if not text.strip() or not all(parts):
        raise ValueError(f'instruction {text!r} has an empty part: give e.g. "Go right; Move top"')
    return parts


MAX_READING = 300  # characters of a planner's reading kept (a page shows it)
# The offline rule planner labels its strategy; the reading is what follows the label.
_RULE_LABEL = re.compile(r"^Rule planner \(not an LLM\):\s*")


def planner_reading(raw: str | None) -> str | None:
    """The planner's reading of an instruction: the ``movement_strategy`` of its JSON reply
    (without the offline rule planner's label), or None when the reply has none."""
    reply = last_json_object(raw) if raw else None
    strategy = reply.get("movement_strategy") if reply else None
    if not isinstance(strategy, str) or not strategy.strip():
        return None
    reading = _RULE_LABEL.sub("", " ".join(strategy.split())).rstrip(".")
    return reading if len(reading) <= MAX_READING else reading[: MAX_READING - 3] + "..."


def language_schedule(
    planner: LLMPlanner,
    instructions: list[str],
    steps: int,
    *,
    strict: bool = False,
    plan: str = "served",
    step: float = DEFAULT_STEP,
) -> list:
    """One segment of ``steps`` steps per instruction, each an :class:`LLMSource` (a fresh one per
    call: sources keep counters). The schedule format of
    :func:`~icco_torchrl.evaluation.protocols.run_schedule`."""
    return [
        (text, LLMSource(planner, text, strict=strict, plan=plan, step=step), steps)
        for text in instructions
    ]
