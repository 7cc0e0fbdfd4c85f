"""Where ``train.compile`` keeps its compiled kernels (Inductor's cache), and whether it can.

A cold compile of the ICCO update takes a minute or more on a CPU, a warm one seconds, so the
kernels persist in :data:`CACHE_DIR` across runs, unless ``TORCHINDUCTOR_CACHE_DIR`` names another
folder. The folder is given to Inductor only while the update compiles or runs
(:func:`scoped`), not to the whole process. A folder that cannot be used (not a folder, not
writable, on a full disk) is found before compiling (:func:`folder_problem`): the update then runs
eagerly after one line.

This module imports no torch: the ``icco`` command calls :func:`note_environment` before torch
is imported, because importing ``torch._dynamo`` creates the folder that
``TORCHINDUCTOR_CACHE_DIR`` names and fails on one it cannot create (a path through a file).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

ENV = "TORCHINDUCTOR_CACHE_DIR"
CACHE_DIR = Path.home() / ".cache" / "icco_torchrl" / "inductor"
# Below this much free space a compile cannot write its kernels (the smoke update's take 8 MB).
MIN_FREE_BYTES = 64 << 20

_noted = False  # note_environment ran before torch could set ENV itself
_given: str | None = None  # ENV as the user set it
_set_aside: str | None = None  # why the user's ENV was set aside (it broke torch's import)


def folder_problem(path: str | Path) -> str | None:
    """Why Inductor cannot keep its cache in ``path`` (created if missing), or None: not a folder,
    not writable, or a disk with less than :data:`MIN_FREE_BYTES` free."""
    if os.path.exists(path) and not os.path.isdir(path):
        return "not a folder"
    try:
        os.makedirs(path, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=path, prefix=".icco-probe-")
        try:
            os.write(fd, b"\0" * 4096)
        finally:
            os.close(fd)
            os.unlink(probe)
        free = shutil.disk_usage(path).free
    except OSError as err:
        return err.strerror or type(err).__name__
    if free < MIN_FREE_BYTES:
        return f"only {free / 2**20:.0f} MB free on its disk"
    return None


def note_environment() -> None:
    """Before torch is imported: remember the user's ``TORCHINDUCTOR_CACHE_DIR``, and set it aside
    (torch then imports with its own default) when it names a folder that cannot be created, so
    that every command still starts; ``train.compile`` then says why and runs eagerly."""
    global _noted, _given, _set_aside
    _noted, _given = True, os.environ.get(ENV)
    if not _given:
        return
    try:
        os.makedirs(_given, exist_ok=True)
    except OSError as err:
        _set_aside = f"{ENV}={_given}: {err.strerror or type(err).__name__}"
        del os.environ[ENV]


def chosen() -> tuple[Path, str | None]:
    """The cache folder a compile uses, and why it cannot, or None when it can."""
    if _set_aside:
        return Path(_given or CACHE_DIR), _set_aside
    given = _given if _noted else _given_after_torch()
    folder = Path(os.path.abspath(given)) if given else CACHE_DIR
    problem = folder_problem(folder)
    return folder, (f"{folder}: {problem}" if problem else None)


def _given_after_torch() -> str | None:
    """``TORCHINDUCTOR_CACHE_DIR`` when :func:`note_environment` did not run: importing
    ``torch._dynamo`` sets it to torch's default folder, which counts as not given."""
    value = os.environ.get(ENV)
    try:
        from torch._inductor.runtime.cache_dir_utils import default_cache_dir
    except ImportError:  # a torch that moved it: take the variable as it is
        return value
    return None if value and os.path.abspath(value) == default_cache_dir() else value


@contextmanager
def scoped(folder: str | Path) -> Iterator[None]:
    """``TORCHINDUCTOR_CACHE_DIR`` set to ``folder`` inside the block only (where Inductor
    compiles), and as it was after."""
    before = os.environ.get(ENV)
    os.environ[ENV] = str(folder)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(ENV, None)
        else:
            os.environ[ENV] = before
