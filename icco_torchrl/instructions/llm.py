"""Language layer: instruction + agent positions -> per-agent waypoints, through litellm.

The policy is trained without an LLM and executed with one (ICCO, "training
without LLM, execution with LLM"): at evaluation this module turns an order
such as "Go right" into K waypoints per agent, the instruction vectors.

- Prompts live in ``prompts/*.txt`` and follow the paper: the field anchored in
  2-D (+x right, +y up), "STRICTLY COMPLY with the following order", and two
  stages, Movement Strategy then Trajectory Generation. ``tap`` is the
  task-aligned prompt (task, rewards, resources, invader) of the QMIX-TAP baseline.
- Both stages live in one JSON object, ``movement_strategy`` first, because a
  strict JSON-schema ``response_format`` leaves a model no room for prose
  outside the JSON. Replies are validated here anyway (providers differ in how
  well they honour a schema) and the last JSON object in the text is used.
- Any litellm model works (``openai/gpt-4o``, ``ollama_chat/llama3.1``, ...);
  API keys are read by litellm from the environment and never touched here.
  The default ``offline/rule-planner`` is a deterministic rule-based planner
  (NOT an LLM, see :mod:`.planner`) registered as a litellm custom provider,
  so the offline path is the same code path as a real model.
- Bad output is a normal event: retried within ``max_retries`` (with the
  reason fed back), then replaced by a fallback and recorded; never raised.
- No reply at all is not: a provider that is unreachable, refuses the key or
  times out on every attempt raises :class:`LLMUnavailable` (one line), so an
  evaluation never silently runs on fallbacks, unless ``fallback_on_error``
  asks for them. Errors that a retry cannot fix (401, 403, 404, 400) are not
  retried. Every ``plan()`` ends within ``deadline_s``, retries included.
- Replies are bounded: one over ``MAX_REPLY_CHARS`` is refused unparsed, the JSON search is
  linear in the reply's length, and error messages and logged replies are cut short, so a
  model that answers with megabytes costs milliseconds and a few lines of log. A ``plan()``
  given a ``cancel`` event stops at the next moment it waits (a newer instruction superseded
  it), and a planner runs at most ``MAX_REQUESTS`` requests at once, abandoned ones included.
"""

from __future__ import annotations

import json
import logging
import os
import re
import reprlib
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from string import Template
from typing import Any

import numpy as np

from .llm_cache import ResponseCache, cache_key
from .planner import DEFAULT_MODEL, register_offline_provider

logger = logging.getLogger(__name__)

PROMPTS = ("plain", "tap")
# Default litellm model per ``backend`` name; any other backend string is taken as a model.
BACKEND_MODELS = {
    "offline": DEFAULT_MODEL,
    "openai": "openai/gpt-4o",
    "ollama": "ollama_chat/llama3.1",
}
ABSURD_FACTOR = (
    10.0  # |coordinate| > ABSURD_FACTOR * field_size: the reply is nonsense, not merely off-field
)
_SHOWN_CHARS = 2000  # a rejected reply shown back to the model is cut to this length
_LOGGED_CHARS = 300  # raw replies in logs are cut to this length
_ERROR_CHARS = 500  # an error message (PlanResult.error, logs) is cut to this length
_VALUE_CHARS = 60  # a bad value quoted in an error message is cut to this length
# A reply longer than this is refused without parsing (a plan for 8 agents is under 2 000).
MAX_REPLY_CHARS = 64 * 1024
# Requests one planner may have running at once, abandoned ones (deadline, cancel) included;
# a further request waits for one of them to end (within the plan's deadline).
MAX_REQUESTS = 2


@dataclass
class PlanResult:
    """Outcome of one planning request.

    ``waypoints`` is always usable ([n_agents, K, 2] float32, inside the field),
    even when ``ok`` is False: it is then the ``fallback`` ("previous" or
    "positions") and ``error`` / ``raw`` say what went wrong.
    """

    waypoints: np.ndarray
    ok: bool
    attempts: int
    fallback: str | None = None
    error: str | None = None
    raw: str | None = None
    cached: bool = False


class ReplyError(ValueError):
    """A reply that cannot be turned into waypoints (worth asking again)."""


class PlannerDeclined(ReplyError):
    """The backend answered ``{"error": ...}``: it says it cannot do this order."""


class LLMUnavailable(RuntimeError):
    """The provider gave no reply at all (unreachable, not authorised, timed out) and
    ``fallback_on_error`` is off."""


class DeadlineExceeded(TimeoutError):
    """A request still running when the plan's ``deadline_s`` ran out."""


class PlanCancelled(RuntimeError):
    """The caller set the plan's ``cancel`` event (a newer instruction superseded it)."""


def _clip(text: str, limit: int) -> str:
    """``text`` cut to ``limit`` characters, ``...`` marking a cut."""
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _quoted(value: Any) -> str:
    """``repr(value)`` cut short for an error message (a reply may hold megabytes): a few items
    of each list and dict, a few levels deep (``reprlib``, which never builds the whole repr)."""
    return _clip(_SHORT_REPR.repr(value), _VALUE_CHARS)


def _short_repr() -> reprlib.Repr:
    short = reprlib.Repr()  # Python 3.11's Repr takes no arguments
    short.maxlevel, short.maxlist, short.maxdict, short.maxtuple = 3, 4, 4, 4
    short.maxstring, short.maxlong, short.maxother = 40, 30, 40
    return short


_SHORT_REPR = _short_repr()


# HTTP statuses that the same request gets again: retrying only spends the deadline.
_FINAL_STATUSES = (400, 401, 403, 404)


def _is_final(exc: BaseException) -> bool:
    """Whether a provider error is final (bad key, no permission, unknown model or URL)."""
    return getattr(exc, "status_code", None) in _FINAL_STATUSES


def _describe(exc: BaseException) -> str:
    """``Type: message (RootCause: message)`` on one line, cut short (provider messages can hold
    whole JSON bodies). The root cause says what litellm's wrapper hides, e.g. "Connection
    refused"."""
    root = exc
    for _ in range(10):  # the chain is short; the bound guards against cycles
        nxt = root.__cause__ or root.__context__
        if nxt is None:
            break
        root = nxt
    text = " ".join(str(exc).split())
    if root is not exc and str(root) not in text:
        text += f" ({type(root).__name__}: {' '.join(str(root).split())})"
    return _clip(f"{type(exc).__name__}: {text}", _ERROR_CHARS)


@cache
def _template(name: str) -> Template:
    return Template(
        (Path(__file__).with_name("prompts") / f"{name}.txt").read_text(encoding="utf-8")
    )


def _litellm() -> Any:
    """Import litellm on first use (it takes seconds) without its network fetch at import."""
    os.environ.setdefault("LITELLM_LOCAL_MODEL_COST_MAP", "True")
    import litellm

    litellm.suppress_debug_info = True
    for name in (
        "LiteLLM",
        "LiteLLM Router",
        "LiteLLM Proxy",
    ):  # else one INFO line per request under Hydra
        logging.getLogger(name).setLevel(logging.WARNING)
    register_offline_provider(litellm)
    return litellm


def _points(values: Any, name: str) -> np.ndarray:
    """An array-like of 2-D points (or None / one point) as a finite float64 [M, 2] array."""
    points = np.zeros((0, 2)) if values is None else np.asarray(values, dtype=np.float64)
    if points.ndim == 1 and points.size == 2:
        points = points[None]
    if points.ndim != 2 or points.shape[1] != 2 or not np.isfinite(points).all():
        raise ValueError(f"{name} must be finite [n, 2] coordinates, got shape {points.shape}")
    return points


def _listing(label: str, points: np.ndarray) -> str:
    return (
        "\n".join(f"- {label}_{i}: ({x:.2f}, {y:.2f})" for i, (x, y) in enumerate(points))
        or "- none"
    )


def _as_json(points: np.ndarray) -> str:
    return json.dumps(np.round(points, 3).tolist())


def _agent_keys(n_agents: int) -> list[str]:
    return [f"agent_{i}" for i in range(n_agents)]


def build_messages(
    instruction: str,
    positions: np.ndarray,
    *,
    prompt: str = "plain",
    n_waypoints: int = 4,
    field_size: float = 6.5,
    resources: np.ndarray | None = None,
    invader: np.ndarray | None = None,
) -> list[dict[str, str]]:
    """System + user messages from ``prompts/{system,prompt}.txt``.

    Positions appear twice: readable lines for the model and a ``POSITIONS_JSON``
    line that the offline planner parses (exactly, instead of guessing from prose).
    """
    half = field_size / 2.0
    keys = _agent_keys(len(positions))
    trajectory = "[" + ", ".join(["[x, y]"] * n_waypoints) + "]"
    example = (
        "{"
        + ", ".join(['"movement_strategy": "..."'] + [f'"{k}": {trajectory}' for k in keys])
        + "}"
    )
    resources, invader = _points(resources, "resources"), _points(invader, "invader")
    user = _template(prompt).substitute(
        x_min=-half,
        x_max=half,
        y_min=-half,
        y_max=half,
        field_json=json.dumps({"x": [-half, half], "y": [-half, half], "home": [0.0, 0.0]}),
        n_agents=len(positions),
        agent_lines=_listing("agent", positions),
        positions_json=_as_json(positions),
        resource_lines=_listing("resource", resources),
        resources_json=_as_json(resources),
        invader_lines=_listing("invader", invader),
        invader_json=_as_json(invader),
        instruction_json=json.dumps(instruction, ensure_ascii=False),
        n_waypoints=n_waypoints,
        agent_keys=", ".join(f'"{k}"' for k in keys),
        example=example,
    )
    return [
        {"role": "system", "content": _template("system").template.strip()},
        {"role": "user", "content": user},
    ]


def response_format(n_agents: int, n_waypoints: int) -> dict[str, Any]:
    """JSON-schema ``response_format``: fixed agent keys, exactly K [x, y] pairs each.

    Fixed keys and item counts bound the reply's length (a schema with an
    open-ended list let small local models ramble until max_tokens).
    """
    pair = {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2}
    trajectory = {"type": "array", "items": pair, "minItems": n_waypoints, "maxItems": n_waypoints}
    keys = _agent_keys(n_agents)
    schema = {
        "type": "object",
        "properties": {"movement_strategy": {"type": "string"}, **{k: trajectory for k in keys}},
        "required": ["movement_strategy", *keys],
        "additionalProperties": False,
    }
    return {
        "type": "json_schema",
        "json_schema": {"name": "waypoints", "strict": True, "schema": schema},
    }


_BRACE_TOKENS = re.compile(r'[{}"]')
_STRING_END = re.compile(r'(?:[^"\\]|\\.)*"', re.DOTALL)


def _braces(text: str) -> list[tuple[int, int]]:
    """Each ``{`` in ``text`` with the index after its matching ``}`` (-1 when unclosed), in one
    pass; inside braces, JSON strings are skipped (outside them, quotes are prose)."""
    found: list[list[int]] = []
    open_: list[list[int]] = []
    pos = 0
    while (match := _BRACE_TOKENS.search(text, pos)) is not None:
        char, pos = match.group(), match.end()
        if char == "{":
            open_.append([match.start(), -1])
            found.append(open_[-1])
        elif char == "}" and open_:
            open_.pop()[1] = pos
        elif char == '"' and open_:
            string = _STRING_END.match(text, pos)
            if string is None:
                break  # an unclosed string: nothing after it closes
            pos = string.end()
    return [(start, end) for start, end in found]


def last_json_object(text: str) -> dict[str, Any] | None:
    """The last top-level JSON object in ``text``, ignoring prose and code fences around it.

    Linear in ``len(text)``: one pass matches the braces, then each candidate ``{...}`` is
    decoded once, left to right, past each object found; one that does not decode costs its
    length from a budget of a few times the text's (``json``'s own search from every ``{`` is
    quadratic: each failure counts lines from the start of the text)."""
    found, budget, pos = None, 4 * len(text) + 10_000, 0
    for start, end in _braces(text):
        if start < pos or end == -1:
            continue  # inside an object already taken, or never closed: not JSON
        if budget <= 0:
            break
        try:
            value = json.loads(text[start:end])
        except (ValueError, RecursionError):
            budget -= end - start
            continue
        if isinstance(value, dict):
            found, pos = value, end
    return found


def _number(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ReplyError(f"coordinate {_quoted(value)} is not a number")
    try:
        return float(value)
    except OverflowError:  # a 400-digit integer
        raise ReplyError(f"coordinate {_quoted(value)} is out of range") from None


def _waypoint(value: Any) -> tuple[float, float]:
    if isinstance(value, dict) and set(value) == {"x", "y"}:
        return _number(value["x"]), _number(value["y"])
    if isinstance(value, list) and len(value) == 2:
        return _number(value[0]), _number(value[1])
    raise ReplyError(f"waypoint {_quoted(value)} is not an [x, y] pair")


def parse_reply(raw: str | None, n_agents: int, n_waypoints: int, field_size: float) -> np.ndarray:
    """Validated waypoints [n_agents, n_waypoints, 2] (float64, clipped to the field).

    Raises :class:`ReplyError` for an empty reply, one over ``MAX_REPLY_CHARS``, no JSON, the
    wrong agent keys or shape, NaN/inf, or coordinates beyond ``ABSURD_FACTOR * field_size``
    (a model that far off misunderstood the frame; clipping would hide it). Its message is at
    most a few hundred characters, whatever the reply holds.
    """
    if raw is None or not raw.strip():
        raise ReplyError("empty reply")
    if len(raw) > MAX_REPLY_CHARS:
        raise ReplyError(f"reply too long: {len(raw)} characters, at most {MAX_REPLY_CHARS}")
    reply = last_json_object(raw)
    if reply is None:
        raise ReplyError("no JSON object in the reply")
    agents = sorted(k for k in reply if re.fullmatch(r"agent_\d+", k))
    if not agents and "error" in reply:
        declined = reply["error"] if isinstance(reply["error"], str) else repr(reply["error"])
        raise PlannerDeclined(_clip(f"planner declined: {declined}", _ERROR_CHARS))
    if set(agents) != set(_agent_keys(n_agents)):
        raise ReplyError(
            f"expected keys agent_0..agent_{n_agents - 1}, got {_quoted(agents)}"
            + (f" ({len(agents)} keys)" if len(agents) > 8 else "")
        )
    waypoints = np.empty((n_agents, n_waypoints, 2))
    for i in range(n_agents):
        trajectory = reply[f"agent_{i}"]
        if not isinstance(trajectory, list) or len(trajectory) != n_waypoints:
            size = f" ({len(trajectory)} items)" if isinstance(trajectory, list) else ""
            raise ReplyError(
                f"agent_{i} must be a list of {n_waypoints} [x, y] waypoints, got "
                f"{_quoted(trajectory)}{size}"
            )
        waypoints[i] = [_waypoint(point) for point in trajectory]
    if not np.isfinite(waypoints).all():
        raise ReplyError("non-finite coordinate (NaN or infinity)")
    if np.abs(waypoints).max() > ABSURD_FACTOR * field_size:
        raise ReplyError(
            f"absurd coordinate {np.abs(waypoints).max():g} for a {field_size:g} m field"
        )
    return np.clip(waypoints, -field_size / 2.0, field_size / 2.0)


class LLMPlanner:
    """Plans waypoints with any litellm model; never raises on bad model output.

    ``stats`` counts plan ``calls``, ``backend_calls`` (litellm requests),
    ``failures`` (rejected attempts), ``fallbacks`` and ``cache_hits``, for
    evaluation metrics. ``backoff_s`` is the pause after a provider exception
    (doubling per attempt; not after a bad reply, which is re-asked at once).
    ``timeout`` bounds one request and ``deadline_s`` a whole :meth:`plan`
    (attempts, pauses and all). When no attempt got a reply, :meth:`plan` raises
    :class:`LLMUnavailable`, or with ``fallback_on_error`` falls back and records it.
    """

    def __init__(
        self,
        model: str = DEFAULT_MODEL,
        api_base: str | None = None,
        temperature: float = 0.0,
        timeout: float = 10.0,
        max_retries: int = 2,
        cache_dir: str | os.PathLike[str] | None = None,
        prompt: str = "plain",
        n_waypoints: int = 4,
        field_size: float = 6.5,
        backoff_s: float = 0.5,
        deadline_s: float = 30.0,
        fallback_on_error: bool = False,
    ) -> None:
        if prompt not in PROMPTS:
            raise ValueError(f"prompt must be one of {PROMPTS}, got {prompt!r}")
        if n_waypoints < 1 or max_retries < 0 or field_size <= 0:
            raise ValueError("need n_waypoints >= 1, max_retries >= 0 and field_size > 0")
        if not timeout > 0 or not deadline_s > 0:
            raise ValueError(
                f"llm timeout_s and deadline_s must be > 0, got {timeout!r} and {deadline_s!r}"
            )
        self.model, self.api_base, self.temperature, self.timeout = (
            model,
            api_base,
            temperature,
            timeout,
        )
        self.max_retries, self.prompt, self.n_waypoints, self.field_size = (
            max_retries,
            prompt,
            n_waypoints,
            field_size,
        )
        self.backoff_s, self.deadline_s, self.fallback_on_error = (
            backoff_s,
            deadline_s,
            bool(fallback_on_error),
        )
        self.cache = ResponseCache(cache_dir)
        self._requests: list[threading.Thread] = []  # requests running, abandoned ones included
        self.stats = {
            "calls": 0,
            "backend_calls": 0,
            "failures": 0,
            "fallbacks": 0,
            "cache_hits": 0,
        }

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], *, field_size: float = 6.5) -> LLMPlanner:
        """Build from a ``conf/llm/*.yaml`` group: ``timeout_s`` is ``timeout``, and a
        null ``model`` means the ``backend``'s default model. Unknown keys raise TypeError."""
        kwargs = {
            ("timeout" if k == "timeout_s" else k): v
            for k, v in dict(cfg).items()
            if k != "backend"
        }
        if kwargs.get("model") is None:
            backend = str(cfg.get("backend", "offline"))
            kwargs["model"] = BACKEND_MODELS.get(backend, backend)
        return cls(field_size=field_size, **kwargs)

    def plan(
        self,
        instruction: str,
        positions: Any,
        previous: Any = None,
        *,
        resources: Any = None,
        invader: Any = None,
        cancel: threading.Event | None = None,
    ) -> PlanResult:
        """Waypoints for ``instruction`` given agent ``positions`` [N, 2] (metres).

        ``resources`` [R, 2] and ``invader`` [I, 2] fill the task-aligned prompt.
        ``previous`` [N, K, 2] is the fallback when every attempt fails (else the
        current positions, i.e. "stay"). ``cancel``, once set, ends the plan with
        :class:`PlanCancelled` at its next wait (a request still running is abandoned to its
        timeout, and counts in ``MAX_REQUESTS``)."""
        pos = _points(positions, "positions")
        messages, fmt, key = self._request(instruction, pos, resources, invader)
        self.stats["calls"] += 1
        cached = self._cached(key, len(pos))
        if cached is not None:
            return cached
        litellm = _litellm()  # outside the loop: a broken install is an error, not a bad reply
        start = time.monotonic()
        deadline = start + self.deadline_s
        waypoints, raw, error, attempts, answered = self._ask(
            litellm, instruction, messages, fmt, len(pos), cancel, deadline
        )
        if waypoints is not None:
            self.cache.put(key, raw, model=self.model, messages=messages)
            return PlanResult(waypoints.astype(np.float32), ok=True, attempts=attempts, raw=raw)
        if not answered and not self.fallback_on_error:
            raise LLMUnavailable(
                f"LLM {self.model} at {self.api_base or 'its default URL'} gave no reply to "
                f"{instruction!r} ({attempts} attempt(s) in {time.monotonic() - start:.1f} s): "
                f"{error}; check llm.api_base, the API key and that the server is up, or set "
                "llm.fallback_on_error=true to run on fallback waypoints"
            )
        return self._fallback(instruction, pos, previous, attempts, error, raw)

    def _request(
        self, instruction: str, pos: np.ndarray, resources: Any, invader: Any
    ) -> tuple[list[dict[str, str]], dict[str, Any], str]:
        """The messages, ``response_format`` and cache key of one plan's request."""
        messages = build_messages(
            instruction,
            pos,
            prompt=self.prompt,
            n_waypoints=self.n_waypoints,
            field_size=self.field_size,
            resources=resources,
            invader=invader,
        )
        fmt = response_format(len(pos), self.n_waypoints)
        key = cache_key(
            self.model, messages, {"response_format": fmt, "temperature": self.temperature}
        )
        return messages, fmt, key

    def _cached(self, key: str, n_agents: int) -> PlanResult | None:
        """The cached reply under ``key`` as a plan; None when there is none or it is invalid."""
        cached = self.cache.get(key)
        if cached is None:
            return None
        try:
            waypoints = parse_reply(cached, n_agents, self.n_waypoints, self.field_size)
        except ReplyError as exc:
            logger.warning(
                "ignoring invalid cached LLM reply (%s); asking %s again", exc, self.model
            )
            return None
        self.stats["cache_hits"] += 1
        return PlanResult(
            waypoints.astype(np.float32), ok=True, attempts=0, raw=cached, cached=True
        )

    def _ask(
        self,
        litellm: Any,
        instruction: str,
        messages: list[dict[str, str]],
        fmt: dict[str, Any],
        n_agents: int,
        cancel: threading.Event | None,
        deadline: float,
    ) -> tuple[np.ndarray | None, str | None, str, int, bool]:
        """``(waypoints or None, raw, error, attempts, answered)``: ask until a reply parses."""
        conversation, raw, error, attempts, answered = messages, None, "", 0, False
        for attempt in range(1, self.max_retries + 2):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                error += f" (deadline_s={self.deadline_s:g} reached)"
                break
            if cancel is not None and cancel.is_set():
                raise PlanCancelled(f"planning {instruction!r} was cancelled")
            raw, attempts, stop = None, attempt, False
            try:
                raw = self._complete(litellm, conversation, fmt, remaining, cancel)
                answered = True
                waypoints = parse_reply(raw, n_agents, self.n_waypoints, self.field_size)
            except PlanCancelled:
                raise
            except PlannerDeclined as exc:
                # "cannot do this" is an answer, not noise: asking again changes nothing
                error, stop = str(exc), True
            except ReplyError as exc:
                error = str(exc)
                conversation = messages + self._feedback(raw, error, n_agents)
            except Exception as exc:
                # timeouts, auth, rate limits, provider bugs: no reply this attempt
                error, stop = _describe(exc), _is_final(exc)
                if not stop and attempt <= self.max_retries and self.backoff_s > 0:
                    self._back_off(attempt, deadline, instruction, cancel)
            else:
                return waypoints, raw, error, attempt, answered
            self.stats["failures"] += 1
            self._log_failure(attempt, instruction, error, raw)
            if stop:
                break
        return None, raw, error, attempts, answered

    def _log_failure(self, attempt: int, instruction: str, error: str, raw: str | None) -> None:
        """Log one rejected attempt, its raw reply cut short."""
        logger.warning(
            "LLM %s attempt %d/%d for %r failed: %s; raw reply: %r",
            self.model,
            attempt,
            self.max_retries + 1,
            instruction,
            error,
            None if raw is None else _clip(raw, _LOGGED_CHARS),
        )

    def _back_off(
        self, attempt: int, deadline: float, instruction: str, cancel: threading.Event | None
    ) -> None:
        """Pause after a provider error (doubling per attempt, cut to the deadline)."""
        pause = min(self.backoff_s * 2 ** (attempt - 1), max(deadline - time.monotonic(), 0.0))
        if cancel is not None and cancel.wait(pause):
            raise PlanCancelled(f"planning {instruction!r} was cancelled") from None
        if cancel is None:
            time.sleep(pause)

    def _complete(
        self,
        litellm: Any,
        messages: list[dict[str, str]],
        fmt: dict[str, Any],
        remaining: float,
        cancel: threading.Event | None = None,
    ) -> str | None:
        self.stats["backend_calls"] += 1
        # max_retries=0: plan()'s loop owns the retry budget, not the OpenAI client inside litellm.
        # drop_params: a provider without JSON-schema support gets the prompt alone (we validate
        # anyway).
        response = _within(
            remaining,
            lambda: litellm.completion(
                model=self.model,
                messages=messages,
                response_format=fmt,
                temperature=self.temperature,
                timeout=min(self.timeout, remaining),
                api_base=self.api_base,
                max_retries=0,
                drop_params=True,
            ),
            cancel,
            self._requests,
        )
        return response.choices[0].message.content

    def _feedback(self, raw: str | None, error: str, n_agents: int) -> list[dict[str, str]]:
        """Show the model its rejected reply and why, as RoCo-style re-prompting does."""
        retry = _template("retry").substitute(
            error=error,
            agent_keys=", ".join(f'"{k}"' for k in _agent_keys(n_agents)),
            n_waypoints=self.n_waypoints,
        )
        return [
            {"role": "assistant", "content": _shown(raw) or "(empty)"},
            {"role": "user", "content": retry},
        ]

    def _fallback(self, instruction: str, pos: np.ndarray, previous: Any, attempts: int, error: str,
                  raw: str | None) -> PlanResult:  # fmt: skip
        shape = (len(pos), self.n_waypoints, 2)
        prev = None if previous is None else np.asarray(previous, dtype=np.float64)
        if prev is not None and prev.shape == shape and np.isfinite(prev).all():
            fallback, waypoints = "previous", prev
        else:
            fallback, waypoints = "positions", np.broadcast_to(pos[:, None], shape)
        waypoints = np.clip(waypoints, -self.field_size / 2.0, self.field_size / 2.0).astype(
            np.float32
        )
        self.stats["fallbacks"] += 1
        logger.warning(
            "LLM %s gave no usable plan for %r after %d attempt(s) (%s); falling back to %s",
            self.model,
            instruction,
            attempts,
            error,
            fallback,
        )
        return PlanResult(
            waypoints, ok=False, attempts=attempts, fallback=fallback, error=error, raw=raw
        )


def _within(
    seconds: float,
    call: Any,
    cancel: threading.Event | None = None,
    running: list[threading.Thread] | None = None,
) -> Any:
    """``call()``, waited for at most ``seconds`` (and until ``cancel`` is set).

    The request's own timeout bounds each wait for a byte, not the whole request: a server
    that trickles its reply could hold it for minutes. So the request runs in a daemon
    thread, and one still running at the deadline (or when cancelled) is left to its timeout
    and ignored. ``running`` lists a planner's request threads: while ``MAX_REQUESTS`` of
    them still run, a new request waits for one to end, so abandoned requests cannot pile up.
    """
    end = time.monotonic() + seconds
    if running is not None:
        _wait_for_slot(running, end, cancel)
    outcome: dict[str, Any] = {}

    def run() -> None:
        try:
            outcome["value"] = call()
        except BaseException as exc:  # re-raised in the caller's thread
            outcome["error"] = exc

    worker = threading.Thread(target=run, name="llm-request", daemon=True)
    if running is not None:
        running.append(worker)
    worker.start()
    _join(worker, end, cancel)
    if worker.is_alive():
        raise DeadlineExceeded(
            f"no reply within the plan's deadline ({seconds:.1f} s left of llm.deadline_s)"
        )
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]


def _join(thread: threading.Thread, end: float, cancel: threading.Event | None) -> None:
    """Join ``thread`` until it ends, ``end`` passes or ``cancel`` is set."""
    while thread.is_alive():
        left = end - time.monotonic()
        if cancel is not None and cancel.is_set():
            raise PlanCancelled("the plan was cancelled")
        if left <= 0:
            return
        thread.join(min(left, 0.05) if cancel is not None else left)


def _wait_for_slot(
    running: list[threading.Thread], end: float, cancel: threading.Event | None
) -> None:
    """Wait until fewer than ``MAX_REQUESTS`` of ``running`` still run (pruning ended ones)."""
    running[:] = [t for t in running if t.is_alive()]
    while len(running) >= MAX_REQUESTS:
        _join(running[0], end, cancel)
        running[:] = [t for t in running if t.is_alive()]
        if len(running) >= MAX_REQUESTS and time.monotonic() >= end:
            raise DeadlineExceeded(
                f"{len(running)} earlier requests still running at the plan's deadline"
            )


def _shown(raw: str | None) -> str | None:
    return None if raw is None else raw[:_SHOWN_CHARS]


_PLANNER_ARGS = (
    "model",
    "api_base",
    "temperature",
    "timeout",
    "max_retries",
    "cache_dir",
    "prompt",
    "backoff_s",
    "deadline_s",
    "fallback_on_error",
)


def plan_waypoints(
    instruction: str,
    positions: Any,
    *,
    backend: str = "offline",
    n_waypoints: int = 4,
    field_size: float = 6.5,
    **context: Any,
) -> np.ndarray:
    """Waypoints [n_agents, n_waypoints, 2] (float32) for ``instruction``: the strict wrapper.

    ``backend`` is "offline" (the rule planner), "openai", "ollama" or any
    litellm model string; ``context`` carries ``resources``, ``invader``,
    ``previous`` and the :class:`LLMPlanner` settings
    (``model`` overrides the backend's default model). With the offline
    backend an instruction it does not understand raises ``ValueError`` naming
    it; other backends return the planner's (possibly fallback) waypoints, and
    raise :class:`LLMUnavailable` when the provider never replies (unless
    ``fallback_on_error=True``).
    """
    unknown = set(context) - set(_PLANNER_ARGS) - {"resources", "invader", "previous"}
    if unknown:
        raise TypeError(f"plan_waypoints() got unexpected context {sorted(unknown)}")
    settings = {k: context.pop(k) for k in _PLANNER_ARGS if k in context}
    settings.setdefault("model", BACKEND_MODELS.get(backend, backend))
    planner = LLMPlanner(n_waypoints=n_waypoints, field_size=field_size, **settings)
    result = planner.plan(instruction, positions, **context)
    if backend == "offline" and not result.ok:
        raise ValueError(
            f"the offline rule planner does not understand the instruction {instruction!r}: "
            f"{result.error}"
        )
    return result.waypoints
