"""Offline rule-based waypoint planner: the default, network-free "LLM" backend.

This is NOT a language model. It is a small deterministic program that matches
words and patterns in an instruction and turns them into formations. It exists
so that evaluation, tests and CI run exactly the code path a real model uses
(prompt -> ``litellm.completion`` -> JSON reply -> validation) without a network,
an API key or model weights, and so that results with it are reproducible.

It understands a closed set of instruction families (see :func:`parse`):

- directions: "go right", "move top", "head to the bottom left", "north-east":
  a line across the field on that side (perpendicular to the direction);
- centre / gathering: "gather center", "regroup at home", "come together":
  a tight cluster at the centre (or at the named side / point, or, with no
  place named, at the team's centroid);
- spreading: "spread out", "fan out", "disperse": well-separated points on a
  large circle around home, each agent moving radially away from the centre;
- quadrants, standard maths convention: 1 = (x>0, y>0), 2 = (x<0, y>0),
  3 = (x<0, y<0), 4 = (x>0, y<0): a small circle at the quadrant's centre;
- named points: "go to (1, -2)", "x=1, y=-2": a cluster at that point;
- formations: "line" (horizontal / vertical), "circle" / "ring", at the
  named place or at home;
- holding: "stop", "stay (put)", "hold position": the current positions;
- task orders (only meaningful with the task-aligned prompt, which carries the
  positions): "collect the resources", "intercept the invader", "do the task".

Anything else (including negated orders such as "don't go left", which a word
matcher would get backwards) raises :class:`UnknownInstruction`; the litellm
provider turns that into a machine-readable ``{"error": ...}`` reply.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

PROVIDER = "offline"
DEFAULT_MODEL = f"{PROVIDER}/rule-planner"

# Formation geometry, as fractions of the half field width h.
SIDE_OFFSET = 0.7  # a line "on the right" sits at x = 0.7 h
DIAGONAL_OFFSET = 0.75  # "top right" is centred at (0.75 h, 0.75 h), inside the corner
LINE_SPACING = 0.5  # at most 0.5 h between neighbours on a line ...
LINE_EXTENT = 1.4  # ... and the whole line at most 1.4 h long
CORNER_SPACING = 0.6  # metres between neighbours on a diagonal line (it sits in a corner)
SPREAD_RADIUS = 0.85  # "spread out": circle of radius 0.85 h around home
CIRCLE_RADIUS = 0.5  # "form a circle" around home
LOCAL_RADIUS = 0.25  # a circle at a quadrant or off-centre place
CLUSTER_RADIUS = 0.25  # metres; tight but agents (radius ~0.15 m) do not overlap
GUARD_RADIUS = 0.6  # metres; the ring around home for "defend home"
DETOUR_RADIUS = 1.5  # metres; a resource this close is worth a detour under the task-aligned prompt

_SUPPORTED = (
    "directions (left/right/up/down/top/bottom, diagonals), quadrant 1-4, points '(x, y)', "
    "gather/centre/home, spread out, line, circle, stop/hold, "
    "task orders (collect resources, intercept the invader, do the task)"
)


class UnknownInstruction(ValueError):
    """The rule planner cannot map this instruction to a formation."""


def _words(pattern: str) -> re.Pattern[str]:
    return re.compile(rf"\b(?:{pattern})\b")


_DIRECTION = {
    "right": _words(r"right(?:wards?)?|east(?:wards?)?"),
    "left": _words(r"left(?:wards?)?|west(?:wards?)?"),
    "up": _words(r"up(?:wards?)?|top|north(?:wards?)?|upper|above"),
    "down": _words(r"down(?:wards?)?|bottom|south(?:wards?)?|lower|below"),
}
_CENTRE = _words(r"cent(?:er|re)|central|middle|midfield|home|origin|base")
_SPREAD = _words(
    r"spread|fan|disperse|scatter|split|break|apart|separate|expand|distribute|cover|widen"
    r"|away from each other"
)
_GATHER = _words(
    r"gather|converge|together|regroup|assemble|rally|cluster|huddle|meet|bunch|unite"
    r"|congregate|convene|return|come back|close in"
)
_LINE = _words(r"line|row|column|file|queue|rank")
_CIRCLE = _words(r"circle|ring|encircle|surround")
_HORIZONTAL = _words(r"horizontal(?:ly)?")
_VERTICAL = _words(r"vertical(?:ly)?")
_HOLD = _words(r"stop|stay(?: put)?|halt|hold|freeze|wait|remain|stand still")
# Words that only name a formation or a place's shape: read when a formation or a place is.
_FORMATION_VERB = _words(r"form|make|create|arrange|take|get|position|place|line up")
_PLACE_NOUN = _words(r"side|edge|corner|border|end|part|half|area|region|zone|wall")
# Verbs that make a task order of a sentence even beside a place ("defend home"); the task's
# nouns alone ("the invader") make one only when no formation or place is named.
_TASK_VERB = _words(
    r"collect|pick|grab|fetch|harvest|defend|protect|guard|intercept|chase|attack|catch"
)
_NEGATION = _words(r"don't|dont|do not|never|avoid|not|no longer")
_COLLECT = _words(r"collect|pick|grab|fetch|harvest|resources?")
_DEFEND = _words(r"defend|protect|guard|intercept|invaders?|intruders?|enemy|enemies")
_WHOLE_TASK = _words(r"task|mission|job|objective|rewards?")
# "line up", "split up", "slow down": "up"/"down" is a particle there, not a direction.
_PARTICLE = re.compile(
    r"\b(line|lining|lined|set|group|bunch|team|pick|gather|join|meet|link|pair|hurry|speed|clump"
    r"|huddle|cluster|split|break|wrap|round|mix|open)\s+up\b"
    r"|\b(calm|slow|settle|sit|shut|narrow)\s+down\b"
)
_NOT_RIGHT = re.compile(r"\ball right\b|\bright (?:now|away)\b")
_HOLD_NEGATED = re.compile(r"\b(?:don't|dont|do not)\s+move\b")

_NUM = r"[-+]?\d+(?:\.\d+)?"
_POINT = re.compile(
    rf"\(\s*({_NUM})\s*,\s*({_NUM})\s*\)|\bto\s+({_NUM})\s*,\s*({_NUM})\b"
    rf"|\bx\s*=\s*({_NUM})\s*,?\s*(?:and\s+)?y\s*=\s*({_NUM})"
)
_QUADRANT_NAMES = {
    "1": 1, "one": 1, "i": 1, "first": 1, "1st": 1,
    "2": 2, "two": 2, "ii": 2, "second": 2, "2nd": 2,
    "3": 3, "three": 3, "iii": 3, "third": 3, "3rd": 3,
    "4": 4, "four": 4, "iv": 4, "fourth": 4, "4th": 4,
}  # fmt: skip
_QUADRANT = (
    re.compile(r"\bquadrant\s*(?:#|no\.?|number)?\s*(\w+)\b"),  # "quadrant 2", "quadrant II"
    re.compile(r"\b(\w+)\s+quadrant\b"),  # "second quadrant"
    re.compile(r"\bq([1-4])\b"),  # "q2"
)
# Standard maths numbering of the quadrants, counter-clockwise from (+, +).
_QUADRANT_SIGNS = {1: (1.0, 1.0), 2: (-1.0, 1.0), 3: (-1.0, -1.0), 4: (1.0, -1.0)}


@dataclass(frozen=True)
class Intent:
    """What an instruction asks for: a formation kind placed at an anchor.

    ``kind`` is one of line, cluster, circle, spread, hold, task. ``anchor`` is
    the formation centre in metres (None: the team's centroid for a cluster).
    ``axis`` is the unit direction a line runs along. ``radius`` is in metres.
    """

    kind: str
    anchor: tuple[float, float] | None = None
    axis: tuple[float, float] = (1.0, 0.0)
    radius: float = 0.0
    collect: bool = False
    defend: bool = False
    description: str = ""
    direction: tuple[float, float] = (0.0, 0.0)  # the side or corner named, if any
    words: frozenset[str] = frozenset()  # the instruction's words this reading rests on


def _quadrant(text: str) -> int | None:
    for pattern in _QUADRANT:
        for match in pattern.finditer(text):
            if match.group(1) in _QUADRANT_NAMES:
                return _QUADRANT_NAMES[match.group(1)]
    return None


def _point(text: str) -> tuple[float, float] | None:
    match = _POINT.search(text)
    if match is None:
        return None
    x, y = [float(group) for group in match.groups() if group is not None]
    return x, y


def _direction(text: str, instruction: str) -> tuple[float, float]:
    found = {name: bool(pattern.search(text)) for name, pattern in _DIRECTION.items()}
    if (found["right"] and found["left"]) or (found["up"] and found["down"]):
        raise UnknownInstruction(f"ambiguous instruction {instruction!r}: opposite directions")
    return float(found["right"]) - float(found["left"]), float(found["up"]) - float(found["down"])


def _side_anchor(direction: tuple[float, float], half: float) -> tuple[float, float]:
    dx, dy = direction
    offset = (DIAGONAL_OFFSET if dx and dy else SIDE_OFFSET) * half
    return dx * offset, dy * offset


def _hits(pattern: re.Pattern[str], text: str) -> set[str]:
    """The words of ``text`` that ``pattern`` matched."""
    return {word for match in pattern.finditer(text) for word in match.group(0).split()}


def _task_intent(text: str, words: set[str]) -> Intent | None:
    whole = bool(_WHOLE_TASK.search(text))
    collect = whole or bool(_COLLECT.search(text))
    defend = whole or bool(_DEFEND.search(text))
    if not (collect or defend):
        return None
    parts = [p for p, on in (("collect resources", collect), ("defend home", defend)) if on]
    used = set(words) | _hits(_WHOLE_TASK, text) | _hits(_COLLECT, text) | _hits(_DEFEND, text)
    used |= _hits(_CENTRE, text) if defend else set()  # "defend home": home is what is defended
    return Intent(
        "task", collect=collect, defend=defend, description=" and ".join(parts),
        words=frozenset(used),
    )  # fmt: skip


def _line_axis(text: str, direction: tuple[float, float]) -> tuple[float, float]:
    """Lines run across the named direction (a "right" line is vertical), unless told otherwise."""
    dx, dy = direction
    if _HORIZONTAL.search(text):
        return 1.0, 0.0
    if _VERTICAL.search(text) or (dx and not dy):
        return 0.0, 1.0
    if dx and dy:
        return -dx / np.sqrt(2.0), dy / np.sqrt(2.0)
    return 1.0, 0.0


def _place_name(direction: tuple[float, float]) -> str:
    dx, dy = direction
    names = [
        ("top" if dy > 0 else "bottom") if dy else "",
        ("right" if dx > 0 else "left") if dx else "",
    ]
    return "the " + " ".join(name for name in names if name) + " side"


def _normalise(instruction: str) -> str:
    text = _NOT_RIGHT.sub(" ", instruction.lower().replace("\u2019", "'"))
    text = _PARTICLE.sub(lambda m: m.group(1) or m.group(2), text)
    text = re.sub(r"\b(north|south)[\s-]?(east|west)\b", r"\1 \2", text)
    return _HOLD_NEGATED.sub("hold", text)


def _place(
    text: str,
    point: tuple[float, float] | None,
    quadrant: int | None,
    direction: tuple[float, float],
    half: float,
) -> tuple[tuple[float, float] | None, str]:
    """``(anchor, place name)`` named by the text: point > quadrant > direction > centre."""
    if point is not None:
        return point, f"point ({point[0]:g}, {point[1]:g})"
    if quadrant is not None:
        sx, sy = _QUADRANT_SIGNS[quadrant]
        return (sx * half / 2, sy * half / 2), f"quadrant {quadrant}"
    if direction != (0.0, 0.0):
        return _side_anchor(direction, half), _place_name(direction)
    if _CENTRE.search(text):
        return (0.0, 0.0), "the centre"
    return None, ""


def parse(instruction: str, half: float) -> Intent:
    """Map an instruction to an :class:`Intent`, or raise :class:`UnknownInstruction`.

    The place (point > quadrant > direction > centre) and the formation words
    are found independently and then combined, so "gather at the top" and
    "line up in quadrant 2" work without listing every combination. A task verb
    ("defend", "collect") makes a task order; the task's nouns alone ("the
    invader") make one only when no formation or place is named, so "form a
    line at the bottom while avoiding the invader" is a line (with "avoiding"
    and "invader" left unread: :attr:`Intent.words` says what was read).
    """
    text = _normalise(instruction)
    if _NEGATION.search(text):
        raise UnknownInstruction(f"negated instruction {instruction!r} is not supported")
    point, quadrant = _point(text), _quadrant(text)
    direction = _direction(text, instruction)
    anchor, place = _place(text, point, quadrant, direction, half)
    shaped = any(p.search(text) for p in (_LINE, _SPREAD, _CIRCLE, _GATHER, _HOLD))
    named = point is not None or quadrant is not None or direction != (0.0, 0.0)
    words = _place_words(text, point, quadrant, direction, anchor)
    task = _task_intent(text, words)
    if task is not None and (_TASK_VERB.search(text) or _WHOLE_TASK.search(text) or not (
            shaped or named)):  # fmt: skip
        return task
    intent = _formation(text, anchor, place, direction, point, quadrant, half)
    if intent is None:
        raise UnknownInstruction(f"unknown instruction: {instruction!r}; understood: {_SUPPORTED}")
    used = words | _hits(_FORMATION_VERB, text) | (_hits(_PLACE_NOUN, text) if named else set())
    for pattern in (_LINE, _SPREAD, _CIRCLE, _GATHER, _HOLD, _HORIZONTAL, _VERTICAL):
        used |= _hits(pattern, text)
    said = instruction.lower().replace("\u2019", "'")  # phrases the normalisation folded
    used |= _hits(_PARTICLE, said)
    used |= _hits(_HOLD_NEGATED, said) if intent.kind == "hold" else set()
    return dataclasses.replace(intent, direction=direction, words=frozenset(used))


def _place_words(text, point, quadrant, direction, anchor) -> set[str]:
    """The words that named the place :func:`_place` chose."""
    if point is not None:
        return {w for m in _POINT.finditer(text) for w in m.group(0).split()}
    if quadrant is not None:
        return {w for p in _QUADRANT for m in p.finditer(text) for w in m.group(0).split()}
    if direction != (0.0, 0.0):
        return set().union(*(_hits(p, text) for p in _DIRECTION.values()))
    return _hits(_CENTRE, text) if anchor is not None else set()


def _formation(text, anchor, place, direction, point, quadrant, half) -> Intent | None:
    """The formation the instruction's words ask for at its place."""
    centred = anchor is None or anchor == (0.0, 0.0)
    spread = bool(_SPREAD.search(text))
    sided = direction != (0.0, 0.0) and point is None and quadrant is None
    corner = sided and direction[0] != 0.0 and direction[1] != 0.0

    if _LINE.search(text) or (spread and sided) or (sided and not corner and not (
            _GATHER.search(text) or _CIRCLE.search(text))):  # fmt: skip
        return Intent("line", anchor or (0.0, 0.0), _line_axis(text, direction),
                      description=f"line at {place or 'the centre'}")  # fmt: skip
    if spread and centred:
        return Intent("spread", (0.0, 0.0), radius=SPREAD_RADIUS * half,
                      description="spread radially away from the centre")  # fmt: skip
    if corner and not _CIRCLE.search(text):
        return Intent("cluster", anchor, description=f"gather in {place.replace('side', 'corner')}")
    if _CIRCLE.search(text) or spread:
        radius = (CIRCLE_RADIUS if centred else LOCAL_RADIUS) * half
        return Intent("circle", anchor or (0.0, 0.0), radius=radius,
                      description=f"circle around {place or 'the centre'}")  # fmt: skip
    if _GATHER.search(text) or point is not None or anchor == (0.0, 0.0):
        return Intent("cluster", anchor, description=f"gather at {place or 'the team centroid'}")
    if quadrant is not None:
        return Intent(
            "circle", anchor, radius=LOCAL_RADIUS * half, description=f"move into {place}"
        )
    if _HOLD.search(text):
        return Intent("hold", description="hold the current positions")
    return None


def _ring_slots(positions: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Evenly spaced points on a circle, handed out in the agents' angular order.

    Keeping the cyclic order and rotating the ring to the agents' mean angular
    offset means nobody has to cross another agent's path to reach its slot.
    """
    n = len(positions)
    rel = positions - centre
    angles = np.arctan2(rel[:, 1], rel[:, 0])
    order = np.argsort(angles, kind="stable")
    base = 2.0 * np.pi * np.arange(n) / n
    shift = angles[order] - base
    theta = np.arctan2(np.sin(shift).mean(), np.cos(shift).mean()) + base
    targets = np.empty_like(positions)
    targets[order] = centre + radius * np.stack([np.cos(theta), np.sin(theta)], axis=1)
    return targets


def _line_slots(
    positions: np.ndarray, anchor: np.ndarray, axis: np.ndarray, half: float
) -> np.ndarray:
    """Evenly spaced points along ``axis`` through ``anchor``; agents keep their order along it."""
    n = len(positions)
    spacing = min(LINE_SPACING * half, LINE_EXTENT * half / max(n - 1, 1))
    if axis[0] and axis[1]:  # a diagonal line sits in a corner: keep it there
        spacing = min(spacing, CORNER_SPACING)
    offsets = (np.arange(n) - (n - 1) / 2.0) * spacing
    order = np.argsort(positions @ axis, kind="stable")
    targets = np.empty_like(positions)
    targets[order] = anchor + offsets[:, None] * axis
    return targets


def _intercept(position: np.ndarray, invader: np.ndarray) -> tuple[float, np.ndarray]:
    """Earliest point on the invader's straight path home this agent reaches first.

    Assumes equal speeds (as in the default env). Returns the fraction of the
    invader's path covered at the meeting point (1 = at home) and the point.
    """
    fractions = np.linspace(0.0, 1.0, 33)
    path = invader[None, :] * (1.0 - fractions[:, None])
    reachable = np.linalg.norm(path - position, axis=1) <= fractions * np.linalg.norm(invader)
    index = int(np.argmax(reachable)) if reachable.any() else len(fractions) - 1
    return float(fractions[index]), path[index]


def _task_targets(
    intent: Intent, positions: np.ndarray, resources: np.ndarray, invader: np.ndarray
) -> np.ndarray:
    """One agent intercepts the invader, others take nearest free resources, the rest guard home."""
    if intent.collect and not intent.defend and len(resources) == 0:
        raise UnknownInstruction("collecting needs resource positions: use the task-aligned prompt")
    targets = np.zeros_like(positions)
    free = list(range(len(positions)))
    if intent.defend and len(invader):
        meets = [_intercept(positions[i], invader[0]) for i in free]
        best = min(free, key=lambda i: meets[i][0])
        targets[best] = meets[best][1]
        free.remove(best)
    if intent.collect and len(resources) and free:
        distances = np.linalg.norm(positions[free][:, None] - resources[None], axis=-1)
        collectors = []
        for _ in range(min(len(free), len(resources))):
            row, col = np.unravel_index(np.argmin(distances), distances.shape)
            targets[free[row]] = resources[col]
            collectors.append(free[row])
            distances[row, :] = np.inf
            distances[:, col] = np.inf
        free = [i for i in free if i not in collectors]
    if free:
        targets[free] = _ring_slots(positions[free], np.zeros(2), GUARD_RADIUS)
    return targets


def _targets(intent: Intent, positions: np.ndarray, half: float, resources: np.ndarray,
             invader: np.ndarray) -> np.ndarray:  # fmt: skip
    anchor = np.asarray(intent.anchor if intent.anchor is not None else positions.mean(axis=0))
    n = len(positions)
    if intent.kind == "line":
        return _line_slots(positions, anchor, np.asarray(intent.axis), half)
    if intent.kind in ("spread", "circle"):
        return _ring_slots(positions, anchor, intent.radius)
    if intent.kind == "cluster":
        # Tight, but wide enough that neighbours on the ring stay ~0.35 m apart.
        radius = 0.0 if n == 1 else max(CLUSTER_RADIUS, 0.35 * n / (2.0 * np.pi))
        return _ring_slots(positions, anchor, radius)
    if intent.kind == "task":
        return _task_targets(intent, positions, resources, invader)
    return positions.copy()  # hold


def rule_plan(
    instruction: str,
    positions: np.ndarray,
    *,
    n_waypoints: int,
    half: float,
    resources: np.ndarray | None = None,
    invader: np.ndarray | None = None,
) -> tuple[np.ndarray, str]:
    """Waypoints ``[n_agents, n_waypoints, 2]`` and a one-line movement strategy.

    Waypoint k (1..K) lies the fraction k/K of the way from the agent's position
    to its formation slot, so the trajectory starts next to the agent and ends
    at the slot. Raises :class:`UnknownInstruction` for anything it cannot map.
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    empty = np.zeros((0, 2))
    resources = (
        empty if resources is None else np.asarray(resources, dtype=np.float64).reshape(-1, 2)
    )
    invader = empty if invader is None else np.asarray(invader, dtype=np.float64).reshape(-1, 2)
    intent = parse(instruction, half)
    targets = np.clip(_targets(intent, positions, half, resources, invader), -half, half)
    fractions = np.arange(1, n_waypoints + 1) / n_waypoints
    waypoints = positions[:, None] + fractions[None, :, None] * (targets - positions)[:, None]
    strategy = f"Rule planner (not an LLM): {intent.description}."
    if intent.kind != "task" and (len(resources) or len(invader)):  # the task-aligned prompt
        waypoints, note = _align_with_task(waypoints, positions, resources, invader, half)
        strategy = f"{strategy[:-1]}; {note}."
    return np.clip(waypoints, -half, half), strategy


def _align_with_task(
    waypoints: np.ndarray,
    positions: np.ndarray,
    resources: np.ndarray,
    invader: np.ndarray,
    half: float,
) -> tuple[np.ndarray, str]:
    """Bend an instruction's plan toward the task, as the task-aligned prompt asks an LLM to.

    The robot that reaches the invader's path home first intercepts it; each other robot with a
    resource within ``DETOUR_RADIUS`` of its position goes through it on the first half of its
    waypoints, then on to its instructed slot.
    """
    waypoints = waypoints.copy()
    notes, busy = [], set()
    if len(invader):
        meets = [_intercept(p, invader[0]) for p in positions]
        best = int(np.argmin([m[0] for m in meets]))
        waypoints[best] = meets[best][1]
        busy.add(best)
        notes.append(f"agent_{best} intercepts the invader")
    k = waypoints.shape[1]
    taken: set[int] = set()
    for i in (i for i in range(len(positions)) if i not in busy and len(resources)):
        distance = np.linalg.norm(resources - positions[i], axis=1)
        distance[list(taken)] = np.inf
        j = int(np.argmin(distance))
        if distance[j] <= DETOUR_RADIUS:
            taken.add(j)
            first = max(k // 2, 1)
            waypoints[i, :first] = positions[i] + np.arange(1, first + 1)[:, None] / first * (
                resources[j] - positions[i]
            )
            notes.append(
                f"agent_{i} picks the resource at ({resources[j][0]:.1f}, {resources[j][1]:.1f}) "
                "on the way"
            )
    return waypoints, "; ".join(notes) or "no task detour needed"


# --- litellm provider: the rule planner behind the same API as a real model. -------------

_ORDER = re.compile(r'STRICTLY COMPLY with the following order:\s*(".*")\s*$', re.MULTILINE)


def _tagged_json(tag: str, text: str) -> Any:
    """The JSON value on the last ``TAG: value`` line of the prompt (None when absent)."""
    found = re.findall(rf"^{tag}:\s*(.+?)\s*$", text, re.MULTILINE)
    return json.loads(found[-1]) if found else None


def reply_to(messages: list[dict[str, Any]]) -> str:
    """The planner's JSON reply to a prompt built by :mod:`icco_torchrl.instructions.llm`.

    Reads the machine-readable lines (order, POSITIONS_JSON, FIELD_JSON, ...)
    rather than the prose. A prompt it cannot read, or an instruction it does not
    understand, gets ``{"error": "..."}``, which the caller recognises.
    """
    text = "\n".join(str(m.get("content") or "") for m in messages if m.get("role") == "user")
    orders = _ORDER.findall(text)
    try:
        if not orders:
            raise ValueError("no 'STRICTLY COMPLY with the following order:' line")
        instruction = json.loads(orders[-1])
        positions = np.asarray(_tagged_json("POSITIONS_JSON", text), dtype=np.float64).reshape(
            -1, 2
        )
        half = float(_tagged_json("FIELD_JSON", text)["x"][1])
        n_waypoints = int(_tagged_json("WAYPOINTS_PER_AGENT", text))
        resources = _tagged_json("RESOURCES_JSON", text)
        invader = _tagged_json("INVADER_JSON", text)
    except (TypeError, ValueError, KeyError) as exc:
        return json.dumps({"error": f"rule planner could not read the prompt: {exc}"})
    try:
        waypoints, strategy = rule_plan(instruction, positions, n_waypoints=n_waypoints, half=half,
                                        resources=resources, invader=invader)  # fmt: skip
    except UnknownInstruction as exc:
        return json.dumps({"error": str(exc)})
    reply: dict[str, Any] = {"movement_strategy": strategy}
    reply.update({f"agent_{i}": np.round(w, 3).tolist() for i, w in enumerate(waypoints)})
    return json.dumps(reply)


@functools.cache
def _provider_class() -> type:
    """Built on first use so that importing this module does not import litellm (seconds)."""
    from litellm import CustomLLM
    from litellm.types.utils import ModelResponse

    class RulePlannerLLM(CustomLLM):
        """litellm custom provider answering with the deterministic rule planner (not an LLM)."""

        def __init__(self) -> None:
            super().__init__()
            self.invocations = 0  # lets tests and benchmarks see whether the backend ran

        def completion(self, *args: Any, **kwargs: Any) -> ModelResponse:
            self.invocations += 1
            message = {"role": "assistant", "content": reply_to(kwargs["messages"])}
            choice = {"index": 0, "finish_reason": "stop", "message": message}
            return ModelResponse(model=DEFAULT_MODEL, choices=[choice])

        async def acompletion(self, *args: Any, **kwargs: Any) -> ModelResponse:
            return self.completion(*args, **kwargs)

    return RulePlannerLLM


def register_offline_provider(litellm: Any) -> Any:
    """Make ``offline/...`` models answer with the rule planner; returns the handler.

    Idempotent, and never replaces an existing ``offline`` entry or any other
    provider in ``litellm.custom_provider_map`` (it is global state shared with
    whatever else the process registered).
    """
    for entry in litellm.custom_provider_map:
        if entry.get("provider") == PROVIDER:
            return entry["custom_handler"]
    handler = _provider_class()()
    litellm.custom_provider_map = [
        *litellm.custom_provider_map,
        {"provider": PROVIDER, "custom_handler": handler},
    ]
    return handler


def is_offline(model: str) -> bool:
    """Whether a litellm model name is this offline rule planner."""
    return model.startswith(f"{PROVIDER}/")


FILLER = frozenset(
    "a an the to and at in on of for do with into onto toward towards please go move head now "
    "then out all you your team robots robot everyone everybody".split()
)  # words nobody expects a formation from: never named as not understood
_PUNCTUATION = "\"'.,;:!?()[]{}\u201c\u201d\u2018\u2019"


def unread_words(instruction: str, half: float, limit: int = 12) -> list[str]:
    """The words of ``instruction`` its reading (:func:`parse`) did not rest on, at most
    ``limit`` different ones (not :data:`FILLER`); empty when it is not understood at all.

    "Go right avoiding the invader" is a line at the right side: "avoiding" and "invader" are
    named, since the planner cannot avoid anything and a person must not think it does.

    >>> unread_words("Form a line along the bottom edge while avoiding the invader", 3.25)
    ['along', 'while', 'avoiding', 'invader']
    """
    try:
        read = {_bare(word) for word in parse(instruction, half).words}
    except UnknownInstruction:
        return []
    unread, seen = [], set()
    for token in instruction.split():
        word = token.strip(_PUNCTUATION)
        key = _bare(word)
        if not key or key in FILLER | seen | read:
            continue
        seen.add(key)  # a word said twice is named once
        unread.append(word)
        if len(unread) == limit:
            break
    return unread


def _bare(word: str) -> str:
    return word.lower().replace("\u2019", "'").strip(_PUNCTUATION)


def how_read(instruction: str, half: float) -> str:
    """One line: how the rule planner reads ``instruction``, and a warning naming the words it
    did not understand (:func:`unread_words`).

    >>> how_read("Gather center", 3.25)
    '"Gather center": gather at the centre'
    >>> how_read("Go right quickly", 3.25)
    '"Go right quickly": line at the right side (warning: not understood: quickly)'
    """
    try:
        reading = parse(instruction, half).description
    except UnknownInstruction as err:
        return f"{json.dumps(instruction)}: not understood ({str(err).split('; ')[0]})"
    unread = unread_words(instruction, half)
    warning = f" (warning: not understood: {', '.join(unread)})" if unread else ""
    return f"{json.dumps(instruction)}: {reading}{warning}"


def check_understood(instructions: list[str], half: float) -> None:
    """``ValueError`` naming the first instruction the offline planner does not understand."""
    for text in instructions:
        try:
            parse(text, half)
        except UnknownInstruction as err:
            raise ValueError(f"the offline planner does not understand {text!r}: {err}") from None
