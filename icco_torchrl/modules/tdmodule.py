"""A TensorDictModule for networks that return plain tensors, with a cheaper write-back.

tensordict 0.14's ``TensorDictModule`` passes every output through ``TensorDict.from_any``,
which calls ``importlib.util.find_spec("pandas")`` each time (a sys.path scan, ~50 us here
when pandas is not installed). The collection policy writes 3-7 outputs per env step, so
this was ~5% of a QMIX collection step. Tensors are written directly; anything else
(dicts, tensordicts, ``tensordict_out``, non-inplace modules) takes the parent's path.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule


class TensorModule(TensorDictModule):
    """``TensorDictModule`` that writes tensor outputs with ``td.set`` (same keys, same result)."""

    def _write_to_tensordict(self, tensordict, tensors, tensordict_out=None, out_keys=None):
        keys = self.out_keys_source if out_keys is None else out_keys
        if (
            tensordict_out is not None
            or self.inplace is not True
            or len(keys) != len(tensors)
            or not all(isinstance(t, torch.Tensor) for t in tensors)
        ):
            return super()._write_to_tensordict(tensordict, tensors, tensordict_out, out_keys)
        for key, tensor in zip(keys, tensors):
            if key != "_":
                tensordict.set(key, tensor)
        return tensordict
