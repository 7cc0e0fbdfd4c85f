"""What :class:`~icco_torchrl.objectives.ICCOLoss` reads from a batch of replayed sequences.

Every key is checked once, with an error that names the key and the shape it needs, into a
:class:`LossBatch` (:meth:`ICCOLoss.read_batch <icco_torchrl.objectives.ICCOLoss.read_batch>`),
and the ``L + 1`` inputs of each sequence (its ``L`` steps and the final next-step) are
assembled for the online and target networks alike (:func:`assemble`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor

if TYPE_CHECKING:
    from icco_torchrl.envs.layout import ObsLayout


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


def present_robots(layout: ObsLayout | None, state: torch.Tensor, n_agents: int) -> torch.Tensor:
    """``[..., N]``: 1.0 for the robots present in ``state [..., state_dim]``, 0.0 for absent ones
    (:meth:`~icco_torchrl.envs.layout.ObsLayout.robot_mask`: an absent robot's state token is all
    zeros); every robot is present without a layout (a fixed team, or an env without one)."""
    if layout is None:
        return state.new_ones(*state.shape[:-1], n_agents)
    return layout.robot_mask(state).to(state.dtype)


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


@dataclass(frozen=True)
class LossBatch:
    """A batch of replayed sequences ``[S, L]`` as :class:`~icco_torchrl.objectives.ICCOLoss`
    reads it: checked tensors (views of the batch), the argument of the loss's tensor part
    (:meth:`~icco_torchrl.objectives.ICCOLoss.losses`, what
    :meth:`~icco_torchrl.objectives.ICCOLoss.compile_losses` traces).

    Built by :meth:`ICCOLoss.read_batch <icco_torchrl.objectives.ICCOLoss.read_batch>`; the
    fields after ``next_mixer_inputs`` are None until :func:`assemble` sets them. ``N`` robots,
    ``F`` observation width, ``D`` the flat state width. Optional fields are None where the
    loss does not read them.

    Attributes:
        obs: observations ``[S, L, N, F]``.
        next_obs: the next observations ``[S, L, N, F]`` (under ``"next"``).
        action: the actions taken ``[S, L, N]``.
        prev_action: the previous actions ``[S, L, N]``, for agents that read them.
        hidden: the recurrent state stored at collection ``[S, L, N, H]``, for recurrent agents.
        state: the global state ``[S, L, D]`` (flattened).
        next_state: the next global state ``[S, L, D]``.
        state_shape: the state's trailing shape as the batch holds it (``(D,)`` for a flat one),
            for an agent that reads the state through its keys.
        reward: the team reward ``[S, L, 1]`` (per-robot rewards reduced).
        terminated: the team's termination ``[S, L, 1]``.
        done: the team's done ``[S, L, 1]``, read when the batch has no ``mask``.
        is_init: the steps that start an episode ``[S, L]`` (read, or ``step_count == 0``).
        mask: the steps in the sequence's episode ``[S, L]`` (the cutter's ``mask``; else
            derived by :func:`assemble`).
        z: the z the agents held ``[S, L, N, Z]`` (with a coordinator).
        z_noise: the noise of each broadcast's draw ``[S, L, N, Z]``.
        z_sent: which robots received a z ``[S, L, N, 1]`` (an adaptive broadcast).
        step_count: steps since reset ``[S, L]`` (with a coordinator).
        next_step_count: the next step's count ``[S, L]``.
        mixer_inputs: the mixer's inputs besides the agents' values, ``{key: [S, L, ...]}``.
        next_mixer_inputs: the same under ``"next"``.
        obs_seq: the ``L + 1`` observations of each sequence ``[S, L+1, N, F]`` (its steps and
            the final next-step), shared by the online and target networks.
        prev_seq: the ``L + 1`` previous actions ``[S, L+1, N]`` (None without ``prev_action``).
        state_seq: the ``L + 1`` states ``[S, L+1, D]``, when the loss reads the state.
    """

    obs: Tensor
    next_obs: Tensor
    action: Tensor
    prev_action: Tensor | None
    hidden: Tensor | None
    state: Tensor
    next_state: Tensor
    state_shape: tuple[int, ...]
    reward: Tensor
    terminated: Tensor
    done: Tensor | None
    is_init: Tensor | None
    mask: Tensor | None
    z: Tensor | None
    z_noise: Tensor | None
    z_sent: Tensor | None
    step_count: Tensor | None
    next_step_count: Tensor | None
    mixer_inputs: dict[NestedKey, Tensor]
    next_mixer_inputs: dict[NestedKey, Tensor]
    obs_seq: Tensor | None = None
    prev_seq: Tensor | None = None
    state_seq: Tensor | None = None


def read_batch(loss, td: TensorDictBase) -> LossBatch:
    """The checked inputs of ``loss`` (an :class:`~icco_torchrl.objectives.ICCOLoss`) from
    ``td [S, L]`` (time last), views of the batch (the few ops that build the sequences are
    :func:`assemble`'s), from the loss's public description of what it reads (``tensor_keys``,
    ``recurrent``, ``reads_prev_action``, ``has_coordinator``, ``threshold``,
    ``reward_reduction``, ``mixer_inputs``)."""
    _check_sequences(td)
    k, reduction = loss.tensor_keys, loss.reward_reduction
    S, L = td.batch_size
    N = get_checked(td, k.action, "[S, T, N]", ndim=3).shape[-1]
    obs_width = get_checked(td, k.observation, "[S, T, N, obs_dim]", ndim=4).shape[-1]
    obs_shape = (N, obs_width)
    hidden = _read_hidden(loss, td, N)
    states = _read_states(td, k, S, L)
    obs = get_checked(td, k.observation, "[S, T, N, obs_dim]", trailing=obs_shape)
    next_obs = get_checked(td, next_key(k.observation), "[S, T, N, obs_dim]", trailing=obs_shape)
    prev_action = get_checked(
        td, k.prev_action, "[S, T, N]", trailing=(N,), optional=not loss.reads_prev_action
    )
    reward = team_value(td, next_key(k.reward), N, "reward", reduction)
    terminated = team_value(td, next_key(k.terminated), N, "flag", reduction)
    step_count = get_checked(
        td, k.step_count, "[S, T, 1]", trailing=(1,), optional=not loss.has_coordinator
    )
    episodes = _read_episode_bounds(td, k, N, reduction, step_count)
    coordination = _read_coordination(loss, td, N, step_count)
    mixer_inputs, next_mixer_inputs = loss.mixer_inputs(td)
    return LossBatch(
        obs=obs,
        next_obs=next_obs,
        action=td.get(k.action),
        prev_action=prev_action,
        hidden=hidden,
        **states,
        reward=reward,
        terminated=terminated,
        **episodes,
        **coordination,
        mixer_inputs=mixer_inputs,
        next_mixer_inputs=next_mixer_inputs,
    )


def _check_sequences(td: TensorDictBase) -> None:
    """Refuse a batch that is not sequences ``[S, T]``."""
    if td.batch_dims != 2:
        raise ValueError(
            f"ICCOLoss expects sequences with batch [S, T] (time last), got batch "
            f"{list(td.batch_size)}"
        )


def _read_hidden(loss, td: TensorDictBase, N: int) -> Tensor | None:
    """The stored recurrent state ``[S, L, N, H]`` (None when the loss's agent is not
    recurrent and the batch has none)."""
    width = getattr(loss.agent.module, "hidden", None)
    return get_checked(
        td,
        loss.tensor_keys.rnn_hidden,
        f"[S, T, N, {width or 'hidden'}]",
        optional=not loss.recurrent,
        trailing=(N, width) if width else None,
    )


def _read_states(td: TensorDictBase, k, S: int, L: int) -> dict:
    """The :class:`LossBatch` fields of the global state: ``state`` and ``next_state``
    flattened to ``[S, L, D]``, and ``state_shape``."""
    state_expected = "[S, T, state_dim] (trailing dims are flattened)"
    raw_state = get_checked(td, k.state, state_expected)
    next_state = get_checked(td, next_key(k.state), state_expected).reshape(S, L, -1)
    return {
        "state": raw_state.reshape(S, L, -1),
        "next_state": next_state,
        "state_shape": tuple(raw_state.shape[2:]),
    }


def _read_episode_bounds(td: TensorDictBase, k, N: int, reduction: str, step_count) -> dict:
    """The :class:`LossBatch` fields that bound the episodes: ``is_init`` (read, or
    ``step_count == 0``), ``mask`` (the cutter's) and, without a mask, ``done``."""
    S, L = td.batch_size
    is_init = team_value(td, k.is_init, N, "flag", reduction, optional=True)
    if is_init is None and step_count is not None:
        is_init = step_count == 0  # derived
    mask = td.get(k.mask, None)
    done = None
    if mask is None:  # derived in assemble()
        done = team_value(td, next_key(k.done), N, "flag", reduction, optional=True)
    elif tuple(mask.shape) not in ((S, L), (S, L, 1)):
        raise ValueError(
            f"ICCOLoss: key {k.mask!r} must have shape [S, T] or [S, T, 1], got {list(mask.shape)}"
        )
    return {
        "done": done,
        "is_init": None if is_init is None else is_init.reshape(S, L).bool(),
        "mask": None if mask is None else mask.reshape(S, L).bool(),
    }


def _read_coordination(loss, td: TensorDictBase, N: int, step_count) -> dict:
    """The :class:`LossBatch` fields a coordinator needs (``z``, ``z_noise``, ``z_sent``,
    ``step_count``, ``next_step_count``); all None without one."""
    k = loss.tensor_keys
    z = z_noise = z_sent = next_step_count = None
    if loss.has_coordinator:
        z_dim = loss.agent.module.z_dim
        z_shape = (N, z_dim)
        z = get_checked(td, k.z, f"[S, T, N, {z_dim}]", trailing=z_shape)
        z_noise = get_checked(td, k.z_noise, f"[S, T, N, {z_dim}]", trailing=z_shape)
        if loss.threshold > 0:
            z_sent = get_checked(td, k.z_sent, "[S, T, N, 1]", trailing=(N, 1)).bool()
        step_count = step_count.squeeze(-1)
        next_step_count = get_checked(
            td, next_key(k.step_count), "[S, T, 1]", trailing=(1,)
        ).squeeze(-1)
    else:
        step_count = None
    return {
        "z": z,
        "z_noise": z_noise,
        "z_sent": z_sent,
        "step_count": step_count,
        "next_step_count": next_step_count,
    }


def assemble(batch: LossBatch, reads_state: bool) -> LossBatch:
    """``batch`` with the ``L + 1`` inputs of each sequence (its ``L`` steps and the final
    next-step), shared by the online and the target networks, and the episode mask where the
    batch has none: the tensor part of reading a batch (what a compiled update traces)."""
    mask = batch.mask
    if mask is None:  # steps after an episode end (done) or a new start (is_init)
        ended = batch.terminated if batch.done is None else batch.done
        mask = episode_mask(ended, batch.is_init)
    prev_seq = state_seq = None
    if batch.prev_action is not None:
        prev_seq = torch.cat([batch.prev_action[:, :1], batch.action], 1)  # [S, L+1, N]
    if reads_state:
        state_seq = torch.cat([batch.state[:, :1], batch.next_state], 1)  # [S, L+1, D]
    return dataclasses.replace(
        batch,
        mask=mask,
        obs_seq=torch.cat([batch.obs[:, :1], batch.next_obs], 1),  # [S, L+1, N, F]
        prev_seq=prev_seq,
        state_seq=state_seq,
    )
