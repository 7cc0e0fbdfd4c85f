"""How the planner read an instruction, in the few words a live page shows.

* :func:`short_reason`: a fall-back's reason, its first clause;
* :func:`planner_reading`: the planner's reading (its reply's ``movement_strategy``);
* :func:`explain`: what a newcomer needs beside them: with the offline rule planner, the phrases
  it understands when it did not understand an instruction (``understood``) and the words of an
  instruction it understood that changed nothing in its reading (``unused``: "go right avoiding
  the invader" is read as "defend home", and "right" and "avoiding" are not used); with any
  planner, a hint when its reason names a setting (``hint``).

The rule planner is a word matcher (:mod:`icco_torchrl.instructions.planner`): a word is unused
when the instruction without it reads the same (:func:`~icco_torchrl.instructions.planner.parse`
gives the same intent), so the answer is the planner's own, whatever its word lists hold.
"""

from __future__ import annotations

import re

from icco_torchrl.instructions.llm import last_json_object
from icco_torchrl.instructions.planner import UnknownInstruction, is_offline, parse

MAX_READING = 300  # characters of the planner's reading kept for display
MAX_REASON = 120  # characters of a fall-back's reason kept for display (its first clause)
MAX_UNUSED = 12  # unused different words listed at most
# Words nobody expects a formation from: never listed as unused.
FILLER = frozenset(
    "a an the to and at in on of for do with into onto toward towards please go move head now "
    "then out all you your team robots robot everyone everybody".split()
)
TAP_HINT = (
    "the task-aligned prompt gives the planner the resources and the invader: start the "
    "command with llm.prompt=tap"
)
# The offline rule planner labels its strategy; the reading is what follows the label.
_RULE_LABEL = re.compile(r"^Rule planner \(not an LLM\):\s*")
_UNDERSTOOD = "; understood: "  # how the rule planner lists what it understands
_PUNCTUATION = "\"'.,;:!?()[]{}\u201c\u201d\u2018\u2019"


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


def planner_reading(raw: str | None) -> str | None:
    """The planner's reading of an instruction: the ``movement_strategy`` of its JSON reply
    (without the offline rule planner's label), or None when the reply has none."""
    reply = last_json_object(raw) if raw else None
    strategy = reply.get("movement_strategy") if reply else None
    if not isinstance(strategy, str) or not strategy.strip():
        return None
    reading = _RULE_LABEL.sub("", " ".join(strategy.split())).rstrip(".")
    return reading if len(reading) <= MAX_READING else reading[: MAX_READING - 3] + "..."


def is_rule_planner(planner) -> bool:
    """Whether ``planner`` (an ``LLMPlanner``) answers with the offline rule planner."""
    return is_offline(str(getattr(planner, "model", "")))


def _intent(text: str, half: float):
    try:
        return parse(text, half)
    except UnknownInstruction:
        return None


def _without(tokens: list[str], *drop: int) -> str:
    return " ".join(t for k, t in enumerate(tokens) if k not in drop)


def unused_words(instruction: str, half: float) -> list[str]:
    """The words of ``instruction`` the rule planner's reading does not use, at most
    ``MAX_UNUSED`` (``FILLER`` words are not listed); empty when it does not understand it.

    A word is unused when the instruction reads the same without it, and it is no stand-in for
    another: a word that takes over when another goes ("collect the resources": either word
    alone reads as collecting) is used."""
    tokens = instruction.split()
    reading = _intent(instruction, half)
    if reading is None:
        return []
    same = [k for k in range(len(tokens)) if _intent(_without(tokens, k), half) == reading]
    together = _intent(_without(tokens, *same), half) == reading  # none stands in for another
    unused, seen = [], set()
    for k in same:
        word = tokens[k].strip(_PUNCTUATION)
        if not word or word.lower() in FILLER | seen:
            continue
        seen.add(word.lower())  # a word said twice is judged (and listed) once
        if together or all(
            _intent(_without(tokens, j, k), half) == reading for j in same if j != k
        ):
            unused.append(word)
        if len(unused) == MAX_UNUSED:
            break
    return unused


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
