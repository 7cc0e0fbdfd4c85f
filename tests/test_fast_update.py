"""The fast update: a traceable GRU with nn.GRU's parameters, the loss's in_keys, the compiled
loss against the eager one (same loss terms and gradients on a fixed batch), the options' bad
input and one training run through the CLI with the compiled update.

The two compiling tests share one Inductor cache, compile one at a time and run in one xdist
group (``make test`` runs with ``--dist loadgroup``), so the CLI run loads what the first test
compiled: Inductor's kernels and AOTAutograd's compiled forward and backward (its cache skips a
graph with a custom autograd.Function, the loss's ReLU, unless told otherwise; the cache is this
test session's own, so no entry outlives the code that made it). A cache that cannot be used, a
failing compile and a stop during a cold compile (cut short after seconds) are checked too.
"""

from __future__ import annotations

import errno
import logging
import os
import pickle
import signal
import subprocess
import sys
import time
from collections import namedtuple
from pathlib import Path

import pytest
import torch
from conftest import locked, run_cli, session_dir
from torch import nn

from icco_torchrl.modules.gru import GRU
from icco_torchrl.objectives import total_loss
from icco_torchrl.training import compile_cache
from icco_torchrl.training import update as update_module
from icco_torchrl.training.build import build, build_components, compose_config
from icco_torchrl.training.checkpoint import load_checkpoint
from icco_torchrl.training.config import ConfigError, validate
from icco_torchrl.training.segments import SegmentCutter
from icco_torchrl.training.update import Update

# Small, fast to compile: the smoke recipe with one broadcast per item.
COMPILE_RECIPE = ["experiment=smoke", "train.sequence_length=4", "method.hidden=16"]


@pytest.fixture(scope="module")
def inductor_env(tmp_path_factory):
    """This test run's Inductor cache (shared by the xdist workers), given to this process and to
    the CLI runs it starts, with AOTAutograd's cache on for the loss's custom autograd.Function
    (the CLI run then loads the compiled forward and backward instead of tracing them again)."""
    import torch._functorch.config as functorch_config

    path = session_dir(tmp_path_factory, "icco-inductor-cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("TORCHINDUCTOR_CACHE_DIR", str(path))
        patch.setenv("TORCHINDUCTOR_AUTOGRAD_CACHE_ALLOW_CUSTOM_AUTOGRAD", "1")  # the CLI's
        patch.setattr(functorch_config, "autograd_cache_allow_custom_autograd_functions", True)
        yield path


@pytest.fixture
def inductor_cache(inductor_env):
    """The shared cache, compiled into by one test at a time: whichever compiling test comes
    second (on any xdist worker) loads what the first compiled."""
    with locked(inductor_env.parent / f"{inductor_env.name}.lock"):
        yield inductor_env


def test_gru_has_nn_grus_parameters_init_and_values():
    """Same state-dict names and shapes (checkpoints load), the same seeded init, the same outputs
    as nn.GRU on a sequence and a step, and the unrolled (compiled) form equal to both."""
    torch.manual_seed(3)
    ref = nn.GRU(6, 5, batch_first=True)
    torch.manual_seed(3)
    gru = GRU(6, 5)
    assert list(gru.state_dict()) == list(ref.state_dict())
    for name, value in ref.state_dict().items():
        torch.testing.assert_close(gru.state_dict()[name], value, atol=0, rtol=0)
    x, h0 = torch.randn(4, 7, 6), torch.randn(4, 5)
    out_ref, h_ref = ref(x, h0.unsqueeze(0))
    out, h = gru(x, h0)
    torch.testing.assert_close(out, out_ref)
    torch.testing.assert_close(h, h_ref.squeeze(0))
    out_u, h_u = gru.unrolled(x, h0)
    torch.testing.assert_close(out_u, out_ref, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(h_u, h_ref.squeeze(0), atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(gru.step(x[:, 0], h0), out_ref[:, 0])


def test_in_keys_are_what_the_loss_reads():
    """The replay stores the loss's keys: every key the update touches, and no other. A loss run on
    a batch cut down to its in_keys gives the same terms as on the whole batch."""
    parts = build_components(method="icco", num_envs=4)
    keys = parts["loss"].in_keys
    assert ("agents", "z_noise") in keys and ("next", "state") in keys and "mask" in keys
    qmix = build_components(method="qmix", num_envs=4)["loss"].in_keys
    assert ("agents", "z") not in qmix and ("agents", "rnn_hidden") in qmix
    torch.manual_seed(0)
    with torch.no_grad():
        rollout = parts["env"].rollout(16, parts["policy"], break_when_any_done=False)
    items = SegmentCutter(length=16)(rollout)
    torch.manual_seed(1)
    whole = parts["loss"](items)
    torch.manual_seed(1)
    cut = parts["loss"](items.select(*keys, strict=True))
    for name in whole.keys():
        torch.testing.assert_close(cut[name], whole[name], atol=0, rtol=0)
    parts["loss"].set_keys(state="global_state", z_noise=("agents", "eps"))  # renamed: read
    renamed = parts["loss"].in_keys
    assert "global_state" in renamed and ("next", "global_state") in renamed
    assert ("agents", "eps") in renamed and ("agents", "z_noise") not in renamed
    assert "state" in renamed  # the mixer's own in_key
    assert parts["loss"].out_keys == list(parts["loss"].metric_keys)


def _grads(loss):
    return {n: p.grad.clone() for n, p in loss.named_parameters() if p.grad is not None}


@pytest.mark.xdist_group("compile")
def test_compiled_loss_gives_the_eager_losses_and_gradients(inductor_cache):
    """ICCO (coordinator, posterior, lambda-returns): the compiled loss's terms and every
    gradient equal the eager loss's on a fixed batch, to float tolerance; then one compiled
    update moves the weights as the eager one does."""
    cfg = compose_config(["method=icco", "device=cpu", *COMPILE_RECIPE])
    torch.manual_seed(0)
    run = build(cfg, for_training=True)
    with torch.no_grad():
        rollout = run.env.rollout(40, run.policy, break_when_any_done=False)
    items = run.cutter(rollout.select(*run.loss.in_keys, strict=False))
    batch = items[: cfg.train.batch_segments]
    torch.manual_seed(5)
    eager = run.loss(batch)
    total_loss(eager).backward()
    eager_grads = _grads(run.loss)
    run.loss.zero_grad(set_to_none=True)

    run.loss.compile_losses(fullgraph=True, dynamic=False)
    torch.manual_seed(5)
    compiled = run.loss(batch)
    total_loss(compiled).backward()
    assert set(compiled.keys()) == set(eager.keys())
    for name in eager.keys():
        torch.testing.assert_close(compiled[name], eager[name], atol=1e-5, rtol=1e-4)
    grads = _grads(run.loss)
    assert grads.keys() == eager_grads.keys() and len(grads) > 20
    for name, grad in eager_grads.items():
        scale = grad.abs().max().clamp_min(1.0)
        torch.testing.assert_close(grads[name] / scale, grad / scale, atol=2e-5, rtol=1e-4)


@pytest.mark.xdist_group("compile")
def test_compiled_training_through_the_cli(tmp_path, inductor_cache):
    """`icco train train.compile=true` trains, evaluates and saves like the eager run, and its
    first evaluation matches the eager run's (same seed: the same data up to the first
    update's float noise)."""
    out = run_cli(
        "train",
        *COMPILE_RECIPE,
        "train.compile=true",
        "train.checkpoint_buffer=false",
        "eval.references=[]",  # the scripted policies: the eager runs of test_train_cli.py
        f"hydra.run.dir={tmp_path}",
        timeout=600,
    )
    assert "done: 2,048 env steps" in out.stdout and "runs eagerly" not in out.stdout
    assert (tmp_path / "checkpoint.pt").exists() and (tmp_path / "eval.csv").exists()
    rows = (tmp_path / "train.csv").read_text().splitlines()
    header = rows[0].split(",")
    last = dict(zip(header, rows[-1].split(",")))
    assert float(last["updates"]) > 0 and float(last["loss_td"]) == float(last["loss_td"])


def _update_and_batch(compile: bool):
    torch.manual_seed(0)
    run = build_components(method="qmix", num_envs=2)
    with torch.no_grad():
        batch = SegmentCutter(length=16)(run.env.rollout(32, run.policy))
    update = Update(run.loss, torch.optim.Adam(run.loss.parameters()), compile=compile)
    return update, batch


_full_disk = namedtuple("usage", "total used free")(1 << 40, 1 << 40, 1 << 20)


@pytest.mark.parametrize("case", ["not a folder", "read-only", "full", "set aside at import"])
def test_an_unusable_compile_cache_gives_one_line_then_the_eager_update(
    tmp_path, monkeypatch, capsys, case
):
    """Found before compiling: a cache path through a file (torch's own import fails on one:
    the command sets it aside first), a read-only folder (even a warm one), a full disk."""
    folder = tmp_path / "cache"
    monkeypatch.setattr(compile_cache, "_noted", True)
    monkeypatch.setattr(compile_cache, "_given", str(folder))
    monkeypatch.setattr(compile_cache, "_set_aside", None)
    said = {
        "not a folder": f"{folder}: not a folder",
        "read-only": f"{folder}: Read-only file system",
        "full": f"{folder}: only 1 MB free on its disk",
        "set aside at import": f"TORCHINDUCTOR_CACHE_DIR={tmp_path / 'file' / 'cache'}: ",
    }[case]
    if case == "not a folder":
        folder.write_text("a file")
    elif case == "read-only":

        def read_only(**kwargs):
            raise OSError(errno.EROFS, "Read-only file system")

        monkeypatch.setattr(compile_cache.tempfile, "mkstemp", read_only)
    elif case == "full":
        monkeypatch.setattr(compile_cache.shutil, "disk_usage", lambda path: _full_disk)
    else:
        (tmp_path / "file").write_text("a file")
        monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "file" / "cache"))
        compile_cache.note_environment()  # what `icco` does before importing torch
        assert "TORCHINDUCTOR_CACHE_DIR" not in os.environ  # so torch's import succeeds
        said += "Not a directory"
    env_before = os.environ.get("TORCHINDUCTOR_CACHE_DIR")
    update, batch = _update_and_batch(compile=True)
    assert not update.compiled
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines == [
        f"note: train.compile=true but its Inductor cache cannot be used ({said}): the update "
        "runs eagerly"
    ]
    assert "loss_td" in update(batch).keys()
    assert os.environ.get("TORCHINDUCTOR_CACHE_DIR") == env_before


@pytest.mark.parametrize("case", ["a compile failure", "a warning", "the loss's own error"])
def test_a_failing_compile_gives_one_line_then_the_eager_update(tmp_path, monkeypatch, capfd, case):
    """A compile that fails at the first update (a damaged cache: torch's error for a damaged
    kernel module; a compiler error): one line, then this update and the next run eagerly,
    stepping the weights as the eager update does. A warning torch logs while compiling (an
    unreadable cache entry it compiles again, with its traceback) is one line. An error of the
    loss itself is raised as it is."""
    from torch._dynamo.exc import BackendCompilerFailed

    def inductor():
        pass

    def fail_once(fn, **kwargs):
        calls = []

        def compiled(*args, **kw):
            calls.append(1)
            if case == "the loss's own error":
                raise ValueError("not the compiler")
            if len(calls) == 1 and case == "a compile failure":
                error = RuntimeError(f"Failed to import {tmp_path}/ab/cab.py")
                raise BackendCompilerFailed(inductor, error, None)
            if len(calls) == 1 and case == "a warning":
                try:
                    raise pickle.UnpicklingError("could not find MARK")
                except pickle.UnpicklingError:
                    logging.getLogger("torch._inductor.codecache").warning(
                        "fx graph cache unable to load compiled graph", exc_info=True
                    )
            return fn(*args, **kw)

        return compiled

    monkeypatch.setattr(compile_cache, "chosen", lambda: (tmp_path, None))
    monkeypatch.setattr(torch, "compile", fail_once)
    eager, batch = _update_and_batch(compile=False)
    eager(batch), eager(batch)
    compiled, _ = _update_and_batch(compile=True)
    assert compiled.compiled and capfd.readouterr() == ("", "")
    if case == "the loss's own error":
        with pytest.raises(ValueError, match="not the compiler"):
            compiled(batch)
        assert "note:" not in capfd.readouterr().out
        return
    compiled(batch), compiled(batch)
    out, err = capfd.readouterr()
    lines = out.strip().splitlines()
    assert lines[0].startswith("compiling the update") and len(lines) == 2, lines
    assert err == ""
    assert (
        lines[1]
        == {
            "a compile failure": (
                f"note: train.compile=true but the compile failed (RuntimeError: Failed to import "
                f"{tmp_path}/ab/cab.py; if its cache is damaged, delete {tmp_path}): the update "
                "runs eagerly"
            ),
            "a warning": (
                "note: torch.compile: fx graph cache unable to load compiled graph "
                "(UnpicklingError: could not find MARK)"
            ),
        }[case]
    )
    assert compiled.compiled == (case == "a warning")
    for a, b in zip(compiled.loss.parameters(), eager.loss.parameters()):
        torch.testing.assert_close(a, b)


@pytest.mark.fault
def test_sigterm_during_a_cold_compile_stops_the_run_within_seconds_with_its_checkpoint(
    tmp_path,
):
    """A cold compile blocks the first update for a minute or more: SIGTERM cuts it short (the
    update is abandoned before its optimiser step) and the run saves its checkpoint and exits
    within Docker's 10 s grace period."""
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "WANDB_MODE": "disabled",
        "PYTHONUNBUFFERED": "1",
        "TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "cold-cache"),
    }
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "icco_torchrl", "train", *COMPILE_RECIPE, "train.compile=true"]
    proc = subprocess.Popen(
        [*cmd, "logger.progress=false", f"hydra.run.dir={run}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        for line in proc.stdout:
            if line.startswith("compiling the update"):
                break
        else:
            pytest.fail(f"the run ended before compiling: {proc.stderr.read()[-3000:]}")
        time.sleep(3)  # well inside the cold compile
        sent = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
        took = time.monotonic() - sent
    finally:
        proc.kill()
    assert proc.returncode == 0, err[-3000:]
    assert took < 10, f"stopped {took:.1f} s after SIGTERM"
    assert "interrupted by SIGTERM" in out and "Traceback" not in err, out + err[-3000:]
    ckpt = load_checkpoint(run / "checkpoint.pt")
    assert ckpt["frames"] > 0 and ckpt["updates"] == 0  # the abandoned update was not applied


def test_cudagraphs_on_a_cpu_fails_naming_the_field():
    with pytest.raises(ConfigError, match=r"config field 'train.cudagraphs'.*CUDA device"):
        validate(compose_config(["device=cpu", "train.cudagraphs=true"]))
    parts = build_components(method="qmix", num_envs=2)
    with pytest.raises(ValueError, match="cudagraphs captures CUDA kernels"):
        Update(parts["loss"], torch.optim.Adam(parts["loss"].parameters()), cudagraphs=True)


def test_gpu_recipe_without_a_gpu_fails_naming_the_field():
    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    with pytest.raises(ConfigError, match="config field 'device'"):
        validate(compose_config(["experiment=gpu"]))


def test_a_torch_that_cannot_compile_gets_a_note_and_the_eager_path(monkeypatch, capsys):
    monkeypatch.setattr(update_module, "can_compile", lambda: "no inductor in this build")
    parts = build_components(method="qmix", num_envs=2)
    update = Update(parts["loss"], torch.optim.Adam(parts["loss"].parameters()), compile=True)
    assert not update.compiled
    err = capsys.readouterr().out.strip().splitlines()
    assert len(err) == 1 and "cannot compile (no inductor in this build)" in err[0]


def test_episode_tracker_matches_the_step_by_step_totals():
    """The batched episode totals equal a step-by-step running sum, bit for bit and in the order
    the episodes ended, across batches, with several ends per env in one batch."""
    from tensordict import TensorDict

    from icco_torchrl.envs import EVENT_KEYS
    from icco_torchrl.trainer import EpisodeTracker

    g = torch.Generator().manual_seed(0)
    B, L = 5, 12
    tracker, sums, expected, got = (
        EpisodeTracker(B, "cpu"),
        torch.zeros(B, 1 + len(EVENT_KEYS)),
        [],
        [],
    )
    for _ in range(4):
        reward = torch.randn(B, L, 1, generator=g)
        events = {k: torch.rand(B, L, generator=g) < 0.3 for k in EVENT_KEYS}
        done = torch.rand(B, L, 1, generator=g) < 0.2
        batch = TensorDict(
            {"next": {"reward": reward, "done": done, "events": events}}, batch_size=[B, L]
        )
        got.append(tracker.update(batch))
        values = torch.stack([reward.squeeze(-1)] + [events[k].float() for k in EVENT_KEYS], -1)
        for t in range(L):
            sums += values[:, t]
            ends = done[:, t, 0]
            expected.append(sums[ends].clone())
            sums[ends] = 0
    torch.testing.assert_close(torch.cat(got), torch.cat(expected), atol=0, rtol=0)
    assert torch.cat(got).shape[0] > 10
    torch.testing.assert_close(tracker.sums, sums, atol=0, rtol=0)


def _captured_against_plain() -> None:
    results = []
    for captured in (False, True):
        torch.manual_seed(0)
        parts = build_components(method="icco", num_envs=4)
        with torch.no_grad():
            items = SegmentCutter(length=16)(parts["env"].rollout(32, parts["policy"]))
        loss = parts["loss"]
        start = [p.detach().clone() for p in loss.parameters()]
        update = Update(loss, torch.optim.Adam(loss.parameters(), foreach=True), grad_clip=10.0)
        if captured:
            update._capture(warmup=2)
        torch.manual_seed(1)
        metrics = [update(items) for _ in range(3)]
        results.append((metrics, [p.detach().clone() for p in loss.parameters()], start))
    (plain, w_plain, start), (graph, w_graph, _) = results
    for a, b in zip(plain, graph):
        for name in a.keys():
            torch.testing.assert_close(b[name], a[name], atol=1e-6, rtol=1e-5)
    for a, b in zip(w_plain, w_graph):
        torch.testing.assert_close(b, a, atol=1e-6, rtol=1e-5)
    assert sum(not torch.equal(a, b) for a, b in zip(w_plain, start)) > 20  # the weights moved


def test_the_captured_update_steps_as_the_plain_one():
    """The CUDA-graph wiring (CudaGraphModule over the whole update, gradients zeroed rather
    than freed, no finite check), run on a CPU where CudaGraphModule calls it eagerly: the same
    metrics and the same weights after three updates as the plain update. In a child process:
    CudaGraphModule takes TensorDict out of torch's pytree registry for good."""
    proc = subprocess.run(
        [sys.executable, "-c", "import test_fast_update as t; t._captured_against_plain()"],
        cwd=Path(__file__).parent,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
