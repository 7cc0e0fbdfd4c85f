"""ReLU for the compiled update: the same function and gradient, with no boolean mask saved.

``torch.relu``'s backward is ``threshold_backward(grad, x, 0)``: AOTAutograd saves the mask
``x <= 0`` as a ``bool`` tensor for it, and Inductor's CPU kernels store a ``bool`` tensor about
20x slower than eager does (a 1536 x 128 mask: 1.9 ms against 90 us), so the ReLU-backward
kernels were the largest fused kernels of the compiled update (``benchmarks/README.md``, "The
compiled update"). :class:`ReLU` saves the float output ``y`` instead and multiplies the incoming
gradient by ``sign(y)``: 1 where ``x > 0``, 0 elsewhere, exactly ``threshold_backward``'s
gradient. Outside ``torch.compile`` it is plain ``torch.relu`` (eager ops, acting), so eager
results are unchanged bit for bit.

Examples:
    >>> import torch
    >>> x = torch.tensor([-1.0, 0.0, 2.0], requires_grad=True)
    >>> SignReLU.apply(x).sum().backward()
    >>> x.grad
    tensor([0., 0., 1.])
"""

from __future__ import annotations

import torch
from torch import nn


class SignReLU(torch.autograd.Function):
    """``relu`` whose backward reads the saved output: ``grad * sign(y)`` (no bool tensor)."""

    @staticmethod
    def forward(x: torch.Tensor) -> torch.Tensor:
        return x.clamp_min(0)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.save_for_backward(output)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        (y,) = ctx.saved_tensors
        return grad * torch.sign(y)


def relu(x: torch.Tensor) -> torch.Tensor:
    """:class:`SignReLU` when traced by ``torch.compile``, ``torch.relu`` otherwise."""
    if torch.compiler.is_compiling():
        return SignReLU.apply(x)
    return torch.relu(x)


class ReLU(nn.Module):
    """``nn.ReLU`` through :func:`relu` (no parameters: a drop-in in saved ``Sequential`` s)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return relu(x)
