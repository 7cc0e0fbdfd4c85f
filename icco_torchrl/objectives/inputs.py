"""What :class:`~icco_torchrl.objectives.ICCOLoss` reads from a batch of replayed sequences.

Every key is checked once, with an error that names the key and the shape it needs, and the
``L + 1`` inputs of each sequence (its ``L`` steps and the final next-step) are assembled for
the online and target networks alike.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

from icco_torchrl.modules.relative import robot_mask


def next_key(key: NestedKey) -> tuple:
    """``key`` under ``"next"``."""
    return ("next", *key) if isinstance(key, tuple) else ("next", key)


def get_checked(td, key, expected: str, ndim=None, trailing=None, optional=False):
    """``td[key]`` with its shape checked; a missing or ill-shaped entry fails naming both."""
    value = td.get(key, None)
    if value is None:
        if optional:
            return None
        present = sorted(map(str, td.keys(True, True)))[:20]
        raise KeyError(f"ICCOLoss needs key {key!r} with shape {expected}; present: {present}")
    bad_ndim = ndim is not None and value.dim() != ndim
    if bad_ndim or (trailing is not None and tuple(value.shape[2:]) != trailing):
        raise ValueError(
            f"ICCOLoss: key {key!r} must have shape {expected}, got {list(value.shape)}"
        )
    return value


def team_value(td, key, N: int, kind: str, reduction: str, optional=False):
    """A team quantity ``[S, L, 1]`` from a team ``[S, L, 1]`` or per-agent ``[S, L, N, 1]`` entry:
    rewards reduced by ``reduction``, flags true when every agent's is."""
    expected = "[S, T, 1] (or per agent [S, T, N, 1])"
    value = get_checked(td, key, expected, optional=optional)
    if value is None:
        return None
    if tuple(value.shape[2:]) == (N, 1):
        if kind == "reward":
            return value.mean(-2) if reduction == "mean" else value.sum(-2)
        return value.all(-2)  # a team's episode ends when every agent's does
    if tuple(value.shape[2:]) != (1,):
        raise ValueError(
            f"ICCOLoss: key {key!r} must have shape {expected}, got {list(value.shape)}"
        )
    return value


def present_robots(loss, state: torch.Tensor, n_agents: int) -> torch.Tensor:
    """``[..., N]``: 1.0 for the robots present in ``state [..., state_dim]``, 0.0 for absent ones
    (an absent robot's state token is all zeros: :func:`~icco_torchrl.modules.relative.robot_mask`),
    read with the layout of the loss's coordinator, mixer or posterior (the first that has one);
    every robot is present when none has (a fixed team, or an env without a layout)."""
    for name in ("coordinator", "mixer", "posterior"):
        layout = getattr(getattr(getattr(loss, name, None), "module", None), "layout", None)
        if layout is not None:
            return robot_mask(state, layout).to(state.dtype)
    return state.new_ones(*state.shape[:-1], n_agents)


def episode_mask(done: torch.Tensor, is_init: torch.Tensor | None) -> torch.Tensor:
    """``[S, L]``: False from the step after an episode end (``done [S, L, 1]``) or from a step that
    starts a new episode (``is_init [S, L]``, the first step excepted) to the sequence's end."""
    ended = done.reshape(done.shape[0], -1).long()
    valid = (torch.cumsum(ended, 1) - ended) == 0
    if is_init is not None:
        started = is_init.long().clone()
        started[:, 0] = 0
        valid &= torch.cumsum(started, 1) == 0
    return valid


def read_sequences(loss, td: TensorDictBase) -> dict:
    """The checked inputs of ``loss`` from ``td [S, L]`` (time last), as a dict of tensors (views
    of the batch: the few ops that build the sequences are :func:`assemble`'s)."""
    if td.batch_dims != 2:
        raise ValueError(
            f"ICCOLoss expects sequences with batch [S, T] (time last), got batch "
            f"{list(td.batch_size)}"
        )
    k, net = loss.tensor_keys, loss.agent.module
    S, L = td.batch_size
    N = get_checked(td, k.action, "[S, T, N]", ndim=3).shape[-1]
    obs_width = get_checked(td, k.observation, "[S, T, N, obs_dim]", ndim=4).shape[-1]
    obs_shape = (N, obs_width)
    recurrent = loss._sequence_agent or loss._reads(k.rnn_hidden)
    width = getattr(net, "hidden", None)
    hidden = get_checked(
        td,
        k.rnn_hidden,
        f"[S, T, N, {width or 'hidden'}]",
        optional=not recurrent,
        trailing=(N, width) if width else None,
    )
    state_shape = "[S, T, state_dim] (trailing dims are flattened)"
    state = get_checked(td, k.state, state_shape).reshape(S, L, -1)
    next_state = get_checked(td, next_key(k.state), state_shape).reshape(S, L, -1)
    reads_prev = loss._sequence_agent or loss._reads(k.prev_action)
    x = dict(
        td=td,
        obs=get_checked(td, k.observation, "[S, T, N, obs_dim]", trailing=obs_shape),
        next_obs=get_checked(td, next_key(k.observation), "[S, T, N, obs_dim]", trailing=obs_shape),
        action=td.get(k.action),
        prev_action=get_checked(
            td, k.prev_action, "[S, T, N]", trailing=(N,), optional=not reads_prev
        ),
        hidden=hidden,
        state=state,
        next_state=next_state,
        reward=team_value(td, next_key(k.reward), N, "reward", loss.reward_reduction),
        terminated=team_value(td, next_key(k.terminated), N, "flag", loss.reward_reduction),
    )
    x["own_reward"] = None
    if loss.channels > 1:  # per-robot reward channels: each robot's own terms [S, L, N]
        own = get_checked(td, next_key(k.own_reward), "[S, T, N, 1]", trailing=(N, 1))
        x["own_reward"] = own.squeeze(-1)
    step_count = get_checked(
        td, k.step_count, "[S, T, 1]", trailing=(1,), optional=not loss.has_coordinator
    )
    is_init = team_value(td, k.is_init, N, "flag", loss.reward_reduction, optional=True)
    if is_init is None and step_count is not None:
        is_init = step_count == 0  # derived
    x["is_init"] = None if is_init is None else is_init.reshape(S, L).bool()
    mask = td.get(k.mask, None)
    x["done"] = None
    if mask is None:  # derived in assemble()
        x["done"] = team_value(
            td, next_key(k.done), N, "flag", loss.reward_reduction, optional=True
        )
    elif tuple(mask.shape) not in ((S, L), (S, L, 1)):
        raise ValueError(
            f"ICCOLoss: key {k.mask!r} must have shape [S, T] or [S, T, 1], got {list(mask.shape)}"
        )
    x["mask"] = None if mask is None else mask.reshape(S, L).bool()
    if loss.has_coordinator:
        z_shape = (N, net.z_dim)
        x["z"] = get_checked(td, k.z, f"[S, T, N, {net.z_dim}]", trailing=z_shape)
        x["z_noise"] = get_checked(td, k.z_noise, f"[S, T, N, {net.z_dim}]", trailing=z_shape)
        x["z_sent"] = None
        if loss.threshold > 0:
            sent = get_checked(td, k.z_sent, "[S, T, N, 1]", trailing=(N, 1))
            x["z_sent"] = sent.bool()
        x["step_count"] = step_count.squeeze(-1)
        x["next_step_count"] = get_checked(
            td, next_key(k.step_count), "[S, T, 1]", trailing=(1,)
        ).squeeze(-1)
    return x


def assemble(x: dict, reads_state: bool) -> dict:
    """``x`` with the ``L + 1`` inputs of each sequence (its ``L`` steps and the final
    next-step), shared by the online and the target networks, and the episode mask where the
    batch has none: the tensor part of reading a batch (what a compiled update traces)."""
    x = dict(x)
    if x["mask"] is None:  # steps after an episode end (done) or a new start (is_init)
        ended = x["terminated"] if x["done"] is None else x["done"]
        x["mask"] = episode_mask(ended, x["is_init"])
    x["obs_seq"] = torch.cat([x["obs"][:, :1], x["next_obs"]], 1)  # [S, L+1, N, F]
    if x["prev_action"] is not None:
        x["prev_seq"] = torch.cat([x["prev_action"][:, :1], x["action"]], 1)
    else:
        x["prev_seq"] = None
    x["state_seq"] = torch.cat([x["state"][:, :1], x["next_state"]], 1) if reads_state else None
    return x
