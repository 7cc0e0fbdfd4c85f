"""The training side and the command line against hostile input: a collector process that hangs,
a converter run on a training's checkpoint, crafted checkpoints (shared lists that expand, deep
nesting, NaN weights), the commands a run prints for pasting, a read-only run folder, and the
one-line help of the command line (a misspelled field, a checkpoint that is not there)."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import math
import os
import resource
import signal
import struct
import subprocess
import sys
import threading
import time
import zipfile
from pathlib import Path

import pytest
import torch
from conftest import ROOT

from icco_torchrl.cli import main
from icco_torchrl.trainer import finish_message, train
from icco_torchrl.training import collector_process
from icco_torchrl.training.checkpoint import load_checkpoint
from icco_torchrl.training.collector_process import CollectorError, ProcessCollector
from icco_torchrl.training.config import compose_config
from icco_torchrl.training.restore import restore
from icco_torchrl.training.run_folder import CheckpointError, RunFolderLock

pytestmark = pytest.mark.fault  # the fault suite: crafted files, hangs, signals

torch.set_num_threads(1)
DEMO = ROOT / "assets" / "demo_icco.pt"


def icco(*args: str) -> int:
    """``icco ARGS`` in this process (its imports paid once); returns the exit code."""
    argv = sys.argv
    try:
        main(list(args))
    except SystemExit as exit_info:
        return exit_info.code
    finally:
        sys.argv = argv
    return 0


def converter():
    """tools/convert_checkpoint.py as a module (a script outside the package)."""
    spec = importlib.util.spec_from_file_location(
        "convert_checkpoint", ROOT / "tools" / "convert_checkpoint.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def memory_cap(extra_gb: float = 2.0):
    """This process may map ``extra_gb`` more than it has: a reader that expands a crafted file
    without bound fails with MemoryError here instead of taking the machine's memory."""
    mapped = int(Path("/proc/self/statm").read_text().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (mapped + int(extra_gb * 2**30), hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


# ---------------------------------------------------------------- crafted checkpoints
def _demo() -> dict:
    return torch.load(DEMO, weights_only=True)


def _shared_lists(path: Path) -> Path:
    """The demo policy with a config value of shared lists: under 1 MB on disk, 2**30 values once
    expanded (each list holds the one below twice)."""
    payload, lists = _demo(), [0]
    for _ in range(30):
        lists = [lists, lists]
    payload["cfg"] = {**payload["cfg"], "notes": lists}
    torch.save(payload, path)
    assert path.stat().st_size < 1_000_000
    return path


def _deeply_nested(path: Path, depth: int = 200_000) -> Path:
    """The demo policy with a config value nested ``depth`` lists deep, its pickle edited by hand
    (pickling it would recurse as deep)."""
    payload, marker = _demo(), "NESTED_HERE"
    payload["cfg"] = {**payload["cfg"], "notes": marker}
    saved = io.BytesIO()
    torch.save(payload, saved)
    pickled = b"X" + struct.pack("<I", len(marker)) + marker.encode()  # the string's opcode
    nested = b"]" * depth + b"a" * (
        depth - 1
    )  # `depth` empty lists, each appended to the one below
    with zipfile.ZipFile(saved) as zin, zipfile.ZipFile(path, "w") as zout:
        for name in zin.namelist():
            data = zin.read(name)
            if name.endswith("data.pkl"):
                assert data.count(pickled) == 1
                data = data.replace(pickled, nested)
            zout.writestr(name, data)
    return path


def _not_finite(value: float):
    def make(path: Path) -> Path:
        payload = _demo()
        name = next(k for k, v in payload["loss"].items() if v.is_floating_point())
        payload["loss"][name] = payload["loss"][name].clone().fill_(value)
        torch.save(payload, path)
        return path

    return make


CRAFTED = {
    "shared lists": (_shared_lists, "more than 1,000,000 values"),
    "deep nesting": (_deeply_nested, "more than 64 levels deep"),
}


@pytest.mark.parametrize("kind", list(CRAFTED))
def test_a_crafted_checkpoint_is_refused_in_one_line_by_every_reader(tmp_path, capsys, kind):
    """Restore (eval, live), resume and the converter read a file that expands without bound, or
    nests without bound, as one line within seconds, in bounded memory, writing nothing."""
    make, said = CRAFTED[kind]
    path = make(tmp_path / "crafted.pt")
    tools = converter()
    with memory_cap():
        for read in (load_checkpoint, lambda p: restore(p, num_envs=1)):
            start = time.monotonic()
            with pytest.raises(CheckpointError) as info:
                read(path)
            message = str(info.value)
            assert "\n" not in message and str(path) in message and said in message
            assert time.monotonic() - start < 30
        assert tools.main([str(path), str(tmp_path / "new.pt")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and said in err and "Traceback" not in err
        assert icco("eval", f"checkpoint={path}", f"eval.out_dir={tmp_path / 'eval'}") == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("icco eval: ") and said in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["crafted.pt"]


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_weights_that_are_not_finite_are_refused_in_one_line(tmp_path, capsys, value):
    """NaN or inf weights act and evaluate to normal-looking numbers: restore (eval, live) and the
    commands refuse them, naming the weights."""
    path = _not_finite(value)(tmp_path / "diverged.pt")
    for read in (load_checkpoint, lambda p: restore(p, num_envs=1)):
        with pytest.raises(CheckpointError) as info:
            read(path)
        message = str(info.value)
        assert "\n" not in message and str(path) in message and "not finite" in message
        assert "agent_params." in message
    for command in ("eval", "live"):
        assert icco(command, f"checkpoint={path}", f"eval.out_dir={tmp_path / 'eval'}") == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith(f"icco {command}: ") and "NaN" in err
    assert load_checkpoint(path, require=())["frames"] >= 0  # the converter may still read it


# ---------------------------------------------------------------- the converter and the run's lock
def test_the_converter_refuses_a_checkpoint_a_training_holds_and_writes_nothing(tmp_path, capsys):
    """Converting a run's checkpoint.pt while an ``icco train`` writes the run folder would remove
    the training's temp file under it: refused in one line, the file left as it is."""
    tools = converter()
    run = tmp_path / "run"
    run.mkdir()
    target = run / "checkpoint.pt"
    target.write_bytes(DEMO.read_bytes())
    before = target.stat()
    for args in ([str(target), str(target)], [str(DEMO), str(target)]):
        with RunFolderLock(run):  # an icco train writing the folder
            assert tools.main(args) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "in use by another icco train" in err and str(run) in err
        after = target.stat()
        assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns)
        assert sorted(p.name for p in run.iterdir()) == [".train.lock", "checkpoint.pt"]
    assert tools.main([str(target), str(target)]) == 0  # once the training is gone
    assert load_checkpoint(target)["frames"] == _demo()["frames"]


# ---------------------------------------------------------------- a collector process that hangs
# Seconds-long runs: 8 envs x 16 steps = 128 frames a batch, nothing evaluated or checkpointed on
# the way.
FAST = (
    "experiment=smoke",
    "logger.progress=false",
    "eval.references=[]",
    "train.eval_interval=0",
    "train.checkpoint_interval=0",
    "device=cpu",
    "train.collector=process",
    "train.total_frames=1024",
)
PER_BATCH = 8 * 16


class _HangsAtTheThirdBatch:
    """A collector whose third batch never comes: an env step that never returns."""

    def __init__(self, collector):
        self.collector = collector

    def __iter__(self):
        for k, batch in enumerate(self.collector):
            if k == 2:
                time.sleep(3600)
            yield batch

    def shutdown(self):
        self.collector.shutdown()


def _hanging_collect(*args, **kwargs):
    """The collector process's entry, with its collector hanging in its third batch."""
    made = collector_process.inline_collector
    collector_process.inline_collector = lambda *a, **k: _HangsAtTheThirdBatch(made(*a, **k))
    collector_process._collect(*args, **kwargs)


def _children() -> list[int]:
    """This process's live children (multiprocessing's resource tracker left out)."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes()
        except (OSError, ValueError):
            continue
        state, ppid = stat.rsplit(")", 1)[1].split()[:2]
        if int(ppid) == os.getpid() and state != "Z" and b"resource_tracker" not in cmdline:
            found.append(int(entry.name))
    return found


@contextlib.contextmanager
def _signals_after(*delays: float, start: threading.Event | None = None):
    """SIGTERM to this process ``delays`` seconds after ``start`` is set (at once without one);
    those not sent when the block ends are not sent."""
    done = threading.Event()
    if start is None:
        start = threading.Event()
        start.set()

    def send():
        start.wait()
        begun = time.monotonic()
        for delay in delays:
            if done.wait(max(0.0, begun + delay - time.monotonic())):
                return
            os.kill(os.getpid(), signal.SIGTERM)

    thread = threading.Thread(target=send, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        start.set()
        thread.join()


def test_a_collector_that_hangs_is_one_line_killed_and_the_learner_saves(tmp_path, monkeypatch):
    """The learner waits a bounded time for a batch: then one line names the stuck process, which
    is killed, and the checkpoint holds every batch the learner took."""
    monkeypatch.setattr(collector_process, "_collect", _hanging_collect)
    monkeypatch.setattr(collector_process, "BATCH_WAIT_S", 3.0)
    monkeypatch.setattr(collector_process, "BATCH_WAIT_FACTOR", 1.0)
    start = time.monotonic()
    with _signals_after(90, 95), pytest.raises(CollectorError) as err:  # else it never ends
        train(compose_config(list(FAST)), tmp_path)
    message = str(err.value)
    assert "\n" not in message and "icco-collector (pid " in message and "stuck" in message
    assert "batch 3" in message and "killed it" in message
    assert time.monotonic() - start < 60 and not _children()
    assert load_checkpoint(tmp_path / "checkpoint.pt")["frames"] == 2 * PER_BATCH
    assert len((tmp_path / "timing.csv").read_text().splitlines()) == 1 + 2


def test_a_sigterm_stops_the_run_at_once_while_its_collector_hangs(tmp_path, monkeypatch, capsys):
    """A supervisor's SIGTERM (10-30 s before its SIGKILL) while the learner waits on a hung
    collector: the run stops within seconds, with a checkpoint of every batch it took."""
    monkeypatch.setattr(collector_process, "_collect", _hanging_collect)
    waiting, began = threading.Event(), []  # the learner waits for the batch that never comes
    receive = ProcessCollector._receive

    def receive_and_say(self):
        if self.released == 3:
            began.append(time.monotonic())
            waiting.set()
        return receive(self)

    monkeypatch.setattr(ProcessCollector, "_receive", receive_and_say)
    with _signals_after(1.0, 45.0, start=waiting):  # the second: else it never ends
        train(compose_config(list(FAST)), tmp_path)
        stopped = time.monotonic()
    took = stopped - began[0]
    assert took < 1.0 + 10.0, f"stopped {took:.1f} s after the wait began"
    assert "interrupted by SIGTERM at 256 frames: saving a checkpoint" in capsys.readouterr().out
    assert load_checkpoint(tmp_path / "checkpoint.pt")["frames"] == 2 * PER_BATCH
    assert not _children()


# ---------------------------------------------------------------- the commands a run prints
HOSTILE = ("run $(touch PWNED1) `touch PWNED2`; touch PWNED3", "Bob's run")


@pytest.mark.parametrize("interrupted", [False, True])
@pytest.mark.parametrize("name", HOSTILE)
def test_the_printed_next_and_continue_commands_are_shell_quoted(tmp_path, name, interrupted):
    """The ``next:`` and ``continue:`` lines are pasted into a shell: a run folder's name is one
    argument there, and nothing in it runs."""
    run = tmp_path / name
    run.mkdir()
    ckpt = run / "checkpoint.pt"
    ckpt.write_bytes(b"")
    message = finish_message(run, ckpt, 128, interrupted, {})
    word = "continue: " if interrupted else "next: "
    (line,) = [line.strip() for line in message.splitlines() if line.strip().startswith(word)]
    pasted = f'icco() {{ printf "%s\\n" "$@"; }}; {line[len(word) :]}'
    said = subprocess.run(["bash", "-c", pasted], cwd=tmp_path, capture_output=True, text=True)
    expected = (
        ["train", f"resume={ckpt}"]
        if interrupted
        else ["eval", f"checkpoint={ckpt}", "eval.protocol=quadrants"]
    )
    assert said.stdout.splitlines() == expected, said.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


# ---------------------------------------------------------------- a read-only run folder
def _read_only(folder: Path) -> list[str]:
    """The command prefix under which ``folder`` is read-only: its modes for a user, a read-only
    bind mount for root (whom modes do not stop); skipped where neither is possible."""
    if os.geteuid() != 0:
        for path in [folder, *folder.rglob("*")]:
            path.chmod(path.stat().st_mode & ~0o222)
        return []
    mount = 'mount --bind "$0" "$0" && mount -o remount,bind,ro "$0" && exec "$@"'
    prefix = ["unshare", "-m", "sh", "-c", mount, str(folder)]
    try:
        probe = subprocess.run([*prefix, "sh", "-c", f"! touch '{folder}/probe'"], timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        pytest.skip("no way to make a folder read-only here (root, no unshare)")
    if probe.returncode != 0:
        pytest.skip("no way to make a folder read-only here (root, no mount namespace)")
    return prefix


def test_resuming_in_a_read_only_run_folder_is_one_line(tmp_path):
    run = tmp_path / "run"
    fast = [*FAST[:-2], "train.total_frames=256"]  # inline: a seconds-long run
    train(compose_config(fast), run)
    before = {p.name: p.stat().st_mtime_ns for p in run.iterdir()}
    prefix = _read_only(run)
    try:
        proc = subprocess.run(
            [*prefix, sys.executable, "-m", "icco_torchrl", "train", *fast]
            + ["train.total_frames=512", f"resume={run / 'checkpoint.pt'}"],
            cwd=ROOT,
            env={**os.environ, "OMP_NUM_THREADS": "1", "WANDB_MODE": "disabled"},
            capture_output=True,
            text=True,
            timeout=300,
        )
    finally:
        for path in [run, *run.rglob("*")]:
            path.chmod(path.stat().st_mode | 0o200)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    line = proc.stderr.strip()
    assert "\n" not in line and line.startswith("icco train: ") and str(run) in line, line
    assert "Read-only file system" in line or "Permission denied" in line
    assert "resume" in line and "writable" in line
    assert {p.name: p.stat().st_mtime_ns for p in run.iterdir()} == before


# ---------------------------------------------------------------- the command line's one line
@pytest.mark.parametrize(
    "typed, meant",
    [
        (["eval", "eval.protocl=quadrants"], "eval.protocol"),
        (["eval", "-m", "eval.protocl=quadrants,random_walk"], "eval.protocol"),
        (["train", "trian.totl_frames=3"], "train.total_frames"),
        (["eval", "env.params.n_agnets=3"], "env.params.n_agents"),
        (["eval", "sede=1"], "seed"),
    ],
)
def test_a_misspelled_field_is_one_line_with_the_field_meant(
    tmp_path, monkeypatch, capsys, typed, meant
):
    monkeypatch.chdir(tmp_path)
    assert icco(*typed) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"icco {typed[0]}: config field ")
    assert err.rstrip().endswith(f"; did you mean {meant}?")
    assert not list(tmp_path.iterdir())


def test_a_field_nothing_like_any_other_gets_no_guess(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert icco("eval", "eval.zzzzqqq=1") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "zzzzqqq" in err and "did you mean" not in err


MISSING = {
    "eval": ("icco eval checkpoint=assets/demo_icco.pt",),
    "live": ("icco live checkpoint=assets/demo_icco.pt",),
    "bridge": ("icco bridge checkpoint=assets/demo_icco.pt",),
    "instruct": ('icco instruct "Go right" checkpoint=assets/demo_icco.pt',),
    "train": ("icco eval checkpoint=assets/demo_icco.pt", "resume="),
}


@pytest.mark.parametrize("command", list(MISSING))
def test_every_missing_checkpoint_names_the_demo_policy(tmp_path, monkeypatch, capsys, command):
    """A checkpoint that is not there is one line naming what the command can run instead: the
    demo policy, as ``icco eval`` names it when it finds no checkpoint."""
    monkeypatch.chdir(ROOT)  # the checkout, as `make` runs the commands
    missing = tmp_path / "run" / "missing.pt"
    key = "resume" if command == "train" else "checkpoint"
    args = [command, *(["Go right"] if command == "instruct" else [])]
    args += [f"{key}={missing}", "live.seconds=1", f"eval.out_dir={tmp_path / 'out'}"]
    assert icco(*args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"icco {command}: checkpoint not found: ")
    assert str(missing) in err and "(assets/README.md)" in err
    assert all(said in err for said in MISSING[command]), err
