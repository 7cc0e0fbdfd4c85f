"""A one-layer GRU with ``nn.GRU``'s parameters that ``torch.compile`` can trace.

Dynamo refuses to trace ``nn.GRU`` in torch 2.13 ("Attempted to wrap RNN, GRU, or LSTM", raised
in ``torch/_dynamo/variables/builder.py`` unless ``torch._dynamo.config.allow_rnn``): touching one
sends the whole function to eager (``tests/test_fast_update.py`` compiles this one). This module
holds the same four parameters under the same names, shapes and initialisation as a one-layer
``nn.GRU(batch_first=True)``, so checkpoints and seeded initial weights are unchanged. In eager
mode a sequence runs through the same ATen kernel as ``nn.GRU`` (``torch.gru``); under
compilation it is written from its gates: one input projection for every step, then per step
one ``h @ W_hh`` and the gate arithmetic, which Inductor fuses into a few kernels.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F


class GRU(nn.Module):
    """``GRU(input_size, hidden_size)``: ``forward(x [B, L, I], h0 [B, H]) -> (out [B, L, H],
    h_last [B, H])``; ``step(x [B, I], h [B, H]) -> h' [B, H]``.

    Examples:
        >>> import torch
        >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
        <torch._C.Generator object at ...>
        >>> gru = GRU(8, 4)
        >>> ref = torch.nn.GRU(8, 4, batch_first=True)
        >>> _ = ref.load_state_dict(gru.state_dict())
        >>> x, h0 = torch.randn(2, 5, 8), torch.randn(2, 4)
        >>> out, h = gru(x, h0)
        >>> torch.allclose(out, ref(x, h0.unsqueeze(0))[0], atol=1e-6)
        True
        >>> torch.allclose(gru.unrolled(x, h0)[0], out, atol=1e-6)
        True
    """

    def __init__(self, input_size: int, hidden_size: int):
        super().__init__()
        self.input_size, self.hidden_size = input_size, hidden_size
        H = hidden_size
        # nn.GRU's names and order (the order is the order of the random init below).
        self.weight_ih_l0 = nn.Parameter(torch.empty(3 * H, input_size))
        self.weight_hh_l0 = nn.Parameter(torch.empty(3 * H, H))
        self.bias_ih_l0 = nn.Parameter(torch.empty(3 * H))
        self.bias_hh_l0 = nn.Parameter(torch.empty(3 * H))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """``nn.GRU``'s: every parameter uniform in ``±1/sqrt(hidden_size)``."""
        bound = 1.0 / math.sqrt(self.hidden_size)
        for weight in self.parameters():
            nn.init.uniform_(weight, -bound, bound)

    def _weights(self):
        return self.weight_ih_l0, self.weight_hh_l0, self.bias_ih_l0, self.bias_hh_l0

    def step(self, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """One step for ``[B, I]`` inputs from ``h [B, H]``."""
        if torch.compiler.is_compiling():
            return self._cell(F.linear(x, self.weight_ih_l0, self.bias_ih_l0), h)
        return torch.gru_cell(x, h, *self._weights())

    def forward(self, x: torch.Tensor, h0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if torch.compiler.is_compiling():
            return self.unrolled(x, h0)
        out, h = torch.gru(
            x,
            h0.unsqueeze(0).contiguous(),
            self._weights(),
            True,
            1,
            0.0,
            self.training,
            False,
            True,
        )
        return out, h.squeeze(0)

    def unrolled(self, x: torch.Tensor, h0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The sequence from the gates (what a compiled caller runs); same values as ``forward``."""
        gi = F.linear(x, self.weight_ih_l0, self.bias_ih_l0)  # every step's input part at once
        h, out = h0, []
        for t in range(x.shape[1]):
            h = self._cell(gi[:, t], h)
            out.append(h)
        return torch.stack(out, 1), h

    def _cell(self, gi: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        i_r, i_z, i_n = gi.chunk(3, -1)
        h_r, h_z, h_n = F.linear(h, self.weight_hh_l0, self.bias_hh_l0).chunk(3, -1)
        r = torch.sigmoid(i_r + h_r)
        z = torch.sigmoid(i_z + h_z)
        n = torch.tanh(i_n + r * h_n)
        return n + z * (h - n)
