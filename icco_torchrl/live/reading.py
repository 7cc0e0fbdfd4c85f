"""How the planner read an instruction, in the few words a live page shows.

* :func:`short_reason`: a fall-back's reason, its first clause;
* :func:`planner_reading`: the planner's reading (its reply's ``movement_strategy``);
* :func:`explain`: what a newcomer needs beside them: with the offline rule planner, the phrases
  it understands when it did not understand an instruction (``understood``) and the words of an
  instruction it understood that its reading did not rest on (``unused``: "go right avoiding
  the invader" is a line at the right side, and "avoiding" and "invader" are not understood);
  with any planner, a hint when its reason names a setting (``hint``).

The rule planner is a word matcher (:mod:`icco_torchrl.instructions.planner`): its reading
(:func:`~icco_torchrl.instructions.planner.parse`) lists the words it rests on, so the answer is
the planner's own, whatever its word lists hold.
"""

from __future__ import annotations

from icco_torchrl.instructions.planner import UnknownInstruction, is_offline, parse, unread_words
from icco_torchrl.instructions.sources import planner_reading

__all__ = ["explain", "planner_reading", "short_reason", "unused_words", "understood_phrases"]

MAX_REASON = 120  # characters of a fall-back's reason kept for display (its first clause)
MAX_UNUSED = 12  # unused different words listed at most
TAP_HINT = (
    "the task-aligned prompt gives the planner the resources and the invader: start the "
    "command with llm.prompt=tap"
)
_UNDERSTOOD = "; understood: "  # how the rule planner lists what it understands


def short_reason(error: str | None, instruction: str | None = None) -> str | None:
    """A fall-back's reason as a page shows it: its first clause, without the planner's prefix
    or a repeat of the instruction, at most ``MAX_REASON`` characters (the planner's own
    message can list everything it understands, or quote a whole reply)."""
    if not error:
        return error
    text = " ".join(str(error).split()).removeprefix("planner declined: ").split("; ")[0]
    if instruction:
        text = text.replace(f": {instruction!r}", "").replace(f" {instruction!r}", "")
    return text if len(text) <= MAX_REASON else text[: MAX_REASON - 3] + "..."


def is_rule_planner(planner) -> bool:
    """Whether ``planner`` (an ``LLMPlanner``) answers with the offline rule planner."""
    return is_offline(str(getattr(planner, "model", "")))


def unused_words(instruction: str, half: float) -> list[str]:
    """The words of ``instruction`` the rule planner's reading did not rest on, at most
    ``MAX_UNUSED`` (:func:`~icco_torchrl.instructions.planner.unread_words`)."""
    return unread_words(instruction, half, MAX_UNUSED)


def understood_phrases(instruction: str, half: float) -> str | None:
    """What the rule planner understands, as it lists it when it does not understand
    ``instruction``; None when it does, or refuses it for another reason (a negation)."""
    try:
        parse(instruction, half)
    except UnknownInstruction as err:
        phrases = str(err).partition(_UNDERSTOOD)[2]
        return phrases or None
    return None


def _asks_for_tap(planner, error: str | None) -> bool:
    """Whether ``error`` asks for the task-aligned prompt and ``planner`` does not use it."""
    return (
        bool(error) and "task-aligned prompt" in error and getattr(planner, "prompt", "") != "tap"
    )


def explain(planner, instruction: str, half: float, ok: bool, error: str | None) -> dict:
    """The :class:`~icco_torchrl.live.loop.PlannerStatus` fields beside the reading and the
    reason (module docstring): ``understood``, ``unused`` and ``hint``."""
    rule = is_rule_planner(planner)
    return {
        "understood": understood_phrases(instruction, half) if rule and not ok else None,
        "unused": unused_words(instruction, half) if rule and ok else None,
        "hint": TAP_HINT if _asks_for_tap(planner, error) else None,
    }
