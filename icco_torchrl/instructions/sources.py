"""Language instructions as a waypoint source: :class:`LLMSource` plans an instruction into
waypoints.

The other sources (random walk, quadrant reference, fixed waypoints) and their base class live
in :mod:`icco_torchrl.envs.waypoints` and are exported from :mod:`icco_torchrl.envs`.
"""

from __future__ import annotations

import copy

import numpy as np
import torch

from icco_torchrl.envs.waypoints import InstructionSource, base_env
from icco_torchrl.instructions.llm import PROMPTS, LLMPlanner


class LLMSource(InstructionSource):
    """A language instruction, planned into waypoints by :class:`LLMPlanner` for each env.

    As in the paper, the LLM is prompted once when the instruction is given (``reset``), with
    the robots' current positions; ``replan_every`` re-prompts every that many steps instead.
    ``prompt`` picks the paper's plain prompt or the task-aligned one of QMIX-TAP ("tap"), which
    also shows the resources and the active invaders. Bad replies are the planner's business
    (retry, then fall back); ``stats`` counts ``plans``, ``failures`` (rejected attempts),
    ``fallbacks`` and ``cache_hits``, and ``errors`` keeps the fallback reasons. With
    ``strict=True`` a fallback raises ``ValueError`` naming the instruction instead: for a
    deterministic planner, a refusal means the instruction is not understood, not noise.
    """

    def __init__(
        self,
        planner: LLMPlanner,
        instruction: str,
        prompt: str | None = None,
        replan_every: int | None = None,
        strict: bool = False,
    ):
        if not isinstance(instruction, str) or not instruction.strip():
            raise ValueError(f"instruction must be a non-empty string, got {instruction!r}")
        if prompt is not None and prompt not in PROMPTS:
            raise ValueError(f"prompt must be one of {PROMPTS}, got {prompt!r}")
        if replan_every is not None and (not isinstance(replan_every, int) or replan_every < 1):
            raise ValueError(
                f"replan_every must be a positive integer or None, got {replan_every!r}"
            )
        if prompt is not None and prompt != planner.prompt:
            planner = copy.copy(planner)  # shares the cache and counters; only the prompt differs
            planner.prompt = prompt
        self.planner, self.instruction, self.replan_every, self.strict = (
            planner,
            instruction.strip(),
            replan_every,
            strict,
        )
        self.stats = {"plans": 0, "failures": 0, "fallbacks": 0, "cache_hits": 0}
        self.errors: list[str] = []
        self._pending: torch.Tensor | None = None

    @property
    def prompt(self) -> str:
        return self.planner.prompt

    def reset(self, env, td):
        self._pending = self.plan(env)

    def __call__(self, env, td, step):
        if step == 0 and self._pending is not None:
            waypoints, self._pending = self._pending, None
            return waypoints
        if step == 0 or (self.replan_every and step % self.replan_every == 0):
            return self.plan(env)
        return None

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


def language_schedule(
    planner: LLMPlanner,
    instructions: list[str],
    steps: int,
    *,
    replan_every: int | None = None,
    strict: bool = False,
) -> list:
    """One segment of ``steps`` steps per instruction, each an :class:`LLMSource` (a fresh one per
    call: sources keep counters). The schedule format of
    :func:`~icco_torchrl.evaluation.protocols.run_schedule`."""
    return [
        (text, LLMSource(planner, text, replan_every=replan_every, strict=strict), steps)
        for text in instructions
    ]
