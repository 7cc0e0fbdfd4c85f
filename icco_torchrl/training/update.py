"""One gradient update as one function: the loss, its backward, the grad-norm clip and the
optimiser step, on a replayed batch; eager, compiled, or captured in a CUDA graph.

``train.compile`` compiles the loss's tensor part (:meth:`ICCOLoss.compile_losses`): every network,
the targets and both terms in one graph with no break, and the backward AOTAutograd derives
from it, so the ~7,000 small ops of an eager forward and backward become a few hundred
matrix products and fused kernels. ``train.cudagraphs`` (CUDA only) captures the whole update
in one CUDA graph with tensordict's ``CudaGraphModule``, as TorchRL's sota scripts and LeanRL
do: one launch an update, no host sync. The target networks' copy stays outside (TorchRL's
``HardUpdate`` counts in Python). ``benchmarks/train_speed.py`` measures the paths side by side.

The compiled kernels persist in :data:`CACHE_DIR` (or ``TORCHINDUCTOR_CACHE_DIR``), given to
Inductor only while the update compiles or runs (:mod:`.compile_cache`). Whatever keeps the
update from compiling (a torch without Inductor, a cache folder that cannot be used, a damaged
cache, a failing compile) is one line, then the eager update; torch's warnings while it compiles
are one line each. A stop (Ctrl-C, SIGTERM) during the first compiled update cuts the compile
short (:func:`~icco_torchrl.training.interrupt.abandonable`): the update is abandoned before its
optimiser step.
"""

from __future__ import annotations

import logging
import os
import re
import traceback
from contextlib import contextmanager, nullcontext
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase

from icco_torchrl.objectives import ICCOLoss, total_loss
from icco_torchrl.training import compile_cache
from icco_torchrl.training.interrupt import abandonable


def can_compile() -> str | None:
    """None when this torch build can compile, else the reason it cannot."""
    try:
        import torch._dynamo  # noqa: F401
        import torch._inductor  # noqa: F401
    except Exception as err:  # a build without Dynamo or Inductor
        return f"{type(err).__name__}: {err}"
    if not torch._dynamo.is_dynamo_supported():
        return "torch._dynamo is not supported on this Python or platform"
    return None


class Update:
    """``update(batch) -> metrics``: one gradient step of ``loss`` with ``optim``.

    Args:
        loss: the :class:`~icco_torchrl.objectives.ICCOLoss` (its parameters are ``optim``'s).
        optim: the optimiser.

    Keyword Args:
        grad_clip: global grad-norm clip (0: none); the norm is returned as ``grad_norm``.
        compile: compile the loss's tensor part (``torch.compile``; a build that cannot
            compile gets a one-line note and the eager path).
        compile_mode: ``torch.compile``'s ``mode`` (None: its default).
        cudagraphs: capture the update in a CUDA graph (the loss's device must be CUDA).
        warmup: eager calls before a CUDA graph is captured.

    The metrics are a detached TensorDict of the loss's ``metric_keys`` (and ``grad_norm``), left
    on the device: reading them (``.item()``) is the caller's one host sync.

    Examples:
        >>> import torch
        >>> from icco_torchrl.training.build import build_components
        >>> from icco_torchrl.training.segments import SegmentCutter
        >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
        <torch._C.Generator object at ...>
        >>> run = build_components(method="qmix", num_envs=4)
        >>> with torch.no_grad():
        ...     items = SegmentCutter(length=16)(run.env.rollout(32, run.policy))
        >>> update = Update(run.loss, torch.optim.Adam(run.loss.parameters()), grad_clip=10.0)
        >>> metrics = update(items)
        >>> sorted(metrics.keys())[:3]
        ['grad_norm', 'loss_td', 'q_taken']
    """

    def __init__(
        self,
        loss: ICCOLoss,
        optim: torch.optim.Optimizer,
        *,
        grad_clip: float = 0.0,
        compile: bool = False,
        compile_mode: str | None = None,
        cudagraphs: bool = False,
        warmup: int = 5,
    ):
        self.loss, self.optim, self.grad_clip = loss, optim, float(grad_clip)
        self.params = [p for p in loss.parameters() if p.requires_grad]
        device = self.params[0].device
        if cudagraphs and device.type != "cuda":
            raise ValueError(
                f"cudagraphs captures CUDA kernels: the loss is on {device}, not a CUDA device"
            )
        self.compiled, self.cudagraphs = False, cudagraphs
        self.cache_dir: Path | None = None  # Inductor's cache, while compiled
        self._compiling = False  # until the first compiled update is done
        self._warned: set[str] = set()  # torch's warnings already said
        if compile:
            self._compile(compile_mode)
        self._step = self._update
        if cudagraphs:
            self._capture(warmup)

    def _compile(self, mode: str | None) -> None:
        """Compile the loss (at its first call), unless this torch cannot or the cache folder
        cannot be used: then one line, and the eager path."""
        reason = can_compile()
        if reason is not None:
            _eager_note(f"this torch cannot compile ({reason})")
            return
        folder, problem = compile_cache.chosen()
        if problem is not None:
            _eager_note(f"its Inductor cache cannot be used ({problem})")
            return
        with compile_cache.scoped(folder):
            self.loss.compile_losses(fullgraph=True, dynamic=False, mode=mode or None)
        self.compiled, self.cache_dir, self._compiling = True, folder, True

    def _capture(self, warmup: int) -> None:
        """Route every call through tensordict's ``CudaGraphModule`` (eager warm-up calls on a
        side stream, then one captured graph replayed; without CUDA it runs eagerly, which is
        how the tests check its wiring on a CPU)."""
        from tensordict.nn import CudaGraphModule

        # A captured graph replays the very same kernels: the finite check (a host sync and a
        # Python branch) moves to the metrics the caller reads once a batch, and gradients keep
        # their buffers (zeroed, not freed).
        self.loss.check_finite = False
        self.cudagraphs = True
        self._step = CudaGraphModule(self._update, warmup=warmup, in_keys=[], out_keys=[])

    def _update(self, batch: TensorDictBase) -> TensorDictBase:
        # The forward and backward change nothing a checkpoint holds: a stop may cut short the
        # first compiled one (where a cold compile takes minutes), never the optimiser step.
        with abandonable() if self._compiling else nullcontext():
            losses = self.loss(batch)
            self.optim.zero_grad(set_to_none=not self.cudagraphs)
            total_loss(losses).backward()
        if self.grad_clip > 0:
            losses["grad_norm"] = torch.nn.utils.clip_grad_norm_(self.params, self.grad_clip)
        self.optim.step()
        return losses.detach()

    def __call__(self, batch: TensorDictBase) -> TensorDictBase:
        if self.cudagraphs and torch.cuda.is_available():
            torch.compiler.cudagraph_mark_step_begin()
        if not self.compiled:
            return self._step(batch)
        quiet = nullcontext()
        if self._compiling:
            print(
                f"compiling the update (Inductor cache {self.cache_dir}): a minute or more on a "
                "CPU when the cache is cold, seconds when it is warm",
                flush=True,
            )
            quiet = _torch_warnings_in_one_line(self._warned)
        try:
            with compile_cache.scoped(self.cache_dir), quiet:
                metrics = self._step(batch)
        except Exception as err:
            if not _compiler_failed(err, self.cache_dir):
                raise
            # Nothing was stepped (a compile fails in the forward or the backward): the loss runs
            # eagerly from now on, this update included.
            self.compiled, self._compiling = False, False
            _eager_note(
                f"the compile failed ({_error_line(err)}; if its cache is damaged, delete "
                f"{self.cache_dir})"
            )
            self._step = _force_eager(self._step)
            return self._step(batch)
        self._compiling = False
        return metrics


def _eager_note(why: str) -> None:
    print(f"note: train.compile=true but {why}: the update runs eagerly", flush=True)


def _force_eager(step):
    """``step`` with every ``torch.compile``'d function in it run as plain Python."""

    def eager(batch: TensorDictBase) -> TensorDictBase:
        with torch.compiler.set_stance("force_eager"):
            return step(batch)

    return eager


# Where a compile failure is raised from: torch's compiler stack (Dynamo, AOTAutograd, Inductor).
_COMPILER_PARTS = tuple(
    os.path.join("torch", part, "") for part in ("_dynamo", "_functorch", "_inductor")
)


def _compiler_failed(err: Exception, cache_dir: Path | None) -> bool:
    """Whether ``err`` came from compiling (or from kernels loaded from the cache), not from the
    loss itself (a non-finite loss is the loss's own error, raised as before)."""
    from torch._dynamo.exc import TorchDynamoException

    if isinstance(err, (TorchDynamoException, OSError)):
        return True
    parts = _COMPILER_PARTS + ((str(cache_dir),) if cache_dir else ())
    for frame, _ in traceback.walk_tb(err.__traceback__):
        if any(part in frame.f_code.co_filename for part in parts):
            return True
    return False


def _error_line(err: BaseException) -> str:
    """The informative line of a compile error (torch's span a page)."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    lines = [line for line in lines if not re.fullmatch(r"backend=.* raised:", line)]
    line = lines[0] if lines else ""
    if not re.match(r"[\w.]+(Error|Exception|Failed)\b", line):
        line = f"{type(err).__name__}: {line}" if line else type(err).__name__
    return line[:200]


@contextmanager
def _torch_warnings_in_one_line(said: set[str]):
    """torch's warnings inside the block (a damaged cache entry it compiles again prints a
    traceback) as one line each, said once."""
    caught: list[logging.LogRecord] = []

    class Catch(logging.Filter):
        def filter(self, record: logging.LogRecord) -> bool:
            if record.levelno < logging.WARNING or record.name.split(".")[0] != "torch":
                return True
            caught.append(record)
            return False

    catch = Catch()
    loggers = [logging.root] + [
        logger
        for name, logger in list(logging.root.manager.loggerDict.items())
        if name.split(".")[0] == "torch" and isinstance(logger, logging.Logger)
    ]
    handlers = {handler for logger in loggers for handler in logger.handlers}
    for handler in handlers:
        handler.addFilter(catch)
    try:
        yield
    finally:
        for handler in handlers:
            handler.removeFilter(catch)
        for record in caught:
            line = (record.getMessage().strip().splitlines() or [""])[0][:200]
            if record.exc_info and record.exc_info[1] is not None:
                line += f" ({_error_line(record.exc_info[1])})"
            if line not in said:
                said.add(line)
                print(f"note: torch.compile: {line}", flush=True)


def metrics_row(metrics: TensorDict) -> dict[str, float]:
    """The metrics as floats (one host sync)."""
    values = torch.stack([v.float() for v in metrics.values()]).tolist()
    return dict(zip(metrics.keys(), values))
