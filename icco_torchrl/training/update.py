"""One gradient update as one function: the loss, its backward, the grad-norm clip and the
optimiser step, on a replayed batch; eager, compiled, or captured in a CUDA graph.

``train.compile`` compiles the loss's tensor part (:meth:`ICCOLoss.compile`): every network,
the targets and both terms in one graph with no break, and the backward AOTAutograd derives
from it, so the ~7,000 small ops of an eager forward and backward become a few hundred
matrix products and fused kernels. ``train.cudagraphs`` (CUDA only) captures the whole update
in one CUDA graph with tensordict's ``CudaGraphModule``, as TorchRL's sota scripts and LeanRL
do: one launch an update, no host sync. The target networks' copy stays outside (TorchRL's
``HardUpdate`` counts in Python). ``benchmarks/train_speed.py`` measures the paths side by side.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase

from icco_torchrl.objectives import ICCOLoss, total_loss

# Compiled kernels persist here across runs (a cold compile of the ICCO update takes minutes on
# a CPU, a warm one seconds), unless TORCHINDUCTOR_CACHE_DIR says otherwise.
CACHE_DIR = Path.home() / ".cache" / "icco_torchrl" / "inductor"


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
        if compile:
            reason = can_compile()
            if reason is None:
                os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(CACHE_DIR))
                loss.compile(fullgraph=True, dynamic=False, mode=compile_mode or None)
                self.compiled = True
            else:
                print(
                    f"note: train.compile=true but this torch cannot compile ({reason}): "
                    f"the update runs eagerly",
                    flush=True,
                )
        self._step = self._update
        if cudagraphs:
            self._capture(warmup)

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
        return self._step(batch)


def metrics_row(metrics: TensorDict) -> dict[str, float]:
    """The metrics as floats (one host sync)."""
    values = torch.stack([v.float() for v in metrics.values()]).tolist()
    return dict(zip(metrics.keys(), values))
