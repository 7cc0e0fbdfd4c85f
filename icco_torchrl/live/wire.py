"""The robot bridge's wire protocol: JSON over UDP, parsed strictly, encoded plainly.

UTF-8 JSON, one object per datagram of at most ``MAX_MESSAGE`` bytes; distances in metres,
angles in radians, field frame centred on home, +x right, +y up. The message types:

* in, ``{"type": "state", "time": t, "robots": [{"id": i, "pose": [x, y, theta]}, ...],
  "resources": [[x, y], ...], "invader": [[x, y]] }`` as a motion-capture system streams it.
  ``robots`` may list any subset (robots reported separately); ``resources`` and ``invader``
  are optional (kept from the last message; ``"invader": []`` means none on the field).
* in, ``{"type": "instruct", "text": "Go right"}``: a language instruction for the team (at most
  ``MAX_INSTRUCTION`` characters).
* in, on either: ``"token": "..."`` (1 to ``MAX_TOKEN`` characters), which the bridge checks
  against ``live.token``; with a token set, a state must also carry ``time`` (seconds, from a
  clock that never goes back), after that of the last state taken for each robot it lists
  (the bridge refuses others as replays).
* out: ``{"type": "command", "time": t, "robots": [{"id": i, "target": [x, y], "v": v, "w": w,
  "stopped": bool, "reason": null | "stale" | "contested" | "team full" | "control error" |
  "bridge stopped"}, ...]}`` (:func:`command_message`; :func:`drive` and :func:`stop` make its
  entries), sent to the address each robot is bound to (the first that reported it).

:func:`parse_message` checks a datagram before anything uses it, cheapest first: its byte length
(at most ``MAX_MESSAGE``), then UTF-8 and JSON (no ``NaN`` or ``Infinity``, numbers of at most
``MAX_DIGITS`` digits, nesting too deep for the parser refused), then strict types: an ``id`` is
an int in ``0..MAX_ROBOT_ID`` (``true`` is not), coordinates are finite numbers of magnitude at
most ``MAX_COORD``, an instruction is valid unicode within ``MAX_INSTRUCTION`` characters. A
datagram that fails raises :class:`ProtocolError` of one line, its ``kind`` naming the check.
What the bridge does with a message (the team, commands, the safety contract) is
:mod:`icco_torchrl.live.bridge`'s.
"""

from __future__ import annotations

import json
import math
import time

from icco_torchrl.live.loop import MAX_INSTRUCTION

MESSAGE_TYPES = ("state", "instruct")  # what may come in; what goes out is "command"
MAX_DATAGRAM = 65_507  # the largest UDP payload over IPv4
MAX_MESSAGE = 16_384  # bytes: a longer datagram is refused before it is decoded
MAX_DIGITS = 40  # characters of one JSON number (longer ones are refused, not converted)
MAX_COORD = 1e4  # metres (and radians): the largest coordinate a state may carry
MAX_TOKEN = 256  # characters of a datagram's "token"
MAX_ROBOT_ID = 2**31 - 1  # the largest robot id a state may carry


class ProtocolError(ValueError):
    """A datagram that does not follow the protocol (module docstring); ``kind`` names the check
    it failed (``oversize``, ``encoding``, ``json``, ``nesting``, ``number``, ``type``,
    ``instruct``, ``token``)."""

    def __init__(self, message: str, kind: str = "type"):
        super().__init__(message)
        self.kind = kind


# ------------------------------------------------------------------ decoding
def _refuse_constant(name: str):
    raise ProtocolError(
        f"{name} is not a number the protocol takes (finite numbers only)", "number"
    )


def _parse_int(text: str) -> int:
    if len(text) > MAX_DIGITS:
        raise ProtocolError(f"a number of {len(text)} characters (at most {MAX_DIGITS})", "number")
    return int(text)


def _parse_float(text: str) -> float:
    if len(text) > MAX_DIGITS:
        raise ProtocolError(f"a number of {len(text)} characters (at most {MAX_DIGITS})", "number")
    value = float(text)
    if not math.isfinite(value):
        raise ProtocolError(f"{text} is out of range (finite numbers only)", "number")
    return value


def _decode(data: bytes):
    """The datagram's JSON value, checked for size, encoding, nesting and numbers."""
    if not isinstance(data, (bytes, bytearray)):
        raise ProtocolError(f"a datagram must be bytes, got {type(data).__name__}")
    if len(data) > MAX_MESSAGE:
        raise ProtocolError(f"{len(data)} bytes or more (at most {MAX_MESSAGE})", "oversize")
    try:
        text = bytes(data).decode("utf-8")
    except UnicodeDecodeError as err:
        raise ProtocolError(f"not UTF-8 JSON: {err}", "encoding") from None
    try:
        return json.loads(
            text,
            parse_int=_parse_int,
            parse_float=_parse_float,
            parse_constant=_refuse_constant,
        )
    except RecursionError:
        raise ProtocolError("not UTF-8 JSON: nested too deeply", "nesting") from None
    except json.JSONDecodeError as err:
        raise ProtocolError(f"not UTF-8 JSON: {err}", "json") from None
    except ValueError as err:  # ProtocolError from a number hook, or int() refusing a literal
        if isinstance(err, ProtocolError):
            raise
        raise ProtocolError(f"not UTF-8 JSON: {err}", "number") from None


# ------------------------------------------------------------------ validation
def _coord(value) -> bool:
    """A finite number (not a bool) within ``MAX_COORD``."""
    return (
        isinstance(value, (int, float))
        and not isinstance(value, bool)
        and math.isfinite(value)
        and abs(value) <= MAX_COORD
    )


def _points(value, size: int) -> bool:
    """A list of ``[x, y]`` (``size`` 2) or ``[x, y, theta]`` (``size`` 3) coordinates."""
    return isinstance(value, list) and len(value) == size and all(_coord(v) for v in value)


def _check_instruct(msg: dict) -> None:
    """An instruct message's ``text``: non-empty, at most ``MAX_INSTRUCTION``, valid unicode."""
    text = msg.get("text")
    if not isinstance(text, str) or not text.strip():
        raise ProtocolError("an instruct message needs a non-empty 'text'", "instruct")
    if len(text.strip()) > MAX_INSTRUCTION:
        raise ProtocolError(
            f"instruction too long: {len(text.strip())} characters, at most {MAX_INSTRUCTION}",
            "instruct",
        )
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise ProtocolError("the instruction is not valid unicode", "instruct") from None


def _check_state(msg: dict) -> None:
    """A state message's ``robots``, ``resources``, ``invader`` and ``time``."""
    robots = msg.get("robots", [])
    if not isinstance(robots, list):
        raise ProtocolError("'robots' must be a list")
    for r in robots:
        rid = r.get("id") if isinstance(r, dict) else None
        if type(rid) is not int or not 0 <= rid <= MAX_ROBOT_ID:
            raise ProtocolError(f"each robot needs an integer 'id' in [0, {MAX_ROBOT_ID}]")
        if not _points(r.get("pose"), 3):
            raise ProtocolError(
                f"robot {rid}: 'pose' must be [x, y, theta] (finite numbers, at most "
                f"{MAX_COORD:g} in size)"
            )
    for key in ("resources", "invader"):
        if key in msg and not (isinstance(msg[key], list) and all(_points(p, 2) for p in msg[key])):
            raise ProtocolError(f"'{key}' must be a list of [x, y] points (finite numbers)")
    if "time" in msg and not (
        isinstance(msg["time"], (int, float))
        and not isinstance(msg["time"], bool)
        and math.isfinite(msg["time"])
    ):
        raise ProtocolError("'time' must be a number (seconds)")


def parse_message(data: bytes) -> dict:
    """The validated message, or :class:`ProtocolError` with one line saying what is wrong."""
    msg = _decode(data)
    if not isinstance(msg, dict) or msg.get("type") not in MESSAGE_TYPES:
        raise ProtocolError("a message must be a JSON object with type 'state' or 'instruct'")
    token = msg.get("token")
    if token is not None and not (isinstance(token, str) and 0 < len(token) <= MAX_TOKEN):
        raise ProtocolError(f"'token' must be a string of 1 to {MAX_TOKEN} characters", "token")
    if msg["type"] == "instruct":
        _check_instruct(msg)
    else:
        _check_state(msg)
    return msg


# ------------------------------------------------------------------ encoding
def drive(rid: int, target, v: float, w: float) -> dict:
    """A command entry that drives robot ``rid`` toward ``target`` at ``(v, w)``."""
    return {"id": rid, "target": target, "v": v, "w": w, "stopped": False, "reason": None}


def stop(rid: int, target, reason: str) -> dict:
    """A command entry that stops robot ``rid`` (``v = w = 0``) for ``reason``."""
    return {"id": rid, "target": target, "v": 0.0, "w": 0.0, "stopped": True, "reason": reason}


def command_message(robots: list[dict]) -> dict:
    """The command message listing ``robots`` (entries of :func:`drive` and :func:`stop`),
    stamped with the wall-clock time."""
    return {"type": "command", "time": time.time(), "robots": robots}


def encode(message: dict) -> bytes:
    """``message`` as one datagram's bytes."""
    return json.dumps(message).encode()
