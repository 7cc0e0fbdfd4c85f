"""Cut the collector's stream of ``[B, L]`` batches into segments ``[S, T]`` for replay.

A segment starts where ``step_count % T == 0`` (a coordinator broadcast step, COPA's layout)
and spans the next T transitions; its bootstrap state is the last step's ``("next", ...)``
entry. Batches need not align with episodes or with T: the last ``T - 1`` steps of each
batch are kept and prepended to the next one, so every broadcast step yields exactly one
segment. Steps after an episode's end inside a segment get ``mask = False``.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase


class SegmentCutter:
    """Stateful cutter: call it on each collector batch (time as the last batch dim)."""

    def __init__(
        self, length: int, step_key="step_count", done_key=("next", "done"), mask_key="mask"
    ):
        if length < 1:
            raise ValueError(f"segment length must be >= 1, got {length}")
        self.length = length
        self.step_key, self.done_key, self.mask_key = step_key, done_key, mask_key
        self._tail: TensorDictBase | None = None

    def __call__(self, batch: TensorDictBase) -> TensorDictBase:
        if batch.batch_dims != 2:
            raise ValueError(
                f"expected a [num_envs, time] batch, got batch size {list(batch.batch_size)}"
            )
        data = batch if self._tail is None else torch.cat([self._tail, batch], 1)
        T, span = self.length, data.shape[1]
        keep_from = max(span - T + 1, 0)  # windows starting here are incomplete
        starts = data.get(self.step_key).reshape(data.shape) % T == 0
        starts[:, keep_from:] = False  # wait for the next batch
        env_idx, t_idx = starts.nonzero(as_tuple=True)
        steps = t_idx.unsqueeze(1) + torch.arange(T, device=t_idx.device)
        segments = data[env_idx.unsqueeze(1), steps]  # [S, T]
        done = segments.get(self.done_key).reshape(segments.shape)
        ended_before = (
            torch.cumsum(done.long(), 1) - done.long()
        )  # episode ends strictly before step k
        segments.set(self.mask_key, ended_before == 0)
        self._tail = data[:, keep_from:] if T > 1 else None
        return segments
