"""A run folder's files and its lock: the names of what a run writes there, the writer's lock, the
atomic writes every file of the run goes through, and the record of what a run has written after
its last frame. The checkpoint (:mod:`.checkpoint`) and the replay dump (:mod:`.replay_dump`) are
written through here.

- **Errors.** Any file of the run that cannot be written (a full disk, a read-only folder, no
  permission) is one :class:`CheckpointError` line naming the path, and leaves no temp file.
- **The lock.** ``icco train`` holds a lock on its folder (:class:`RunFolderLock`, a file opened
  without following links): a second writer is refused in one line (:class:`RunFolderBusy`).
- **The record.** Whether the final evaluation and the learning curve of the last frame were
  written (:func:`fresh_outputs`: nothing yet; a run's state records it), so a resume writes what
  a stopped run left out.
"""

from __future__ import annotations

import errno
import fcntl
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

CHECKPOINT = "checkpoint.pt"  # a run's checkpoint, in its run folder
REPLAY_DIR = "replay"  # the replay buffer dump beside it (train.checkpoint_buffer)
LOCK_FILE = ".train.lock"  # held by the icco train writing the folder
REFERENCES_FILE = "references.json"  # the reference policies' evaluation, beside eval.csv
SNAPSHOTS = "policies"  # train.policy_snapshots: the weights of every evaluation, <frames>.pt


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable, or does not match the requested config; or a run folder
    cannot be written."""


class RunFolderBusy(CheckpointError):
    """Another ``icco train`` holds the run folder's lock, or its lock file is not one this project
    may open (a link): the folder is left as it is."""


# ---------------------------------------------------------------- errors
def one_line(err: Exception) -> str:
    """The informative line of an exception message (torch's weights-only errors span a page)."""
    text = str(err)
    marker = re.search(r"WeightsUnpickler error:?\s*(\S[^\n]*)", text)
    if marker:
        return marker.group(1).strip()
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return (lines or [type(err).__name__])[0][:200]


def cannot_write(what: str, path: Path, err: OSError) -> CheckpointError:
    """One line for a failed write: a full disk, a read-only folder, no permission."""
    reason = err.strerror or str(err) or type(err).__name__
    hint = {
        errno.ENOSPC: "free some space and run again",
        errno.EDQUOT: "free some space and run again",
        errno.EROFS: "write the run to a writable folder",
        errno.EACCES: "write the run to a folder you may write",
        errno.EPERM: "write the run to a folder you may write",
    }.get(err.errno, "check the folder and run again")
    return CheckpointError(f"cannot write {what} {path}: {reason}; {hint}")


# ---------------------------------------------------------------- atomic writes
def _temp_pattern(name: str) -> re.Pattern:
    """Names of the temp files/folders made by
    ``tempfile.mk*temp(prefix=f".{name}.", suffix=".tmp")``."""
    return re.compile(rf"\.{re.escape(name)}\.[a-z0-9_]{{8}}\.tmp")


def remove_stale_temps(path: Path) -> None:
    """Delete temp files/folders of ``path`` left by a process killed while writing it."""
    pattern = _temp_pattern(path.name)
    if not path.parent.is_dir():
        return
    for entry in path.parent.iterdir():
        if pattern.fullmatch(entry.name):
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)


def write_all(fd: int, data) -> None:
    """Write every byte of ``data`` to ``fd`` (plain ``write`` calls: a full disk raises ENOSPC)."""
    view = memoryview(data).cast("B")
    while view:
        view = view[os.write(fd, view[: 1 << 24]) :]


def free_bytes(folder: Path) -> int:
    """Free space in ``folder`` for this user."""
    return shutil.disk_usage(folder).free


def write_folder_atomically(
    path: Path,
    files: Iterable[tuple[str, Any]],
    what: str,
    *,
    size: int,
    old: Path,
    keep_old: bool = False,
) -> Path:
    """Write ``files`` (``(name in the folder, bytes)`` pairs, about ``size`` bytes in all) as the
    folder ``path``: into a temp folder beside it with plain writes, then swapped in, so a crash
    never leaves a half-written folder there; the folder it replaces is kept as ``old`` (with
    ``keep_old``, until the caller drops it). Temp folders of a writer that was killed are removed
    first, and a disk without room for ``size`` is refused before anything is written. A full
    disk or a read-only folder is one :class:`CheckpointError` line naming ``what`` and ``path``,
    and leaves no temp folder."""
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(path)
        free = free_bytes(path.parent)
        if size + (1 << 20) > free:
            raise OSError(
                errno.ENOSPC,
                f"No space left on device ({what} needs {size / 1e6:.1f} MB, "
                f"{free / 1e6:.1f} MB are free)",
            )
        tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
        for name, data in files:
            file = tmp / name
            file.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                write_all(fd, data)
                os.fsync(fd)
            finally:
                os.close(fd)
        shutil.rmtree(old, ignore_errors=True)
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
        if not keep_old:
            shutil.rmtree(old, ignore_errors=True)
    except OSError as err:
        raise cannot_write(what, path, err) from None
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return path


def write_atomically(path: Path, data, what: str) -> Path:
    """Write the bytes ``data`` to ``path`` through a temp file beside it and a rename, so a crash
    never leaves a half-written file there. A full disk or a read-only folder is one
    :class:`CheckpointError` line naming ``what`` and ``path``, and leaves no temp file."""
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(path)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        try:
            write_all(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError as err:
        raise cannot_write(what, path, err) from None
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
    return path


# ---------------------------------------------------------------- the lock
class RunFolderLock:
    """An exclusive lock on a run folder (``flock`` on :data:`LOCK_FILE`), held while ``icco train``
    writes it: a second writer (two resumes of one checkpoint, two runs given one
    ``hydra.run.dir``) is refused in one line instead of both writing the same files. The lock
    goes with the process, however it ends; the file stays (deleting it would race).

    The lock file is opened without following links: in a run folder received from elsewhere a
    ``.train.lock`` that is a symbolic link (or no plain file) is refused in one line, and whatever
    it points to is left untouched."""

    def __init__(self, run_dir: str | Path):
        self.run_dir = Path(run_dir)
        self._fd: int | None = None

    def __enter__(self) -> RunFolderLock:
        path = self.run_dir / LOCK_FILE
        flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, flags, 0o644)
        except OSError as err:
            if err.errno == errno.ELOOP:  # O_NOFOLLOW met a link
                raise self._not_a_lock_file("a symbolic link") from None
            raise cannot_write("the run folder", self.run_dir, err) from None
        if not stat.S_ISREG(os.fstat(fd).st_mode):  # a FIFO or a device: not ours to write
            os.close(fd)
            raise self._not_a_lock_file("no plain file")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise RunFolderBusy(
                f"run folder {self.run_dir} is in use by another icco train (pid {holder}): "
                "wait for it to end, or stop it first"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def _not_a_lock_file(self, what: str) -> RunFolderBusy:
        return RunFolderBusy(
            f"run folder {self.run_dir}: its {LOCK_FILE} is {what}, not a lock file; refusing to "
            f"open it: delete {self.run_dir / LOCK_FILE} and run again"
        )

    def __exit__(self, *exc) -> None:
        if self._fd is not None:
            os.close(self._fd)  # releases the lock
            self._fd = None


# ---------------------------------------------------------------- the record of what was written
def fresh_outputs() -> dict:
    """What a run has written after its last frame: nothing yet (the ``outputs`` field of
    :class:`~icco_torchrl.training.checkpoint.RunState`)."""
    return {"final_evaluation": False, "final_metrics": {}, "learning_curve": False}
