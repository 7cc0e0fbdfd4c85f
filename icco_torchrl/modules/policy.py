"""The collection/evaluation policy and the env primer that carries its recurrent state.

Policy = [coordinator] -> agent -> greedy Q (``QValueModule``) -> epsilon-greedy
(``EGreedyModule``, active only under RANDOM exploration) -> record the action as next step's
``prev_action``. Under ``ExplorationType.DETERMINISTIC`` the same policy is greedy and the
coordinator emits its mean: that is the evaluation policy.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import Compose, InitTracker, StepCounter, TensorDictPrimer
from torchrl.envs.utils import ExplorationType
from torchrl.modules import EGreedyModule, QValueModule

from icco_torchrl.modules.tdmodule import TensorModule


def make_primer(
    n_agents: int,
    hidden: int,
    z_dim: int = 0,
    device="cpu",
    group: str = "agents",
    *,
    n_actions: int,
) -> TensorDictPrimer:
    """Zeros at reset for the per-robot GRU state, previous action (one of the env's ``n_actions``)
    and (with a coordinator) z, under ``group``."""
    entries = dict(
        rnn_hidden=Unbounded((n_agents, hidden), device=device),
        prev_action=Categorical(n_actions, (n_agents,), dtype=torch.int64, device=device),
    )
    if z_dim:
        entries.update(
            z=Unbounded((n_agents, z_dim), device=device),
            z_noise=Unbounded((n_agents, z_dim), device=device),
        )
    return TensorDictPrimer(
        Composite({group: Composite(entries, shape=(n_agents,), device=device)}, device=device),
        expand_specs=True,
    )


def recurrent_transforms(env, hidden: int, z_dim: int = 0, group: str = "agents") -> Compose:
    """What any TorchRL multi-agent env needs for ICCO's recurrent agents and coordinator:
    ``StepCounter`` (broadcast steps), ``InitTracker`` (episode starts) and :func:`make_primer`,
    sized from ``env``'s specs (agents and actions of ``(group, "action")``).

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from icco_torchrl.envs import ResourceCollectionEnv
        >>> base = ResourceCollectionEnv(num_envs=2)
        >>> env = TransformedEnv(base, recurrent_transforms(base, hidden=16, z_dim=4))
        >>> env.reset()["agents", "rnn_hidden"].shape
        torch.Size([2, 3, 16])
    """
    action = env.full_action_spec[group, "action"]
    n_agents, n_actions = action.shape[-1], int(action.space.n)
    primer = make_primer(n_agents, hidden, z_dim, env.device, group, n_actions=n_actions)
    return Compose(StepCounter(), InitTracker(), primer)


class GuidedEGreedyModule(EGreedyModule):
    """Epsilon-greedy whose exploratory actions come from a ``guide`` policy (``td -> td`` writing
    the same action key, e.g. a scripted reference policy) instead of uniform draws: with
    probability ``eps`` each agent takes the guide's action. Off-policy Q-learning learns from any
    behaviour, so the replay then holds the task events a random walk rarely meets. Greedy
    (DETERMINISTIC) rollouts never call the guide."""

    def __init__(self, guide, **kwargs):
        super().__init__(**kwargs)
        self.__dict__["guide"] = guide  # not a submodule: no parameters, not in the state dict

    def forward(self, tensordict):
        from torchrl.envs.utils import exploration_type  # the context's current type

        if exploration_type() not in (ExplorationType.RANDOM, None):
            return tensordict
        action = tensordict.get(self.action_key)
        guided = self.guide(tensordict.exclude(self.action_key)).get(self.action_key)
        explore = torch.rand(action.shape, device=action.device) < self.eps
        tensordict.set(self.action_key, torch.where(explore, guided.to(action.dtype), action))
        return tensordict


def make_policy(
    agent: TensorDictModule,
    action_spec,
    coordinator: TensorDictModule | None = None,
    *,
    eps_init: float = 1.0,
    eps_end: float = 0.05,
    annealing_num_steps: int = 1,
    group: str = "agents",
    action_name: str = "action",
    guide=None,
) -> TensorDictSequential:
    """``action_spec``: the env's unbatched full action spec (``env.full_action_spec_unbatched``).

    Keys live under ``group``: ``action_value``, ``action_name``, ``chosen_action_value`` and the
    next step's ``prev_action``. The agent must write ``(group, "action_value")``.
    """
    action_key = (group, action_name)
    q_value = QValueModule(
        action_value_key=(group, "action_value"),
        out_keys=[action_key, (group, "action_value"), (group, "chosen_action_value")],
        spec=None,
        action_space="categorical",
    )
    kwargs = dict(
        spec=action_spec,
        eps_init=eps_init,
        eps_end=eps_end,
        annealing_num_steps=annealing_num_steps,
        action_key=action_key,
    )
    explore = EGreedyModule(**kwargs) if guide is None else GuidedEGreedyModule(guide, **kwargs)
    if (
        action_spec.device is not None
    ):  # its eps buffers start on the CPU; it refuses actions elsewhere
        explore = explore.to(action_spec.device)
    remember = TensorModule(
        nn.Identity(), in_keys=[action_key], out_keys=[("next", group, "prev_action")]
    )
    modules = ([coordinator] if coordinator is not None else []) + [
        agent,
        q_value,
        explore,
        remember,
    ]
    return TensorDictSequential(*modules)


def exploration_module(policy: TensorDictSequential) -> EGreedyModule:
    """The policy's EGreedyModule (its ``eps`` buffer is the exploration rate)."""
    return next(m for m in policy.module if isinstance(m, EGreedyModule))
