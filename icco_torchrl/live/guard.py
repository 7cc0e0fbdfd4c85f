"""What the page server and the bridge share to stay bounded under a crowd: log lines throttled
to one a period, token buckets, a limit on token guesses, one-line echoes of untrusted text and
the token kept out of the run folder's files."""

from __future__ import annotations

import hmac
import json
import math
import os
import re
import time
from collections import OrderedDict
from pathlib import Path

LOG_EVERY = 1.0  # seconds between two log lines of one kind (refusals, joins, failures, ...)
MAX_ECHO = 160  # characters of untrusted text (a reason, a path) echoed in a log line
GUESS_RATE = 1.0  # wrong tokens a second one source may try, after a burst of GUESS_BURST
GUESS_BURST = 10
GUESS_RATE_ALL = 10.0  # wrong tokens a second all sources together may try, after GUESS_BURST_ALL
GUESS_BURST_ALL = 20
MAX_SOURCES = 1024  # sources (IP addresses) whose wrong tokens are counted (the most recent)
MAX_TRUSTED = 256  # peers (full addresses) that gave the right token, exempt from the limit
REDACTED = "<redacted>"


def one_line(text, limit: int = MAX_ECHO) -> str:
    """``text`` on one line of at most ``limit`` characters, printable ASCII."""
    text = " ".join(str(text).split())
    text = text.encode("ascii", "backslashreplace").decode("ascii")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def held(n: int) -> str:
    """What a throttled log line adds about the lines held back since the last one."""
    return f" ({n} more since the last line)" if n else ""


class Throttle:
    """At most one log line per ``every`` seconds; :meth:`due` says whether one may be written now
    and how many were held back since the last."""

    def __init__(self, every: float = LOG_EVERY):
        self.every, self.next_at, self.held = every, -math.inf, 0

    def due(self) -> tuple[bool, int]:
        now = time.monotonic()
        if now < self.next_at:
            self.held += 1
            return False, 0
        held, self.held, self.next_at = self.held, 0, now + self.every
        return True, held


class Bucket:
    """A token bucket: ``burst`` at once, then ``rate`` a second."""

    def __init__(self, rate: float, burst: float):
        self.rate, self.burst = float(rate), float(burst)
        self.allowance, self.checked = float(burst), time.monotonic()

    def _refill(self) -> None:
        now = time.monotonic()
        self.allowance = min(self.burst, self.allowance + (now - self.checked) * self.rate)
        self.checked = now

    def ready(self) -> bool:
        """Whether one more fits (nothing is spent)."""
        self._refill()
        return self.allowance >= 1.0

    def spend(self) -> None:
        self._refill()
        self.allowance = max(0.0, self.allowance - 1.0)

    def admit(self) -> bool:
        """Spend one when it fits; whether it did."""
        if not self.ready():
            return False
        self.allowance -= 1.0
        return True


class TokenCheck:
    """Compare a given token with ``token`` in constant time, at most ``GUESS_RATE`` wrong ones a
    second from one source (after ``GUESS_BURST``) and ``GUESS_RATE_ALL`` from all of them (after
    ``GUESS_BURST_ALL``): beyond, a token is refused unchecked, so guessing it takes years, not
    seconds. A right token spends nothing.

    A ``peer`` (a full address, e.g. ``(ip, port)``) that gave the right token is trusted (the
    ``MAX_TRUSTED`` most recent): its tokens are always compared and its wrong ones spend
    nothing, so guesses from other ports of its IP, or from anywhere, cannot lock it out. Its
    trust tells a guesser nothing: what the token unlocks goes to the trusted address, not to
    the guesser's."""

    def __init__(self, token: str):
        self.token = token.encode("utf-8", "surrogatepass")
        # The token as a datagram may spell it: plain UTF-8, or as json.dumps escapes it.
        self.spellings = {
            self.token,
            json.dumps(token)[1:-1].encode("utf-8", "surrogatepass"),
            json.dumps(token, ensure_ascii=False)[1:-1].encode("utf-8", "surrogatepass"),
        }
        self.all = Bucket(GUESS_RATE_ALL, GUESS_BURST_ALL)
        self.sources: OrderedDict[str, Bucket] = OrderedDict()
        self.trusted: OrderedDict = OrderedDict()  # peers that gave the right token
        self.guesses = 0  # wrong tokens compared
        self.unchecked = 0  # tokens refused unchecked (over the limit)

    def spelled_in(self, data: bytes) -> bool:
        """Whether ``data`` holds the token's bytes at all (a cheap screen before parsing: a
        datagram without them cannot carry the right token)."""
        return any(spelling in data for spelling in self.spellings)

    def check(self, given: str | None, source: str, peer=None) -> str | None:
        """None when ``given`` is the token, else why it is refused (one line). ``given`` None:
        a token already known wrong (a datagram without its bytes), counted as a guess."""
        trusted = peer is not None and peer in self.trusted
        bucket = None if trusted else self._bucket(source)
        if bucket is not None and not (bucket.ready() and self.all.ready()):
            self.unchecked += 1
            return (
                f"too many wrong tokens (at most {GUESS_RATE:g} a second from one address, "
                f"{GUESS_RATE_ALL:g} from all): refused unchecked, try again in a few seconds"
            )
        if given is not None and hmac.compare_digest(
            given.encode("utf-8", "surrogatepass"), self.token
        ):
            if peer is not None:
                self.trusted[peer] = None
                self.trusted.move_to_end(peer)
                while len(self.trusted) > MAX_TRUSTED:
                    self.trusted.popitem(last=False)
            return None
        self.guesses += 1
        if bucket is not None:
            bucket.spend()
            self.all.spend()
        return "wrong token"

    def _bucket(self, source: str) -> Bucket:
        """The guess allowance of ``source`` (the ``MAX_SOURCES`` most recent are kept)."""
        bucket = self.sources.get(source)
        if bucket is None:
            bucket = self.sources[source] = Bucket(GUESS_RATE, GUESS_BURST)
            while len(self.sources) > MAX_SOURCES:
                self.sources.popitem(last=False)
        self.sources.move_to_end(source)
        return bucket


# ------------------------------------------------------------------ the token in the run folder
_OVERRIDE = re.compile(r"^[+~]{0,2}live\.token=")
TOKEN_VARIABLE = "ICCO_LIVE_TOKEN"  # the environment variable a live.token= override moves to


def keep_token_out(overrides: list[str]) -> list[str]:
    """Before Hydra writes its files (``.hydra/*.yaml``, ``cli.log``) for ``icco live`` or
    ``icco bridge``: this process's new files and folders become its owner's only (umask 077),
    and a ``live.token=SECRET`` override is passed on through the environment
    (:func:`token_through_environment`), so that no file ever holds the token, not even for
    the moment before :func:`redact_run_folder` runs. Returns the overrides for Hydra."""
    os.umask(0o077)
    return token_through_environment(overrides)


def token_through_environment(overrides: list[str]) -> list[str]:
    """``overrides`` with a ``live.token=SECRET`` override (``+`` and ``++`` ones too) read as
    Hydra reads it and replaced by ``live.token=${oc.env:ICCO_LIVE_TOKEN}``, SECRET set in this
    process's environment (``TOKEN_VARIABLE``). An interpolation (``${oc.env:...}``), ``null``,
    a sweep or a deletion is left as given, and so is an override Hydra cannot parse (Hydra
    then says why)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    out = []
    for item in overrides:
        if isinstance(item, str) and _OVERRIDE.match(item) and not item.startswith("~"):
            try:
                value = OverridesParser.create().parse_overrides([item])[0].value()
            except Exception:  # Hydra's own error, in one line, when it composes
                value = None
            if isinstance(value, (str, int, float)) and not isinstance(value, bool):
                value = str(value)
                if value and "${" not in value:
                    os.environ[TOKEN_VARIABLE] = value
                    item = item[: item.index("=") + 1] + "${oc.env:" + TOKEN_VARIABLE + "}"
        out.append(item)
    return out


def redact_run_folder(folder, token: str | None) -> list[Path]:
    """Keep ``token`` out of the files Hydra wrote in ``folder`` (``.hydra/*.yaml``: the config,
    the overrides, Hydra's own record): ``live.token`` and every ``live.token=...`` override
    there read ``<redacted>``. The folder's files become readable by their owner only (0600,
    folders 0700). Returns the files rewritten."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    rewritten = []
    hydra = folder / ".hydra"
    if token is not None and hydra.is_dir():
        raw = _raw_overrides(hydra / "overrides.yaml")
        for path in sorted(hydra.glob("*.yaml")):
            text = path.read_text()
            new = _redact(text, token, raw)
            if new != text:
                _write_private(path, new)
                rewritten.append(path)
    for path in [folder, *folder.rglob("*")]:
        if path.is_symlink():
            continue
        try:
            os.chmod(path, 0o700 if path.is_dir() else 0o600)
        except OSError:
            pass
    return rewritten


def _raw_overrides(path: Path) -> list[str]:
    """The ``live.token=...`` overrides as given on the command line."""
    from omegaconf import OmegaConf

    if not path.is_file():
        return []
    items = OmegaConf.to_container(OmegaConf.load(path))
    return [s for s in items or [] if isinstance(s, str) and _OVERRIDE.match(s)]


def _redact(text: str, token: str, raw: list[str]) -> str:
    """``text`` (one of Hydra's YAML files) with the token's value redacted."""
    from omegaconf import OmegaConf

    for item in raw:  # in the overrides list and hydra.job.override_dirname
        prefix = item[: item.index("=") + 1]
        text = text.replace(item, prefix + REDACTED)
    try:
        cfg = OmegaConf.create(text)
        live = cfg._get_node("live") if OmegaConf.is_dict(cfg) and "live" in cfg else None
        if live is not None and OmegaConf.is_dict(live) and "token" in live:
            live.token = REDACTED  # the composed config (config.yaml), never resolved
            text = OmegaConf.to_yaml(cfg)
    except Exception:  # not a config OmegaConf reads back: the text replacements below only
        pass
    if len(token) >= 4 and token in text:  # anything left that spells it (quoted, escaped)
        text = text.replace(token, REDACTED)
    return text


def _write_private(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)
