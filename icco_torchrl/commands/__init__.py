"""The ``icco`` commands that combine several layers: thin functions over library calls.

``icco eval`` (:mod:`.evaluate`) and ``icco instruct`` (:mod:`.instruct`) sit above both
:mod:`icco_torchrl.evaluation` and :mod:`icco_torchrl.instructions`, which do not import each
other; :func:`clean_errors` turns bad input into one line and exit code 2.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager

from icco_torchrl.training.checkpoint import CheckpointError
from icco_torchrl.training.config import ConfigError


@contextmanager
def clean_errors(command: str):
    """Bad input (missing or incompatible checkpoint, bad value) ends the command with a
    one-line message and exit code 2 instead of a traceback."""
    try:
        yield
    except (CheckpointError, ConfigError, ValueError) as err:
        print(f"icco {command}: {err}", file=sys.stderr)
        raise SystemExit(2) from None
