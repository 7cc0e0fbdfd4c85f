"""On-disk cache of LLM replies, so an evaluation that used a model can be replayed exactly.

One JSON file per request, named by the sha256 of everything that decides the
answer (model, prompt messages, response format, temperature). Timeouts, retry
budgets and the API base are left out of the key: they change whether an
answer arrives, not which one. Only replies that passed validation are stored,
so a transient bad reply is asked again next time instead of being replayed.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)


def cache_key(model: str, messages: list[dict[str, Any]], settings: dict[str, Any]) -> str:
    """sha256 hex digest of a canonical JSON encoding of the request."""
    payload = json.dumps(
        {"model": model, "messages": messages, "settings": settings},
        sort_keys=True,
        separators=(",", ":"),
        ensure_ascii=False,
    )
    return hashlib.sha256(payload.encode("utf-8")).hexdigest()


class ResponseCache:
    """Raw reply strings keyed by :func:`cache_key`; ``cache_dir=None`` disables it."""

    def __init__(self, cache_dir: str | os.PathLike[str] | None) -> None:
        self.directory = None if cache_dir is None else Path(cache_dir)

    def get(self, key: str) -> str | None:
        """The stored reply, or None (disabled, missing, or unreadable: treated as a miss)."""
        if self.directory is None:
            return None
        path = self.directory / f"{key}.json"
        try:
            return str(json.loads(path.read_text(encoding="utf-8"))["raw"])
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            logger.warning("ignoring unreadable LLM cache entry %s: %s", path, exc)
            return None

    def put(self, key: str, raw: str, *, model: str, messages: list[dict[str, Any]]) -> None:
        """Store a reply next to the request that produced it (for auditing a replay).

        Written to a temporary file and renamed, so evaluations running in
        parallel on one cache never read a half-written entry.
        """
        if self.directory is None:
            return
        entry = {"model": model, "messages": messages, "raw": raw}
        tmp: str | None = None
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=self.directory, prefix=f".{key[:16]}-", suffix=".tmp")
            with os.fdopen(fd, "w", encoding="utf-8") as handle:
                json.dump(entry, handle, ensure_ascii=False, indent=1)
            os.replace(tmp, self.directory / f"{key}.json")
        except OSError as exc:  # a full disk must not end an evaluation; the plan is still used
            logger.warning("could not write LLM cache entry under %s: %s", self.directory, exc)
            if tmp is not None:
                Path(tmp).unlink(missing_ok=True)
