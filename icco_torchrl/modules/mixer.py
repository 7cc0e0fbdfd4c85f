"""QMIX mixers: monotone in every Q^i, conditioned on the global state.

``qmix`` is TorchRL's ``QMixer``: hypernetworks on the flat state, of a width fixed by the team
size. ``attention`` (:class:`TokenMixer`) is the same two-layer monotone mixing with the
hypernetworks read off the state *tokens*, so one set of weights mixes any team up to
``n_agents`` (COPA's attention hypernetwork, in the form of a masked QMIX): robot i's first-layer
weights come from its own token after one attention read of every present token, the biases and
the second layer from the present robots' pooled features, and an absent robot (an all-zero
state token, :meth:`~icco_torchrl.envs.layout.ObsLayout.robot_mask`) is left out: its Q is never
read.

COPA instead feeds coach encoder features to the hypernetworks (so the TD loss also trains the
coach encoder); here the coordinator is trained by the TD loss through z and by the CE term,
which is what the ICCO paper describes. Swap in any ``torchrl.modules.Mixer`` if you need more.

Sizes are declared once: :class:`TokenMixer` takes ``embed_dim`` and ``hidden`` as required
keyword arguments; :func:`make_mixer` holds the mixing width's default (``embed_dim=32``, QMIX's)
and takes ``hidden`` (``method.hidden``) for ``kind="attention"``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import QMixer

from icco_torchrl.modules.activations import ReLU
from icco_torchrl.modules.encoders import EntityAttentionEncoder

if TYPE_CHECKING:
    from icco_torchrl.envs.layout import ObsLayout

MIXERS = ("qmix", "attention")


class TokenMixer(nn.Module):
    """Monotone mixing of ``q [..., N, 1]`` on the state tokens of ``layout``: ``[..., 1]``.

    ``Q_tot = w2 . elu(sum_i w1_i q_i + b1) + V`` over the present robots (an absent robot's Q is
    read as 0, whatever it holds), with ``w1_i = |W h_i|``, ``w2 = |W c|``, ``b1`` and ``V``
    from ``c``. ``h_i`` is robot i's token after a single-head attention read of every typed
    state token (absent robots left out), ``c`` the mean of ``h_i`` over the present robots.
    ``dQ_tot / dq_i >= 0`` for every present robot, 0 for an absent one; no parameter depends on
    ``n_agents``.
    """

    def __init__(self, layout: ObsLayout, *, embed_dim: int, hidden: int):
        super().__init__()
        if embed_dim < 1 or hidden < 1:
            raise ValueError(f"embed_dim and hidden must be >= 1, got {embed_dim}, {hidden}")
        self.layout, self.embed_dim = layout, embed_dim
        D, T = layout.state_token_dim, layout.state_tokens
        self.encoder = EntityAttentionEncoder(D, T, D, hidden)
        self.hyper_w_1 = nn.Linear(hidden, embed_dim)
        self.hyper_b_1 = nn.Linear(hidden, embed_dim)
        self.hyper_w_final = nn.Linear(hidden, embed_dim)
        self.V = nn.Sequential(nn.Linear(hidden, embed_dim), ReLU(), nn.Linear(embed_dim, 1))

    def forward(self, chosen_action_value: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        L = self.layout
        N = L.n_agents
        lead = chosen_action_value.shape[:-2]
        if chosen_action_value.shape[-2:] != (N, 1) or state.shape[-1] != L.state_dim:
            raise ValueError(
                f"TokenMixer mixes q [..., {N}, 1] on a state [..., {L.state_dim}], got "
                f"{list(chosen_action_value.shape)} and {list(state.shape)}"
            )
        tokens = L.tokens(state)  # [..., T, D]
        present = L.robot_mask(state)  # [..., N]
        typed = L.typed(state)  # [..., T]: absent robots' tokens are not read
        every = state.unsqueeze(-2).expand(*lead, N, state.shape[-1])
        h = self.encoder(torch.cat([tokens[..., :N, :], every], -1), typed.unsqueeze(-2))
        m = present.to(h.dtype).unsqueeze(-1)  # [..., N, 1]
        context = (m * h).sum(-2) / m.sum(-2).clamp_min(1.0)  # [..., hidden]
        w1 = self.hyper_w_1(h).abs()  # [..., N, E]
        q = torch.where(present.unsqueeze(-1), chosen_action_value, 0.0)  # absent: never read
        hidden = nn.functional.elu((w1 * q).sum(-2) + self.hyper_b_1(context))  # [..., E]
        w_final = self.hyper_w_final(context).abs()
        return (hidden * w_final).sum(-1, keepdim=True) + self.V(context)


def make_mixer(
    state_dim: int,
    n_agents: int,
    *,
    kind: str,
    embed_dim: int = 32,
    layout: ObsLayout | None = None,
    hidden: int | None = None,
    device="cpu",
    local_value_key=("agents", "chosen_action_value"),
    state_key="state",
    global_value_key="chosen_action_value",
) -> TensorDictModule:
    """in: ``local_value_key [.., N, 1]``, ``state_key``; out: ``global_value_key [.., 1]``.

    ``kind``: ``"qmix"`` (TorchRL's ``QMixer`` on the flat state, one team size) or
    ``"attention"`` (:class:`TokenMixer`, any team up to ``n_agents``; needs the ``layout`` and
    its width ``hidden``). ``embed_dim``: the mixing width of either.
    """
    if kind not in MIXERS:
        raise ValueError(f"mixer must be one of {MIXERS}, got {kind!r}")
    if kind == "attention":
        if layout is None or (layout.state_dim, layout.n_agents) != (state_dim, n_agents):
            raise ValueError("mixer='attention' reads state tokens: it needs the env's layout")
        if hidden is None:
            raise ValueError("mixer='attention' needs its width: hidden")
        net = TokenMixer(layout, embed_dim=embed_dim, hidden=hidden).to(device)
    else:
        net = QMixer(
            state_shape=(state_dim,), mixing_embed_dim=embed_dim, n_agents=n_agents, device=device
        )
        net.V[1] = ReLU()  # the compiled update's ReLU (modules/activations.py), same function
    return TensorDictModule(net, in_keys=[local_value_key, state_key], out_keys=[global_value_key])
