"""QMIX mixer: monotone in every Q^i, conditioned on the global state (TorchRL's ``QMixer``).

COPA instead feeds coach encoder features to the hypernetworks (so the TD loss also trains the
coach encoder); here the coordinator is trained by the TD loss through z and by the CE term,
which is what the ICCO paper describes. Swap in any ``torchrl.modules.Mixer`` if you need more.
"""

from __future__ import annotations

from tensordict.nn import TensorDictModule
from torchrl.modules import QMixer


def make_mixer(
    state_dim: int,
    n_agents: int,
    *,
    embed_dim: int = 32,
    device="cpu",
    local_value_key=("agents", "chosen_action_value"),
    state_key="state",
    global_value_key="chosen_action_value",
) -> TensorDictModule:
    """in: ``local_value_key [.., N, 1]``, ``state_key``; out: ``global_value_key [.., 1]``."""
    return TensorDictModule(
        QMixer(
            state_shape=(state_dim,), mixing_embed_dim=embed_dim, n_agents=n_agents, device=device
        ),
        in_keys=[local_value_key, state_key],
        out_keys=[global_value_key],
    )
